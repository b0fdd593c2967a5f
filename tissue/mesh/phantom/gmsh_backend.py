"""gmsh plumbing: a deterministic session and the extraction of its meshes as arrays.

:func:`gmsh_session` initialises gmsh without user configuration files and single-threaded
(both could change the mesh), and puts back the SIGPIPE action that gmsh's initialisation
resets. :func:`extract_volume_mesh` and :func:`extract_surface_mesh` read the current model's
tets or triangles with the nodes renumbered compactly in gmsh's tag order, so the same model
gives the same arrays. Coordinates are whatever units the model was built in (metres here).
"""

from __future__ import annotations

import contextlib
import ctypes
import signal
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.errors import MeshError
from tissue.mesh import signed_tet_volumes


def set_sigpipe(action: Any) -> None:
    """Put SIGPIPE's action back after gmsh's initialisation, which sets the OS-level action
    to the default (end the process) behind Python's back. Python ignores SIGPIPE so that a
    write to a closed pipe raises ``BrokenPipeError``; without this, a process whose pipes
    close (a study's workers on Ctrl-C) is killed by the signal instead of handling it."""
    if action is None:
        return
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGPIPE, action)
    elif action in (signal.SIG_IGN, signal.SIG_DFL):  # off the main thread: through libc
        ctypes.CDLL(None).signal(int(signal.SIGPIPE), int(action))


@contextlib.contextmanager
def gmsh_session(verbose: bool = False) -> Iterator[Any]:
    """gmsh initialised with fixed, deterministic options; finalised on exit.

    User configuration files are not read (they could change the mesh); meshing is single
    threaded (thread scheduling would reorder nodes). If the caller already had gmsh
    initialised, a fresh model is used and removed and gmsh is left initialised, with the
    options above left set.
    """
    import gmsh

    owned = not gmsh.isInitialized()
    if owned:
        pipe_action = signal.getsignal(signal.SIGPIPE)
        gmsh.initialize(readConfigFiles=False, interruptible=False)
        set_sigpipe(pipe_action)
    try:
        gmsh.model.add(f"probegym-{time.monotonic_ns()}")
        options = {
            "General.Terminal": 1 if verbose else 0,
            "General.Verbosity": 5 if verbose else 0,
            "General.NumThreads": 1,
            "Mesh.MaxNumThreads1D": 1,
            "Mesh.MaxNumThreads2D": 1,
            "Mesh.MaxNumThreads3D": 1,
            "Geometry.OCCParallel": 0,
            "Mesh.RandomSeed": 1,
            "Mesh.RandomFactor": 1e-9,
            "Mesh.RandomFactor3D": 1e-12,
            "Mesh.Algorithm": 6,
            "Mesh.Algorithm3D": 1,
            "Mesh.Optimize": 1,
            "Mesh.OptimizeNetgen": 0,
            "Mesh.ElementOrder": 1,
            "Mesh.MeshSizeFromCurvature": 0,
            "Mesh.MeshSizeFromPoints": 1,
            "Mesh.MeshSizeExtendFromBoundary": 1,
            "Mesh.MeshSizeMin": 0.0,
        }
        for name, value in options.items():
            gmsh.option.setNumber(name, value)
        yield gmsh
    finally:
        if owned:
            gmsh.finalize()
        else:
            with contextlib.suppress(Exception):
                gmsh.model.remove()


@dataclass
class RawMesh:
    nodes: NDArray[np.float64]
    tets: NDArray[np.int64]
    region: NDArray[np.int64]

    @property
    def tet_count(self) -> int:
        return int(self.tets.shape[0])


def extract_volume_mesh(gmsh: Any, region_of_volume: dict[int, int]) -> RawMesh:
    """Tets of the current gmsh model, nodes renumbered compactly in tag order, tets
    positively oriented, region label from the volume entity each tet belongs to."""
    tag_blocks, region_blocks = [], []
    for volume, label in sorted(region_of_volume.items()):
        types, _, node_tags = gmsh.model.mesh.getElements(3, volume)
        for element_type, tags in zip(types, node_tags, strict=True):
            if element_type != 4:  # 4 = 4-node tetrahedron
                raise MeshError(f"gmsh produced element type {element_type}; expected tets")
            block = np.asarray(tags, dtype=np.int64).reshape(-1, 4)
            tag_blocks.append(block)
            region_blocks.append(np.full(block.shape[0], label, dtype=np.int64))
    if not tag_blocks:
        raise MeshError("gmsh produced no tetrahedra")
    region = np.concatenate(region_blocks)
    nodes, tets = compact(gmsh, np.concatenate(tag_blocks))
    negative = signed_tet_volumes(nodes, tets) < 0
    tets[negative, 2], tets[negative, 3] = tets[negative, 3], tets[negative, 2].copy()
    return RawMesh(nodes=nodes, tets=tets, region=region)


def extract_surface_mesh(gmsh: Any) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """All triangles of the current gmsh model's 2D mesh, nodes renumbered compactly."""
    blocks = []
    for _, surface in gmsh.model.getEntities(2):
        types, _, node_tags = gmsh.model.mesh.getElements(2, surface)
        for element_type, tags in zip(types, node_tags, strict=True):
            if element_type != 2:  # 2 = 3-node triangle
                raise MeshError(f"gmsh produced element type {element_type}; expected triangles")
            blocks.append(np.asarray(tags, dtype=np.int64).reshape(-1, 3))
    return compact(gmsh, np.concatenate(blocks))


def compact(
    gmsh: Any, element_tags: NDArray[np.int64]
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Positions [m] of the nodes the elements use, and the elements renumbered onto them.

    Args:
        element_tags: gmsh node tags per element, (element_count, k).
    """
    node_tags, coordinates, _ = gmsh.model.mesh.getNodes()
    coordinates = np.asarray(coordinates, dtype=np.float64).reshape(-1, 3)
    node_tags = np.asarray(node_tags, dtype=np.int64)
    used, elements = np.unique(element_tags, return_inverse=True)
    position_of_tag = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
    position_of_tag[node_tags] = np.arange(node_tags.size)
    return coordinates[position_of_tag[used]], elements.reshape(element_tags.shape).astype(np.int64)
