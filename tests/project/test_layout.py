"""The project's packages are the ones imported, and imports go one way."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("package", ["tissue", "envs", "agents", "assets"])
def test_generic_package_names_resolve_to_this_repository(package: str) -> None:
    # "envs" and friends are generic names (a PyPI package called envs exists).
    module = __import__(package)
    assert Path(module.__file__).resolve().parent == ROOT / package


def test_tissue_imports_no_robot_or_learning_stack() -> None:
    code = (
        "import sys, tissue, tissue.sim.simulator, tissue.mesh.phantom, tissue.mesh.io;"
        "import tissue.sim.solvers;"
        "heavy = ('mujoco', 'gymnasium', 'torch', 'stable_baselines3');"
        "bad = [m for m in heavy if m in sys.modules];"
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def _imports(package: str) -> list[tuple[str, str, tuple[str, ...]]]:
    """(file, module imported, names imported) for every import in ``package``'s sources."""
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                found += [(str(path), alias.name, ()) for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = tuple(alias.name for alias in node.names)
                found.append((str(path), node.module, names))
    return found


def test_imports_go_one_way_and_envs_use_only_the_front_door() -> None:
    """agents -> envs -> tissue: tissue imports neither, envs not agents; envs reaches tissue
    only through ``import tissue`` / ``from tissue import <public name>``."""
    import tissue

    public = set(tissue.__all__)
    for path, module, _ in _imports("tissue"):
        assert module.split(".")[0] not in ("envs", "agents"), (path, module)
    for path, module, names in _imports("envs"):
        top = module.split(".")[0]
        assert top != "agents", (path, module)
        if top == "tissue":
            assert module == "tissue", f"{path} imports {module}: use tissue's public names"
            assert set(names) <= public, (path, sorted(set(names) - public))


def test_agents_reach_the_tissue_through_its_front_door_and_the_lab_surface() -> None:
    """agents/ imports ``tissue`` and ``tissue.lab`` only, and only names in their
    ``__all__``: the lab's needs beyond the front door are one documented surface."""
    import tissue
    import tissue.lab

    surfaces = {"tissue": set(tissue.__all__), "tissue.lab": set(tissue.lab.__all__)}
    for path, module, names in _imports("agents"):
        if module.split(".")[0] != "tissue":
            continue
        assert module in surfaces, f"{path} imports {module}: use tissue or tissue.lab"
        unknown = set(names) - surfaces[module]
        assert not unknown, f"{path} imports {sorted(unknown)} from {module}, not in its __all__"


def _private_crossings(package: str) -> list[str]:
    """Each place in ``package`` where a module uses another project module's ``_private``
    name: imported by name, or read as an attribute of an imported module."""
    found = []
    for path in sorted((ROOT / package).rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        modules: dict[str, str] = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                if node.module.split(".")[0] not in ("tissue", "envs", "agents"):
                    continue
                for alias in node.names:
                    if alias.name.startswith("_"):
                        found.append(f"{path}: {alias.name} from {node.module}")
                    modules[alias.asname or alias.name] = f"{node.module}.{alias.name}"
            elif isinstance(node, ast.Import):
                for alias in node.names:
                    if alias.name.split(".")[0] in ("tissue", "envs", "agents"):
                        modules[(alias.asname or alias.name).split(".")[0]] = alias.name
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
                and isinstance(node.value, ast.Name)
                and node.value.id in modules
            ):
                found.append(f"{path}: {node.value.id}.{node.attr}")
    return found


@pytest.mark.parametrize("package", ["tissue", "envs", "agents"])
def test_no_private_name_crosses_a_module_boundary(package: str) -> None:
    """A ``_name`` is its module's own: what another module needs has a public name (a
    package's ``__init__`` re-exports it where the package shares it)."""
    assert _private_crossings(package) == []


def test_the_private_name_check_sees_one(tmp_path, monkeypatch) -> None:
    layout = sys.modules[__name__]
    fake = tmp_path / "agents"
    fake.mkdir()
    (fake / "bad.py").write_text(
        "from tissue.sim.solvers import _hidden\nimport tissue.profile\nx = tissue._secret\n"
    )
    monkeypatch.setattr(layout, "ROOT", tmp_path)
    found = layout._private_crossings("agents")
    assert len(found) == 2 and "_hidden" in found[0] and "tissue._secret" in found[1]


def test_the_import_check_sees_a_private_import(tmp_path, monkeypatch) -> None:
    """The check above fails on an envs module reaching into tissue's internals."""
    layout = sys.modules[__name__]
    fake = tmp_path / "envs"
    fake.mkdir()
    (fake / "bad.py").write_text("from tissue.sim.simulator import TissueSimulator\n")
    monkeypatch.setattr(layout, "ROOT", tmp_path)
    (tmp_path / "tissue").mkdir()
    with pytest.raises(AssertionError, match="public names"):
        layout.test_imports_go_one_way_and_envs_use_only_the_front_door()


#: tissue's layers, lowest first (docs/architecture.md): a module imports only from its own
#: layer or lower ones, at module level or inside a function.
TISSUE_LAYERS = (
    (
        "tissue.errors",
        "tissue.choices",
        "tissue.status",
        "tissue.step_result",
        "tissue.threads",
        "tissue.profile",
    ),
    ("tissue.mesh", "tissue.probe"),
    ("tissue.fem",),
    ("tissue.sim",),
    ("tissue.contact",),
    ("tissue.pbd",),
    (
        "tissue.spec",
        "tissue.model",
        "tissue.lesions",
        "tissue.surface_mesh",
        "tissue.lab",
        "tissue",
    ),
)


def _tissue_unit(module: str) -> str:
    """``tissue.<sub-package or module>``, or ``tissue`` itself."""
    return ".".join(module.split(".")[:2])


def _layer(unit: str) -> int:
    for rank, units in enumerate(TISSUE_LAYERS):
        if unit in units:
            return rank
    raise AssertionError(f"{unit} is in no layer of TISSUE_LAYERS: add it (and to the docs)")


def test_tissue_layers_import_only_downwards() -> None:
    for path, module, _ in _imports("tissue"):
        if module.split(".")[0] != "tissue":
            continue
        relative = Path(path).relative_to(ROOT).with_suffix("").parts
        importer = "tissue" if relative == ("tissue", "__init__") else ".".join(relative[:2])
        imported = _tissue_unit(module)
        assert _layer(imported) <= _layer(importer), (
            f"{path} imports {module}: {imported} lies above {importer} in TISSUE_LAYERS"
        )


def test_the_architecture_page_names_every_package() -> None:
    """docs/architecture.md says what every package and sub-package owns, and names none
    that does not exist."""
    import re

    page = (ROOT / "docs" / "architecture.md").read_text()
    named = set(re.findall(r"`((?:tissue|envs|agents)(?:\.\w+)*)`", page))
    packages = {
        ".".join(init.parent.relative_to(ROOT).parts)
        for top in ("tissue", "envs", "agents")
        for init in (ROOT / top).rglob("__init__.py")
    }
    assert packages - named == set(), "packages the architecture page does not describe"
    for name in named:
        path = ROOT.joinpath(*name.split("."))
        assert path.is_dir() or path.with_suffix(".py").is_file(), f"{name} does not exist"
    for units in TISSUE_LAYERS:
        for unit in units:
            assert unit == "tissue" or f"`{unit}`" in page, f"{unit} is not on the page"


def test_the_layer_check_sees_an_upward_import(tmp_path, monkeypatch) -> None:
    """The layer check fails on a mesh module that reaches up into contact, even lazily."""
    layout = sys.modules[__name__]
    fake = tmp_path / "tissue" / "mesh"
    fake.mkdir(parents=True)
    (fake / "bad.py").write_text("def f():\n    from tissue.contact import registry\n")
    monkeypatch.setattr(layout, "ROOT", tmp_path)
    with pytest.raises(AssertionError, match="lies above"):
        layout.test_tissue_layers_import_only_downwards()


def test_only_tissue_profile_compares_profiles() -> None:
    """What a profile decides is written in tissue/profile.py; the layers below read its
    choices by name (profile_choices(mode).newton), never compare profiles themselves."""
    import re

    comparison = re.compile(
        r"(\bis\b|\bis not\b|==|!=)\s*Profile\.|\b(mode|profile)\s*(==|!=|\bis\b)\s"
    )
    for path in sorted((ROOT / "tissue").rglob("*.py")):
        if path.name == "profile.py" and path.parent.name == "tissue":
            continue
        for number, line in enumerate(path.read_text().splitlines(), start=1):
            assert not comparison.search(line), f"{path}:{number} compares profiles: {line}"


def _module_graph() -> dict[str, set[str]]:
    """Every module of tissue, envs and agents -> the modules of the three it imports (any
    import statement: at module level, inside a function, under TYPE_CHECKING); a package's
    ``__init__`` is left out as a target (it re-exports what its modules define)."""
    files: dict[str, Path] = {}
    for package in ("tissue", "envs", "agents"):
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    packages = {name for name, path in files.items() if path.name == "__init__.py"}
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        if name in packages:
            continue
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets |= {node.module} | {f"{node.module}.{a.name}" for a in node.names}
            elif isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
        graph[name] = {t for t in targets if t in files and t not in packages and t != name}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles: strongly connected sets of two or more modules (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for target in graph.get(module, ()):
            if target not in index:
                visit(target)
                low[module] = min(low[module], low[target])
            elif target in stack:
                low[module] = min(low[module], index[target])
        if low[module] == index[module]:
            members = []
            while True:
                member = stack.pop()
                members.append(member)
                if member == module:
                    break
            if len(members) > 1:
                circles.append(sorted(members))

    for module in graph:
        if module not in index:
            visit(module)
    return circles


def test_no_import_circles_even_deferred() -> None:
    """No two modules import each other, directly or round a longer circle, and a deferred
    or type-only import does not hide one."""
    assert _circles(_module_graph()) == []
    # The check sees a circle, here a deferred one.
    assert _circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
