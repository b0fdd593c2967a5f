"""The command line under bad input, concurrency and first use: nothing lost, nothing
misleading (each rule for every command)."""

from __future__ import annotations

import importlib
import json
import os
import pkgutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from agents.cli import main

ROOT = Path(__file__).resolve().parents[2]
UNWRITABLE = "/proc/probegym-cannot-write/out.json"


def _import_commands() -> None:
    """Import every module of ``agents`` first, so that none binds a patched name for good
    (a ``from tissue.mesh.phantom import breast_phantom`` run while the patch holds)."""
    import agents

    for info in pkgutil.walk_packages(agents.__path__, "agents."):
        importlib.import_module(info.name)


def _fail_if_called(monkeypatch, target: str) -> None:
    _import_commands()

    def refuse(*args, **kwargs):
        raise AssertionError(f"{target} ran although the arguments were bad")

    monkeypatch.setattr(target, refuse)


@pytest.mark.parametrize(
    "argv",
    [
        ["compress", "--mesh", "623", "--json", UNWRITABLE],
        ["hard-cases", "--cases", "deep_30mm", "--json", UNWRITABLE],
        ["bench", "tissue", "--levels", "623", "--json", UNWRITABLE],
        ["bench", "contact", "--levels", "623", "--json", UNWRITABLE],
        ["bench", "peer", "--levels", "623", "--json", UNWRITABLE],
        ["bench", "env", "--levels", "623", "--json", UNWRITABLE],
        ["mesh", "--level", "623", "--out", "/proc/probegym-cannot-write/mesh.vtu"],
        ["study", "--quick", "--out", "/proc/probegym-cannot-write/study"],
    ],
)
def test_a_bad_output_path_fails_at_once_in_one_line(monkeypatch, capsys, argv) -> None:
    """Exit 2 with one line naming the option, before any mesh is made or loaded."""
    _fail_if_called(monkeypatch, "tissue.mesh.phantom.breast_phantom")
    _fail_if_called(monkeypatch, "tissue.mesh.phantom.cached_mesh")
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "cannot write" in err[0] and "probegym-cannot-write" in err[0]


def test_defaults_land_under_probegym_out(tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["compress", "--mesh", "623", "--depths", "0.002", "--settle-steps", "2"]) == 0
    written = tmp_path / "probegym-out" / "compress" / "compress.json"
    assert written.is_file() and not (tmp_path / "compress.json").exists()
    record = json.loads(written.read_text())
    assert record["depths"][0]["depth_m"] == 0.002


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--direction", "0,0,1"], "fixed base"),
        (["--depths", "0.01,0.09"], "go through the tissue"),
        (["--depths", "0.004,0.002"], "must increase"),
        (["--lesion", "2"], "give --scene DIR"),
        (["--young", "1e307"], "stiffer than any solid"),
        (["--poisson", "0.4999999999999"], "Lame parameter"),
        (["--fixed-plane", "z=min"], "apply to --mesh FILE only"),
        (["--contact", "springs"], "unknown contact method 'springs'"),
        (["--profile", "fast"], "unknown profile 'fast'"),
    ],
)
def test_compress_refuses_what_it_used_to_accept(monkeypatch, capsys, extra, message) -> None:
    _fail_if_called(monkeypatch, "agents.lab.compress_command.run_compression")
    assert main(["compress", "--mesh", "623", "--json", os.devnull, *extra]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("depth", ["0", "-5", "nan", "inf", "31"])
def test_demo_refuses_depths_it_cannot_press(monkeypatch, capsys, depth: str) -> None:
    _fail_if_called(monkeypatch, "tissue.mesh.phantom.breast_phantom")
    assert main(["demo", "--level", "623", "--depth-mm", depth]) == 2
    assert "--depth-mm must be a depth in (0, 30] mm" in capsys.readouterr().err


def _phantom_file(tmp_path: Path, scale: float = 1.0) -> Path:
    """The 623-tet phantom as a VTU file (its nodes times ``scale``: 1000 for millimetres)."""
    import meshio

    from tissue.mesh.phantom import breast_phantom

    mesh = breast_phantom(623)
    path = tmp_path / "phantom.vtu"
    meshio.write(
        path,
        meshio.Mesh(
            mesh.nodes * scale, [("tetra", mesh.tets)], cell_data={"region": [mesh.region]}
        ),
    )
    return path


def test_a_fixed_plane_that_touches_no_node_is_refused(tmp_path, capsys) -> None:
    path = _phantom_file(tmp_path)
    argv = ["compress", "--mesh", str(path), "--json", os.devnull, "--fixed-plane", "z=0.5"]
    assert main(argv) == 2
    assert "touches no node" in capsys.readouterr().err


def test_a_millimetre_mesh_is_named_and_scale_reads_it(tmp_path, capsys) -> None:
    path = _phantom_file(tmp_path, scale=1000.0)
    argv = ["compress", "--mesh", str(path), "--fixed-plane", "z=min", "--json", os.devnull]
    assert main([*argv, "--depths", "0.002", "--settle-steps", "2"]) == 2
    assert "--scale 0.001" in capsys.readouterr().err
    assert main([*argv, "--depths", "0.002", "--settle-steps", "2", "--scale", "0.001"]) == 0


def test_compress_exits_1_when_the_run_was_unstable(tmp_path) -> None:
    """The paper's 10-substep PBD inverts a tet under a deep press at 623 tets."""
    out = tmp_path / "run.json"
    argv = ["compress", "--mesh", "623", "--contact", "pbd", "--profile", "paper",
            "--depths", "0.01,0.02,0.03", "--settle-steps", "5", "--json", str(out)]  # fmt: skip
    code = main(argv)
    record = json.loads(out.read_text())
    assert (code == 1) == (record["instability"] is not None)
    assert code == 1


def test_json_is_strict_and_a_non_finite_force_is_a_failure(tmp_path) -> None:
    from agents.outputs import write_json
    from tissue.contact import make_contact_model
    from tissue.mesh.phantom import breast_phantom
    from tissue.probe import linear_probe
    from tissue.sim.simulator import SimulationConfig
    from tissue.status import StepStatus

    path = write_json(
        {"force": [np.nan, -np.inf, 1.0], "nested": {"x": np.inf}}, tmp_path / "a.json"
    )
    assert json.loads(path.read_text()) == {"force": [None, None, 1.0], "nested": {"x": None}}
    model = make_contact_model(
        "penalty", breast_phantom(623), linear_probe(), config=SimulationConfig(mode="paper")
    )
    advance = model._advance

    def poisoned(h):
        status, points, forces, diagnostics = advance(h)
        return status, np.ones((1, 3)), np.full((1, 3), np.nan), diagnostics

    model._advance = poisoned
    result = model.step([0.0, 0.0, 0.2], [1.0, 0.0, 0.0, 0.0])
    assert result.status is StepStatus.DIVERGED
    assert np.all(np.isfinite(result.force_world_n))


def test_old_and_new_option_names_mean_the_same() -> None:
    from agents.cli import _build_parser

    parser = _build_parser()
    old = parser.parse_args(["compress", "--method", "pbd", "--mode", "paper"])
    new = parser.parse_args(["compress", "--contact", "pbd", "--profile", "paper"])
    assert (old.method, old.mode) == (new.method, new.mode) == ("pbd", "paper")
    study = parser.parse_args(["study", "--contact", "lm", "--profile", "robust"])
    assert (study.methods, study.config) == ("lm", "robust")
    hard = parser.parse_args(["hard-cases", "--contact", "lm", "--profile", "paper"])
    assert (hard.methods, hard.config) == ("lm", "paper")


_HOLD_LOCK = """
import sys, time
from pathlib import Path
from agents.outputs import exclusive_folder
with exclusive_folder(Path(sys.argv[1]), "probegym study"):
    print("locked", flush=True)
    time.sleep(60)
"""


def test_a_second_study_on_the_same_folder_is_refused(tmp_path, capsys) -> None:
    """Two studies rewriting one results.jsonl each kept only their own records: the
    folder is locked by the first (an OS lock that dies with its process)."""
    out = tmp_path / "study"
    holder = subprocess.Popen(
        [sys.executable, "-c", _HOLD_LOCK, str(out)], cwd=ROOT, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        argv = ["study", "--levels", "623", "--lesions", "1", "--contact", "lm",
                "--profile", "robust", "--reference-level", "623", "--out", str(out)]  # fmt: skip
        assert main(argv) == 2
        assert f"another probegym study (process {holder.pid}) is writing to" in (
            capsys.readouterr().err
        )
    finally:
        holder.kill()
        holder.wait()
    # The lock died with its process: nothing stale is left to refuse the next study.
    from agents.outputs import exclusive_folder

    with exclusive_folder(out, "probegym study"):
        pass


#: ``python -c`` running ``probegym`` with Python's own SIGINT handler, as a terminal starts
#: it. A process inherits ignored signals, and a command started in the background by a
#: non-interactive shell (``cmd &`` in a script) ignores SIGINT: a study started under such a
#: pytest never saw the Ctrl-C and ran to its end (exit 0, every record written).
_AS_FROM_A_TERMINAL = (
    "import runpy, signal; "
    "signal.signal(signal.SIGINT, signal.default_int_handler); "
    "runpy.run_module('agents.cli', run_name='__main__', alter_sys=True)"
)


@pytest.mark.slow
def test_ctrl_c_on_a_study_says_what_was_kept_in_one_line(tmp_path) -> None:
    out = tmp_path / "study"
    stdout, stderr = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
    with stdout.open("w") as out_file, stderr.open("w") as err_file:
        study = subprocess.Popen(
            [sys.executable, "-c", _AS_FROM_A_TERMINAL, "study", "--levels", "623,1363",
             "--lesions", "1,3", "--reference-level", "1363", "--workers", "2",
             "--no-progress", "--out", str(out)],
            cwd=ROOT, stdout=out_file, stderr=err_file, stdin=subprocess.DEVNULL,
            start_new_session=True,
        )  # fmt: skip
        results = out / "results.jsonl"
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and not (results.exists() and results.stat().st_size):
            time.sleep(0.5)
        os.killpg(study.pid, signal.SIGINT)  # as a terminal's Ctrl-C: the whole group
        study.wait(timeout=120)
    err = stderr.read_text()
    # A study that ended on its own (rc 0) was never interrupted: the message says how much
    # it wrote and how this process holds SIGINT.
    kept_lines = len(results.read_text().splitlines()) if results.exists() else 0
    held = signal.getsignal(signal.SIGINT)
    assert study.returncode == 130, (study.returncode, err, f"{kept_lines} records", held)
    lines = [line for line in err.splitlines() if line.strip()]
    assert "Traceback" not in err and len(lines) == 1, err
    assert "run the same command again to resume" in lines[0]
    kept = [json.loads(line) for line in results.read_text().splitlines()]
    assert kept and all("key" in record for record in kept)


def test_demo_mesh_and_hard_cases_run(tmp_path, capsys) -> None:
    """Each command once, small: what a new user types first."""
    assert main(["demo", "--level", "623", "--depth-mm", "2"]) == 0
    assert "status" in capsys.readouterr().out
    mesh_path = tmp_path / "phantom.vtu"
    assert main(["mesh", "--level", "623", "--out", str(mesh_path)]) == 0
    import meshio

    assert meshio.read(mesh_path).cells_dict["tetra"].shape == (571, 4)
    out = tmp_path / "hard.json"
    argv = ["hard-cases", "--cases", "edge_contact", "--contact", "lm", "--profile", "robust",
            "--level", "623", "--json", str(out)]  # fmt: skip
    assert main(argv) == 0
    (record,) = json.loads(out.read_text())
    assert record["case"] == "edge_contact" and record["stable"] and record["energy_ok"]


def _tiny_study(out: Path, *extra: str) -> list[str]:
    return ["study", "--levels", "623", "--lesions", "1", "--contact", "lm,penalty",
            "--profile", "robust", "--reference-level", "623", "--depths", "0.004",
            "--settle-steps", "5", "--no-progress", "--out", str(out), *extra]  # fmt: skip


def test_a_study_with_two_workers_records_every_cell(tmp_path, capsys) -> None:
    """The README's main command's way of running, small: two worker processes."""
    out = tmp_path / "study"
    assert main(_tiny_study(out, "--workers", "2")) == 0
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert sorted(r["key"] for r in records) == ["robust/lm/623/1", "robust/penalty/623/1"]
    assert all(r["status"] == "ok" and r["load_average"] >= 0 for r in records)
    assert (out / "results.jsonl").stat().st_mode & 0o777 == 0o666 & ~_umask()
    assert "failed" not in capsys.readouterr().err


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_a_study_scored_against_measured_positions(tmp_path) -> None:
    """--measured: the truth from a CSV (lesion, depth_index, x, y, z), no reference run;
    the errors are the distances to those points."""
    out = tmp_path / "study"
    csv = tmp_path / "measured.csv"
    csv.write_text("lesion,depth_index,x_m,y_m,z_m\n1,1,0.0,0.0,0.05\n")
    assert main(_tiny_study(out, "--measured", str(csv))) == 0
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    for record in records:
        assert record["truth"] == "measured"
        expected = np.linalg.norm(np.subtract(record["tracked_m"][0], [0.0, 0.0, 0.05]))
        assert record["errors_m"][0] == pytest.approx(expected, rel=1e-9)
    assert json.loads((out / "references.json").read_text()) == {}  # no reference was run


@pytest.mark.slow
def test_the_readmes_main_command(tmp_path) -> None:
    """``probegym study --quick --workers 2``, end to end, in a fresh output folder: every
    cell recorded, the robust profile completing all of them, every output written."""
    result = subprocess.run(
        [sys.executable, "-m", "agents.cli", "study", "--quick", "--workers", "2",
         "--no-progress"],
        cwd=tmp_path, capture_output=True, text=True, timeout=1800,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    out = tmp_path / "probegym-out" / "study"
    records = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(records) == 96
    robust = [r for r in records if r["config"] == "robust"]
    assert robust and all(r["stability_percent"] == 100.0 for r in robust)
    for name in ("stability.md", "errors.png", "times.png", "accuracy_vs_time.png",
                 "report.md", "report.html", "summary.json"):  # fmt: skip
        assert (out / name).stat().st_size > 0


@pytest.mark.parametrize(
    ("value", "message"),
    [("[1]", "is not a JSON object"), ("{", "is not JSON")],
)
def test_train_env_kwargs_must_be_a_json_object(capsys, value, message) -> None:
    with pytest.raises(SystemExit) as exited:
        main(["train", "probegym/ForceScan-v0", "--env-kwargs", value])
    assert exited.value.code == 2
    assert message in capsys.readouterr().err


def test_train_env_kwargs_may_not_set_what_has_an_option(monkeypatch, capsys) -> None:
    _fail_if_called(monkeypatch, "agents.learning.train.command.train")
    argv = ["train", "probegym/ForceScan-v0", "--env-kwargs", '{"contact": "pbd"}']
    assert main(argv) == 2
    assert "use --contact instead" in capsys.readouterr().err


def test_train_env_kwargs_reach_the_run_settings() -> None:
    from agents.cli import _build_parser
    from agents.learning.train.command import _settings

    kwargs = '{"start_offset_range_m": [0, 0.01]}'
    args = _build_parser().parse_args(["train", "probegym/LesionSearch-v0", "--env-kwargs", kwargs])
    settings = _settings(args, "ppo", "lm", 0, Path("out"))
    assert settings.env_kwargs["start_offset_range_m"] == (0, 0.01)
    assert settings.env_kwargs["contact"] == "lm"
