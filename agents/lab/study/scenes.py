"""The study's scenes: where its meshes, lesions and probe paths come from.

``synthetic``: the built-in phantom (:mod:`tissue.mesh.phantom`) at the 9 levels, lesions 1-10.
The probe is placed on the skin above each lesion, normal to the surface: the pressing
direction is the inward normal of the collision surface at the skin point straight above
the lesion's centre, aimed through the centre, with the probe's long axis down the slope (a
radial scan plane); the path is the same in world coordinates at every level (every level
shares one collision surface and one set of tracked points).

Most lesions lie on the dome's flanks, where the skin is tilted 45-55 degrees: pressed 25-30
mm along the normal, frictionless tissue (the paper's assumption) can slip out from under
the probe, or be pinched between the probe and the fixed base; the converged reference does
the same, and the study reports it (largest landmark jump, force per depth).

``paper`` (or a directory laid out like ../shared/paper-scene): the published scene, on its
own mesh (level ``published``) and re-meshed at the 9 levels; lesions are its tumours and
the path is their real probe poses ``Transform0..4``.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from agents.lab.compress import Waypoint, plan_scene, straight_path
from agents.lab.study.spec import NATIVE_LEVEL
from tissue import PUBLISHED_SCENE, ConfigError, ProbeShape
from tissue.lab import (
    Probe,
    TetMesh,
    boundary_faces,
    contact_surface,
    first_contact_pose,
    published_scene_dir,
    radial_roll_rad,
    skin_normal_above,
    spring_nodes_to_volume,
    triangle_grid,
)


def default_paper_scene_dir() -> Path:
    """The published scene's directory (see :data:`tissue.spec.PAPER_SCENE_ENV_VAR`)."""
    return published_scene_dir(PUBLISHED_SCENE, hint="give --scene DIR")


@dataclass
class StudyScene:
    """One scene of the study; see the module docstring.

    Attributes:
        name: ``synthetic`` or ``paper``.
        directory: the published scene's directory (None for synthetic).
        lesion_ids: the scene's lesion numbers (1-based).
        collision_edge_m: the skin's edge [m] (:attr:`tissue.TissueSpec.collision_edge_m`);
            None: the scene's own surface (the paper's).
    """

    name: str
    directory: Path | None
    lesion_ids: tuple[int, ...]
    _scene: Any = field(default=None, repr=False)
    collision_edge_m: float | None = None

    # ------------------------------------------------------------------ meshes

    def mesh(self, level: int) -> TetMesh:
        """The scene's volume mesh at ``level`` (generated and cached on first use), its skin
        at :attr:`collision_edge_m`."""
        if self.directory is None:
            from tissue.lab import breast_phantom

            return breast_phantom(level, collision_edge_m=self.collision_edge_m)
        if level == NATIVE_LEVEL:
            mesh = self.paper_scene().mesh
        else:
            from tissue.lab import remesh_paper_scene

            mesh = remesh_paper_scene(self.directory, level)
        if self.collision_edge_m is None:
            return mesh
        from tissue.lab import with_collision_edge

        return with_collision_edge(mesh, self.collision_edge_m)

    def paper_scene(self) -> Any:
        if self._scene is None:
            from tissue.lab import load_paper_scene

            assert self.directory is not None
            self._scene = load_paper_scene(self.directory)
        return self._scene

    def landmark_name(self, lesion: int) -> str:
        """The landmark tracking ``lesion``."""
        return f"lesion_{lesion}" if self.directory is None else f"tumor{lesion}"

    def fingerprint(self) -> str:
        """Changes whenever the scene's data change (keys the reference cache)."""
        skin = "" if self.collision_edge_m is None else f"-skin{self.collision_edge_m:g}"
        if self.directory is None:
            from tissue.lab import GENERATOR_VERSION, PhantomSpec

            return f"synthetic-g{GENERATOR_VERSION}-{PhantomSpec().content_hash()[:16]}{skin}"
        digest = hashlib.sha256()
        for path in sorted(self.directory.rglob("*")):
            if path.is_file():
                digest.update(path.relative_to(self.directory).as_posix().encode())
                digest.update(path.read_bytes())
        return f"paper-{digest.hexdigest()[:16]}{skin}"

    # ------------------------------------------------------------------ paths

    def path(
        self, mesh: TetMesh, shape: ProbeShape, lesion: int, depths_m: tuple[float, ...]
    ) -> tuple[Waypoint, list[Waypoint]]:
        """The probe's start pose and one waypoint per depth for ``lesion``."""
        if self.directory is not None:
            return plan_scene(self.paper_scene().probe_poses[lesion])
        assert mesh.landmarks is not None and mesh.collision_surface is not None
        centres = np.asarray(mesh.metadata["lesion_centres_m"], dtype=np.float64)
        centre = centres[lesion - 1]
        direction = -skin_normal_above(mesh, centre)
        surface = contact_surface(mesh)
        roll = radial_roll_rad(shape, direction)
        position, quat = first_contact_pose(
            surface, mesh.nodes, shape, centre, direction, roll_rad=roll
        )
        return straight_path(position, quat, direction, list(depths_m))

    def base_clearance_m(
        self, mesh: TetMesh, shape: ProbeShape, lesion: int, depths_m: tuple[float, ...]
    ) -> float:
        """Least distance [m] between the probe at ``lesion``'s deepest pose and the
        mesh's fixed base (negative: the pose would drive the probe into it, squeezing the
        tissue between them to nothing, which no method can complete).

        The base is sampled on the boundary triangles whose corners are all fixed (28
        points each, a grid of 6 divisions per edge): a coarse level's few fixed nodes
        alone leave gaps a tilted probe fits between.
        """
        _, stops = self.path(mesh, shape, lesion, depths_m)
        probe = Probe(shape)
        probe.set_pose(stops[-1].position, stops[-1].quat_wxyz)
        distance, _ = probe.signed_distance_world(_fixed_base_samples(mesh))
        return float(distance.min(initial=np.inf))

    def prescribed_nodes(self, mesh: TetMesh, lesion: int) -> tuple[int, ...] | None:
        """The published a-priori node set of ``lesion`` (None: chosen at first contact)."""
        if self.directory is None:
            return None
        return spring_nodes_to_volume(mesh, self.paper_scene().spring_nodes[lesion])


def _fixed_base_samples(mesh: TetMesh, per_edge: int = 6) -> NDArray[np.float64]:
    """Points [m] spread over the mesh's fixed boundary (triangles with all corners fixed),
    shape (k, 3); the fixed nodes themselves where no such triangle exists."""
    fixed = np.zeros(mesh.node_count, dtype=bool)
    fixed[mesh.fixed_nodes] = True
    faces = boundary_faces(mesh.tets)
    faces = faces[fixed[faces].all(axis=1)]
    if faces.size == 0:
        return mesh.nodes[fixed]
    weights = triangle_grid(per_edge)  # (g, 3)
    corners = mesh.nodes[faces]  # (f, 3, 3)
    return np.einsum("gk,fka->fga", weights, corners).reshape(-1, 3)


def open_scene(scene: str, collision_edge_m: float | None = None) -> StudyScene:
    """``synthetic``, ``paper`` or a directory, its skin at ``collision_edge_m`` [m] (None:
    its own); a clear error for anything unreadable."""
    if scene == "synthetic":
        return StudyScene("synthetic", None, tuple(range(1, 11)), None, collision_edge_m)
    directory = default_paper_scene_dir() if scene == "paper" else Path(scene)
    if not directory.is_dir():
        raise ConfigError(
            f"--scene {scene!r} is neither 'synthetic', 'paper' nor a readable directory"
        )
    from tissue.lab import load_paper_scene

    loaded = load_paper_scene(directory)
    return StudyScene("paper", directory.resolve(), loaded.tumour_ids, loaded, collision_edge_m)
