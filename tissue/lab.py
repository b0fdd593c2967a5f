"""The lab's surface of the tissue: what the study, the benchmarks and the diagnostics need
beyond the front door (:mod:`tissue`).

The environments and a user's script need only ``import tissue``. The lab (agents' study,
benchmarks, compression and hard-case commands) works one level down: it builds contact
models on a mesh of its own, reads meshes and the published scene, times linear solvers and
the kernels' compilation. Those names live here, in one documented place, so that nothing
outside ``tissue`` reaches into its modules (tests/project/test_layout.py enforces it).

Groups (each name's own docstring gives its units and shapes):

* meshes: :class:`TetMesh`, the phantom ladder (:func:`breast_phantom`, :data:`PHANTOM_LEVELS`,
  :func:`parse_level`, :func:`describe_mesh`, :class:`PhantomSpec`), files
  (:func:`load_tet_mesh`, :func:`write_mesh`), the published scene
  (:func:`load_paper_scene`, :func:`remesh_paper_scene`, :func:`spring_nodes_to_volume`,
  :func:`published_scene_dir`) and the skin's collision edge;
* probes: :class:`Probe`, :class:`BoxProbe`, :func:`linear_probe`, :func:`parse_probe_spec`,
  :func:`quat_to_matrix`;
* contact: the method's choice (:func:`contact_method`, :data:`CONTACT_MODELS`), a model on a
  simulator (:func:`make_contact_model`), each method's settings, placement of a probe on the
  skin, and the stability monitor;
* simulation: :class:`SimulationConfig`, :class:`TissueSimulator`, the linear solvers, the
  paper's timing constants and the profile choices;
* :func:`compiled_kernels`: one compiled kernel per module that has them (the first run's
  compilation is said before it happens, ``agents/lab/first_use.py``).
"""

from __future__ import annotations

from typing import Any

from tissue.choices import Choice
from tissue.contact import CONTACT_MODELS, contact_method, make_contact_model
from tissue.contact.fe_model import model_surface
from tissue.contact.lagrange import LagrangeParams
from tissue.contact.penalty import PenaltyParams, default_stiffness_n_per_m
from tissue.contact.placement import (
    first_contact_pose,
    radial_roll_rad,
    ray_surface_hit,
    skin_normal_above,
)
from tissue.contact.prescribed import PrescribedParams
from tissue.contact.stability import StabilityLimits, StabilityMonitor
from tissue.contact.surface_points import contact_surface
from tissue.mesh import TetMesh, boundary_faces, top_surface_nodes, triangle_grid
from tissue.mesh.io import load_tet_mesh, write_mesh
from tissue.mesh.paper_scene import load_paper_scene, remesh_paper_scene, spring_nodes_to_volume
from tissue.mesh.phantom import (
    GENERATOR_VERSION,
    PHANTOM_LEVELS,
    PhantomSpec,
    breast_phantom,
    describe_mesh,
    mesh_cache_dir,
    parse_level,
)
from tissue.mesh.skin import check_collision_edge, with_collision_edge
from tissue.pbd import PBDConfig, PBDContact
from tissue.probe import BoxProbe, Probe, linear_probe, parse_probe_spec, quat_to_matrix
from tissue.profile import PAPER_PROBE_SPEED_M_S, PAPER_TISSUE_DT_S, profile_choices
from tissue.sim.simulator import SimulationConfig, TissueSimulator
from tissue.sim.solvers import (
    ConstrainedSystem,
    DirectFactorizer,
    LinearSolver,
    LinearSolverConfig,
)
from tissue.spec import published_scene_dir
from tissue.status import worst


def compiled_kernels() -> list[Any]:
    """A sample of the numba kernels a simulation compiles, one per module that has them:
    their disk caches tell whether the first run after installing will compile (numba
    dispatchers; their ``_cache`` is numba's own)."""
    from tissue.contact.lagrange import projected_gauss_seidel
    from tissue.contact.penalty import spring_terms
    from tissue.fem.kernels import anp_patch_pass, element_pass, gather_elements
    from tissue.pbd.sweep import project_tets
    from tissue.sim.solvers.node_blocks import node_block_product

    return [
        element_pass.parallel,
        element_pass.serial,
        gather_elements.parallel,
        anp_patch_pass.parallel,
        node_block_product.serial,
        project_tets,
        projected_gauss_seidel,
        spring_terms,
    ]


__all__ = [
    "CONTACT_MODELS",
    "GENERATOR_VERSION",
    "PAPER_PROBE_SPEED_M_S",
    "PAPER_TISSUE_DT_S",
    "PHANTOM_LEVELS",
    "BoxProbe",
    "Choice",
    "ConstrainedSystem",
    "DirectFactorizer",
    "LagrangeParams",
    "LinearSolver",
    "LinearSolverConfig",
    "PBDConfig",
    "PBDContact",
    "PenaltyParams",
    "PhantomSpec",
    "PrescribedParams",
    "Probe",
    "SimulationConfig",
    "StabilityLimits",
    "StabilityMonitor",
    "TetMesh",
    "TissueSimulator",
    "boundary_faces",
    "breast_phantom",
    "check_collision_edge",
    "compiled_kernels",
    "contact_method",
    "contact_surface",
    "default_stiffness_n_per_m",
    "describe_mesh",
    "first_contact_pose",
    "linear_probe",
    "load_paper_scene",
    "load_tet_mesh",
    "make_contact_model",
    "mesh_cache_dir",
    "model_surface",
    "parse_level",
    "parse_probe_spec",
    "profile_choices",
    "published_scene_dir",
    "quat_to_matrix",
    "radial_roll_rad",
    "ray_surface_hit",
    "remesh_paper_scene",
    "skin_normal_above",
    "spring_nodes_to_volume",
    "top_surface_nodes",
    "triangle_grid",
    "with_collision_edge",
    "worst",
    "write_mesh",
]
