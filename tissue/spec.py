"""What a tissue is made of: :class:`TissueSpec`, and the one place it is resolved.

A :class:`TissueSpec` is a frozen, validated description (mesh, materials, contact method and
its parameters, profile, time step, probe). :func:`resolve_spec` turns it, once, into every
lower-level configuration a tissue is built from (:class:`ResolvedTissue`), asking the
contact strategy for its settings under the spec's profile (:mod:`tissue.profile`).

The profiles themselves are described in :mod:`tissue.profile`.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from tissue.contact.registry import contact_choice
from tissue.contact.sleep import check_sleep_speed
from tissue.errors import ConfigError, check_setting_names
from tissue.fem.material import NeoHookean, TissueMaterials
from tissue.mesh import CollisionSurface, TetMesh
from tissue.probe import ProbeShape, parse_probe_spec
from tissue.profile import PAPER_TISSUE_DT_S, Profile, check_tissue_dt

if TYPE_CHECKING:
    from tissue.contact.base import ContactModel

#: ``TissueSpec(mesh=PUBLISHED_SCENE)`` loads the published scene from where the project
#: looks for it (``PROBEGYM_PAPER_SCENE``, then ``shared/paper-scene`` beside the checkout).
PUBLISHED_SCENE = "paper-scene"
#: Where the published scene is looked for, in order: this variable, then beside the checkout.
PAPER_SCENE_ENV_VAR = "PROBEGYM_PAPER_SCENE"


@dataclass(frozen=True)
class TissueSpec:
    """A tissue to build with :func:`tissue.make_tissue`. Frozen; validated when made.

    Attributes:
        mesh: a phantom level (its tet count on the paper's ladder, e.g. ``1363``; int or
            digits), a tet-mesh file meshio reads (with ``fixed_plane`` or
            ``fixed_nodes_file``), ``"paper-scene"`` or a directory laid out as the
            published scene (with ``scene_lesion`` for the paper profile's prescribed node
            set), or a :class:`tissue.mesh.TetMesh`.
        contact: a registered contact method (:func:`tissue.contact_methods`): ``penalty``,
            ``lm``, ``prescribed``, ``pbd`` or one registered with
            :func:`tissue.register_contact`; its name or its registered class (the spec
            keeps the name here and the class as :attr:`contact_type`).
        profile: ``paper`` or ``robust`` (:mod:`tissue.profile`).
        tissue_dt: the tissue time step [s], in (0, 1] (the paper's,
            :data:`tissue.profile.PAPER_TISSUE_DT_S`).
        young_pa: the bulk tissue's Young's modulus [Pa] (default 2850).
        poisson: the bulk tissue's Poisson ratio (default 0.49).
        lesion_stiffness_ratio: E_lesion / E_tissue (default 4).
        materials: a full :class:`tissue.fem.material.TissueMaterials` instead of the three above.
        contact_params: the method's parameters (an instance of its class's
            ``params_type``), replacing the profile's; None: the profile's.
        probe: the probe's shape: ``face`` (the linear probe, default), ``sphere:R``,
            ``box:LX,LY,LZ``, ``cylinder:R,H``, a mesh file, or a
            :class:`tissue.probe.ProbeShape`.
        fixed_plane: (mesh file) fix the nodes on a plane, ``"z=min"``.
        fixed_nodes_file: (mesh file) a file of fixed node indices.
        mesh_scale: (mesh file) factor to metres (0.001 for a mesh in millimetres).
        scene_lesion: (published scene) the tumour whose published node set the paper
            profile's prescribed displacement holds.
        collision_edge_m: the skin's resolution: the edge length [m] of the collision surface
            contact acts on. None (the default): the mesh's own surface (the phantom's
            1,004 triangles and the published scene's ``breast_500.stl``, as in the paper;
            a mesh file's boundary). A length builds one at that scale
            (:mod:`tissue.mesh.skin`): the phantom's dome meshed again by gmsh, any other
            surface refined by edge bisection; it must lie between the volume's boundary
            resolution and the finest a step can afford (the error names the range). The
            environments use a skin at the probe's scale (``envs.probe_env``).
        sleep_speed_m_s: let the tissue sleep [m/s]: a step with the tissue at rest (every
            node slower than this), out of contact and the probe clear of the skin by more
            than its travel in the step and the method's reach does no tissue work at all
            (:meth:`tissue.contact.base.ContactModel.step`; its
            ``TissueStep.diagnostics.details["asleep"]`` is 1.0), and the tissue wakes as
            the probe approaches. None (the default): it never sleeps, every step is solved.
            The environments use :data:`tissue.SLEEP_SPEED_M_S` (1e-6 m/s). Only how the
            tissue is stepped: no mesh or calibration depends on it.
        contact_type: (not an argument) the registered strategy class ``contact`` names,
            looked up once here; everything built from the spec takes it from here.
    """

    mesh: int | str | os.PathLike[str] | TetMesh = 1363
    contact: str | type[ContactModel] = "lm"
    profile: str = "robust"
    tissue_dt: float = PAPER_TISSUE_DT_S
    young_pa: float | None = None
    poisson: float | None = None
    lesion_stiffness_ratio: float | None = None
    materials: TissueMaterials | None = None
    contact_params: Any = None
    probe: str | ProbeShape = "face"
    fixed_plane: str | None = None
    fixed_nodes_file: str | os.PathLike[str] | None = None
    mesh_scale: float = 1.0
    scene_lesion: int | None = None
    collision_edge_m: float | None = None
    sleep_speed_m_s: float | None = None
    contact_type: type[ContactModel] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.collision_edge_m is not None:
            edge = self.collision_edge_m
            if isinstance(edge, bool) or not isinstance(edge, (int, float, np.floating)):
                raise ConfigError(
                    f"collision_edge_m must be a length in metres or None; got {edge!r}"
                )
            if not (math.isfinite(float(edge)) and float(edge) > 0.0):
                raise ConfigError(
                    f"collision_edge_m must be a positive length in metres; got {edge!r}"
                )
            object.__setattr__(self, "collision_edge_m", float(edge))
        object.__setattr__(self, "sleep_speed_m_s", check_sleep_speed(self.sleep_speed_m_s))
        contact_type = contact_choice(self.contact)
        method = contact_type.name
        object.__setattr__(self, "contact", method)
        object.__setattr__(self, "contact_type", contact_type)
        object.__setattr__(self, "profile", Profile.parse(self.profile).value)
        object.__setattr__(self, "tissue_dt", check_tissue_dt(self.tissue_dt))
        overrides = (self.young_pa, self.poisson, self.lesion_stiffness_ratio)
        if self.materials is not None:
            if any(value is not None for value in overrides):
                raise ConfigError(
                    "give either materials or young_pa / poisson / lesion_stiffness_ratio, not "
                    "both (the materials already say all three)"
                )
            if not isinstance(self.materials, TissueMaterials):
                raise ConfigError(
                    f"materials must be a tissue.fem.material.TissueMaterials; got "
                    f"{type(self.materials).__name__}"
                )
        else:
            self.resolved_materials()  # validates the overrides now
        expected = contact_type.params_type
        if self.contact_params is not None and not isinstance(self.contact_params, expected):
            raise ConfigError(
                f"contact {method!r} takes contact_params of type {expected.__name__}; "
                f"got {type(self.contact_params).__name__}"
            )
        params_dt = getattr(self.contact_params, "tissue_dt", self.tissue_dt)
        if params_dt != self.tissue_dt:
            raise ConfigError(
                f"contact_params.tissue_dt ({params_dt}) differs from "
                f"tissue_dt ({self.tissue_dt}); give the step once, as tissue_dt"
            )
        if not isinstance(self.probe, (str, ProbeShape)):
            raise ConfigError(
                f"probe must be a probe spec string (e.g. 'face', 'sphere:0.01') or a "
                f"ProbeShape; got {type(self.probe).__name__}"
            )
        if isinstance(self.probe, str):
            parse_probe_spec(self.probe)  # validates now
        if not (np.isfinite(self.mesh_scale) and self.mesh_scale > 0):
            raise ConfigError(f"mesh_scale must be a positive factor; got {self.mesh_scale!r}")
        kind = self.mesh_kind()
        file_options = (
            self.fixed_plane is not None
            or self.fixed_nodes_file is not None
            or self.mesh_scale != 1.0
        )
        if file_options and kind != "file":
            raise ConfigError(
                "fixed_plane, fixed_nodes_file and mesh_scale apply to a mesh file only; got "
                f"mesh={self.mesh!r}"
            )
        if kind == "file" and self.fixed_plane is None and self.fixed_nodes_file is None:
            raise ConfigError(
                f"the mesh file {str(self.mesh)!r} needs its fixed nodes: give "
                "fixed_plane='z=min' (or another plane) or fixed_nodes_file=PATH"
            )
        if self.scene_lesion is not None and kind != "scene":
            raise ConfigError(
                f"scene_lesion applies to the published scene only (mesh='{PUBLISHED_SCENE}' "
                f"or its directory); got mesh={self.mesh!r}"
            )

    @classmethod
    def from_overrides(cls, **overrides: Any) -> TissueSpec:
        """Build from keyword arguments, rejecting unknown names with the valid ones listed."""
        check_setting_names(overrides, (f.name for f in fields(cls) if f.init), "tissue")
        return cls(**overrides)

    def mesh_kind(self) -> str:
        """``level``, ``file``, ``scene`` or ``mesh`` (a TetMesh given)."""
        mesh = self.mesh
        if isinstance(mesh, TetMesh):
            return "mesh"
        if isinstance(mesh, bool):
            raise ConfigError(f"mesh must be a level, a file or a directory; got {mesh!r}")
        if isinstance(mesh, (int, np.integer)) or (isinstance(mesh, str) and mesh.isdigit()):
            from tissue.mesh.phantom import parse_level

            parse_level(int(mesh))  # validates the level
            return "level"
        if isinstance(mesh, (str, os.PathLike)):
            text = os.fspath(mesh)
            if text == PUBLISHED_SCENE or Path(text).is_dir():
                return "scene"
            if Path(text).suffix:
                if not Path(text).is_file():
                    raise ConfigError(f"mesh file {text!r} does not exist")
                return "file"
        raise ConfigError(
            f"mesh must be a phantom level (e.g. 1363), a tet-mesh file, '{PUBLISHED_SCENE}' or "
            f"a directory in its layout, or a TetMesh; got {mesh!r}"
        )

    def resolved_materials(self) -> TissueMaterials:
        """The materials: ``materials``, or the defaults with the overrides applied."""
        if self.materials is not None:
            return self.materials
        base = TissueMaterials()
        tissue = NeoHookean(
            self.young_pa if self.young_pa is not None else base.tissue.young_pa,
            self.poisson if self.poisson is not None else base.tissue.poisson,
            base.tissue.density_kg_m3,
        )
        ratio = self.lesion_stiffness_ratio
        return TissueMaterials(
            tissue=tissue,
            lesion_stiffness_ratio=base.lesion_stiffness_ratio if ratio is None else ratio,
        )

    def published_node_set(self, mesh: TetMesh) -> tuple[int, ...]:
        """The published prescribed-node set of :attr:`scene_lesion` on the published scene
        ``mesh``, as volume boundary nodes."""
        from tissue.mesh.paper_scene import load_paper_scene, spring_nodes_to_volume

        scene = load_paper_scene(published_scene_dir(self.mesh))
        if self.scene_lesion not in scene.spring_nodes:
            raise ConfigError(
                f"scene_lesion {self.scene_lesion} is not in the published scene; choose one "
                f"of {sorted(scene.spring_nodes)}"
            )
        return spring_nodes_to_volume(mesh, scene.spring_nodes[self.scene_lesion])

    def probe_shape(self) -> ProbeShape:
        """The probe's geometry."""
        return self.probe if isinstance(self.probe, ProbeShape) else parse_probe_spec(self.probe)


@dataclass(frozen=True)
class ResolvedTissue:
    """Everything a tissue is built from, decided once from a :class:`TissueSpec`.

    Attributes:
        spec: the spec it came from.
        contact_type: the contact strategy's class (``spec.contact_type``; :attr:`method`
            is its registry name).
        mesh: the tet mesh.
        materials: per-region materials.
        probe_shape: the probe's geometry.
        config: the FE simulation's configuration, or the tissue's own (PBD's).
        params: the strategy's parameters (None where ``config`` says all, as PBD's).
        drawn_skin: the skin :meth:`tissue.Tissue.surface` draws where the contact skin is
            finer than a drawing can take (:func:`drawn_skin`), embedded in the same volume;
            None: the contact skin itself.
    """

    spec: TissueSpec
    contact_type: type[ContactModel]
    mesh: TetMesh
    materials: TissueMaterials
    probe_shape: ProbeShape
    config: Any
    params: Any
    drawn_skin: CollisionSurface | None = None

    @property
    def method(self) -> str:
        """The contact method's registry name."""
        return self.contact_type.name


def load_spec_mesh(spec: TissueSpec) -> TetMesh:
    """The tet mesh ``spec.mesh`` names (phantom levels are generated once and cached)."""
    kind = spec.mesh_kind()
    if kind == "level":
        from tissue.mesh.phantom import breast_phantom

        assert isinstance(spec.mesh, (int, str, np.integer))
        return breast_phantom(int(spec.mesh), collision_edge_m=spec.collision_edge_m)
    if kind == "mesh":
        assert isinstance(spec.mesh, TetMesh)
        mesh = spec.mesh
    elif kind == "scene":
        from tissue.mesh.paper_scene import load_paper_scene

        mesh = load_paper_scene(published_scene_dir(spec.mesh)).mesh
    else:
        from tissue.mesh.io import load_tet_mesh

        assert isinstance(spec.mesh, (str, os.PathLike))
        fixed_file = spec.fixed_nodes_file
        mesh = load_tet_mesh(
            Path(spec.mesh),
            fixed_plane=spec.fixed_plane,
            fixed_nodes_file=None if fixed_file is None else Path(fixed_file),
            scale=spec.mesh_scale,
        )
    if spec.collision_edge_m is None:
        return mesh
    from tissue.mesh.skin import with_collision_edge

    return with_collision_edge(mesh, spec.collision_edge_m)


def published_scene_dir(mesh: object, hint: str = "give its directory") -> Path:
    """The published scene's directory for ``mesh`` (``"paper-scene"`` or a directory).

    ``"paper-scene"`` is looked for, in order, at :data:`PAPER_SCENE_ENV_VAR`, then at
    ``shared/paper-scene`` beside the checkout, then under the working directory. ``hint`` ends
    the error raised where none is found (how the caller names another directory).
    """
    text = os.fspath(mesh) if isinstance(mesh, (str, os.PathLike)) else ""
    if text and text != PUBLISHED_SCENE:
        return Path(text)
    candidates = []
    if os.environ.get(PAPER_SCENE_ENV_VAR):
        candidates.append(Path(os.environ[PAPER_SCENE_ENV_VAR]))
    repo = Path(__file__).resolve().parents[1]
    candidates += [repo.parent / "shared" / "paper-scene", Path.cwd() / "shared" / "paper-scene"]
    for candidate in candidates:
        if candidate.is_dir():
            return candidate
    raise ConfigError(
        f"the published scene ('{PUBLISHED_SCENE}') was not found at "
        f"{', '.join(str(c) for c in candidates)}. Set {PAPER_SCENE_ENV_VAR} or {hint}"
    )


def resolve_spec(spec: TissueSpec, mesh: TetMesh | None = None) -> ResolvedTissue:
    """Decide every lower-level configuration of ``spec`` once.

    Args:
        spec: the tissue.
        mesh: its mesh if already loaded (else :func:`load_spec_mesh`).
    """
    mesh = load_spec_mesh(spec) if mesh is None else mesh
    materials = spec.resolved_materials()
    contact_type = spec.contact_type
    config, params = contact_type.settings_for(spec, mesh, materials)
    return ResolvedTissue(
        spec, contact_type, mesh, materials, spec.probe_shape(), config, params, drawn_skin(spec)
    )


def drawn_skin(spec: TissueSpec) -> CollisionSurface | None:
    """The skin to draw for ``spec`` where its contact skin is finer than
    :data:`tissue.mesh.skin.DRAWN_EDGE_M`: the same surface at that edge, or, where the
    volume's boundary is finer still (the 105,004- and 176,506-tet levels), the mesh's own
    surface; None where the contact skin is coarse enough to draw. The spec's volume is
    the same whatever its skin, so the surface's embedding holds for the tissue's nodes."""
    from tissue.mesh.skin import DRAWN_EDGE_M

    if spec.collision_edge_m is None or spec.collision_edge_m >= DRAWN_EDGE_M:
        return None
    try:
        mesh = load_spec_mesh(replace(spec, collision_edge_m=DRAWN_EDGE_M))
    except ConfigError:
        mesh = load_spec_mesh(replace(spec, collision_edge_m=None))
    return mesh.collision_surface
