"""Reading and writing tet meshes: any format meshio knows, and probegym's own cache format.

* :func:`load_tet_mesh` turns any tetrahedral mesh meshio reads (gmsh ``.msh``, VTK/VTU,
  Medit, Abaqus, ...) into a :class:`~tissue.mesh.TetMesh`, with fixed nodes chosen by a plane
  or read from an index file. Lengths are scaled to metres once, here.
* :func:`write_mesh` writes a mesh, optionally deformed, to any meshio format by suffix
  (``.vtu`` for ParaView), with the region label as cell data and displacement as point data.
* :func:`save_mesh_npz` / :func:`load_mesh_npz` store a complete mesh (collision surface,
  landmarks, metadata) in one ``.npz`` file; the generated-mesh cache uses them.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from tissue.errors import ConfigError, MeshError
from tissue.mesh import TetMesh, signed_tet_volumes

# Nodes within this fraction of the mesh's largest extent from a fixing plane are on it.
_PLANE_TOLERANCE_FRACTION = 1e-6
_PLANE_SPEC = re.compile(r"^\s*([xyz])\s*=\s*(min|max|[-+0-9.eE]+)\s*$")
_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}
# Bumped whenever the .npz layout written by save_mesh_npz changes.
_NPZ_FORMAT = 1


def parse_fixed_plane(spec: str) -> tuple[int, str | float]:
    """Parse a fixing-plane spec such as ``"z=min"``, ``"x=max"`` or ``"z=0.0"``.

    Returns:
        (axis index 0..2, ``"min"``/``"max"`` or a coordinate [m] after scaling).

    Raises:
        ConfigError: the spec is not ``<axis>=<min|max|number>`` with axis in x, y, z.
    """
    match = _PLANE_SPEC.match(spec) if isinstance(spec, str) else None
    if match is None:
        raise ConfigError(
            f"fixed_plane={spec!r} is not a plane spec; expected '<axis>=<min|max|value>' with "
            "axis one of x, y, z, for example 'z=min', 'x=max' or 'z=0.0'"
        )
    axis, where = match.groups()
    if where in ("min", "max"):
        return _AXIS_INDEX[axis], where
    try:
        return _AXIS_INDEX[axis], float(where)
    except ValueError as error:
        raise ConfigError(f"fixed_plane={spec!r}: {where!r} is not a number") from error


def nodes_on_plane(
    nodes: NDArray[np.float64], spec: str, tolerance: float | None = None
) -> NDArray[np.int64]:
    """Indices of nodes [m], shape (node_count, 3), lying on a plane spec (see
    :func:`parse_fixed_plane`), within ``tolerance`` [m] (default: 1e-6 of the mesh's extent).
    """
    axis, where = parse_fixed_plane(spec)
    coordinate = nodes[:, axis]
    if where == "min":
        value = float(coordinate.min())
    elif where == "max":
        value = float(coordinate.max())
    else:
        value = float(where)
    if tolerance is None:
        tolerance = _PLANE_TOLERANCE_FRACTION * float(np.max(np.ptp(nodes, axis=0)))
    found = np.flatnonzero(np.abs(coordinate - value) <= tolerance).astype(np.int64)
    if found.size == 0:
        low, high = float(coordinate.min()), float(coordinate.max())
        raise ConfigError(
            f"fixed_plane={spec!r} touches no node (the mesh spans {low:g} to {high:g} m along "
            f"that axis); use 'min' or 'max', or a value on the mesh's base"
        )
    return found


def read_index_file(path: str | Path, node_count: int) -> NDArray[np.int64]:
    """Read 0-based node indices (whitespace or comma separated) and check their range.

    Raises:
        MeshError: the file is missing, holds non-integers, or an index is out of range.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"fixed-node file {str(path)!r} does not exist; give an existing file")
    text = path.read_text().replace(",", " ")
    try:
        values = np.array([float(token) for token in text.split()], dtype=np.float64)
    except ValueError as error:
        raise MeshError(
            f"fixed-node file {str(path)!r} must hold integer node indices: {error}"
        ) from error
    if values.size and not np.all(values == np.round(values)):
        raise MeshError(f"fixed-node file {str(path)!r} holds non-integer values")
    indices = values.astype(np.int64)
    if indices.size and (indices.min() < 0 or indices.max() >= node_count):
        raise MeshError(
            f"fixed-node file {str(path)!r} has indices in [{indices.min()}, {indices.max()}] "
            f"but the mesh has {node_count} nodes (valid: 0..{node_count - 1}, 0-based); "
            "check that the file belongs to this mesh and is 0-based"
        )
    return indices


def orient_tets(nodes: NDArray[np.float64], tets: NDArray[np.int64]) -> NDArray[np.int64]:
    """Tets with the last two nodes swapped where the signed volume is negative."""
    tets = np.array(tets, dtype=np.int64, copy=True)
    negative = signed_tet_volumes(nodes, tets) < 0
    tets[negative, 2], tets[negative, 3] = tets[negative, 3], tets[negative, 2].copy()
    return tets


def load_tet_mesh(
    path: str | Path,
    *,
    fixed_plane: str | None = None,
    plane_tolerance: float | None = None,
    fixed_nodes_file: str | Path | None = None,
    scale: float = 1.0,
    orient: bool = True,
    name: str | None = None,
) -> TetMesh:
    """Load any tetrahedral mesh meshio reads as a :class:`TetMesh`.

    Only linear tets (meshio ``tetra``) are kept; surface cells are ignored and nodes used by
    no tet are dropped (fixed-node indices from a file refer to the file's numbering and are
    renumbered). Regions come from, in order of preference, a ``region`` cell array (labels
    as stored, as :func:`write_mesh` writes them), gmsh physical groups (``gmsh:physical``:
    sorted tags map to labels 0, 1, ..., names from the file's physical names), or
    ``medit:ref``; otherwise every tet is region 0, ``"tissue"``.

    Args:
        path: the mesh file.
        fixed_plane: fix the nodes on a plane, ``"<axis>=<min|max|value>"`` (value in metres,
            after scaling), for example ``"z=min"``.
        plane_tolerance: distance [m] from the plane within which nodes count as on it;
            default 1e-6 of the mesh's largest extent.
        fixed_nodes_file: a text file of 0-based node indices to fix (combined with
            ``fixed_plane`` when both are given).
        scale: factor applied to the file's coordinates to get metres (0.001 for mm files).
        orient: swap two nodes of each negatively oriented tet; with False such tets raise.
        name: the mesh's name; default the file name.

    Returns:
        The mesh, node positions in metres.

    Raises:
        MeshError: missing or unreadable file, no tets, bad fixed indices, mesh in mm
            (extent over 2 m: pass ``scale=0.001``), inverted tets with ``orient=False``.
        ConfigError: a malformed ``fixed_plane`` or a non-positive ``scale``.
    """
    import meshio

    path = Path(path)
    if not path.is_file():
        raise MeshError(f"mesh file {str(path)!r} does not exist; give the path of a mesh file")
    if not (np.isfinite(scale) and scale > 0):
        raise ConfigError(f"scale={scale!r} must be a positive number (0.001 for mm files)")
    if fixed_plane is not None:
        parse_fixed_plane(fixed_plane)
    messages = io.StringIO()
    try:
        # meshio prints each failed format attempt and calls sys.exit on a file no reader
        # takes; a library must neither print nor exit, so both are caught here.
        with contextlib.redirect_stdout(messages), contextlib.redirect_stderr(messages):
            data = meshio.read(path)
    except (Exception, SystemExit) as error:  # meshio raises many types
        detail = " ".join((str(error) if not isinstance(error, SystemExit) else "").split())
        detail = detail or " ".join(messages.getvalue().split()) or "unknown format"
        raise MeshError(
            f"meshio cannot read {str(path)!r}: {detail}; give a tet mesh in a format meshio "
            "reads (gmsh .msh, .vtu, .vtk, .mesh, ...)"
        ) from None

    blocks = [i for i, block in enumerate(data.cells) if block.type == "tetra"]
    if not blocks:
        found = sorted({block.type for block in data.cells}) or ["no cells"]
        raise MeshError(
            f"{str(path)!r} holds no linear tetrahedra (found: {', '.join(found)}); "
            "give a volume mesh of 4-node tets"
        )
    tets_file = np.concatenate([data.cells[i].data for i in blocks]).astype(np.int64)
    labels, region_names = _regions(data, blocks)

    used, tets = np.unique(tets_file, return_inverse=True)
    tets = tets.reshape(-1, 4).astype(np.int64)
    nodes = np.asarray(data.points, dtype=np.float64)[:, :3] * scale
    file_node_count = nodes.shape[0]
    nodes = nodes[used]
    if orient:
        tets = orient_tets(nodes, tets)

    fixed = np.zeros(0, dtype=np.int64)
    if fixed_nodes_file is not None:
        file_fixed = read_index_file(fixed_nodes_file, file_node_count)
        new_index = np.full(file_node_count, -1, dtype=np.int64)
        new_index[used] = np.arange(used.size)
        fixed = new_index[file_fixed]
        if np.any(fixed < 0):
            raise MeshError(
                f"fixed-node file {str(fixed_nodes_file)!r} names {int(np.sum(fixed < 0))} nodes "
                "that belong to no tet; check that the file belongs to this mesh"
            )
    if fixed_plane is not None:
        fixed = np.union1d(fixed, nodes_on_plane(nodes, fixed_plane, plane_tolerance))
    return TetMesh(
        nodes=nodes,
        tets=tets,
        region=labels,
        fixed_nodes=fixed,
        region_names=region_names,
        name=name or path.name,
        metadata={"source": str(path), "scale": scale},
    )


def _regions(data: Any, blocks: list[int]) -> tuple[NDArray[np.int64], tuple[str, ...]]:
    """Region label per tet and region names from a meshio mesh's cell data."""
    cell_data = data.cell_data
    for key in ("region", "gmsh:physical", "medit:ref"):
        if key in cell_data:
            values = np.concatenate([np.asarray(cell_data[key][i]) for i in blocks])
            values = values.astype(np.int64).reshape(-1)
            break
    else:
        tet_count = int(sum(len(data.cells[i].data) for i in blocks))
        return np.zeros(tet_count, np.int64), ("tissue",)

    names_by_tag = {
        int(tag_dim[0]): name
        for name, tag_dim in (data.field_data or {}).items()
        if len(np.atleast_1d(tag_dim)) >= 2 and int(np.atleast_1d(tag_dim)[1]) == 3
    }
    if key == "region":
        labels = values
        count = int(labels.max()) + 1
        names = [names_by_tag.get(k + 1, f"region_{k}") for k in range(count)]
    else:
        tags, labels = np.unique(values, return_inverse=True)
        names = [names_by_tag.get(int(tag), f"region_{int(tag)}") for tag in tags]
    if not names_by_tag:
        names[0] = "tissue"
    return labels.astype(np.int64), tuple(names)


def write_mesh(
    mesh: TetMesh,
    path: str | Path,
    positions: NDArray[np.float64] | None = None,
    point_data: dict[str, NDArray[np.float64]] | None = None,
) -> Path:
    """Write a mesh, at rest or deformed, to any format meshio knows (by the path's suffix).

    The tets carry a ``region`` cell array (label per tet); gmsh files (binary gmsh 4.1)
    also carry the region names (physical names, tag = label + 1), which other formats
    lose (they come back as ``"tissue"``, ``"region_1"``, ...). Points carry ``fixed``
    (1 on fixed nodes) and, when ``positions`` is given, ``displacement`` [m].

    Args:
        mesh: the mesh.
        path: the output file; ``.vtu`` opens in ParaView.
        positions: deformed node positions [m], shape (node_count, 3); default rest.
        point_data: extra per-node arrays, each shape (node_count,) or (node_count, k).

    Returns:
        The path written.
    """
    import meshio

    path = Path(path)
    points = mesh.nodes if positions is None else np.asarray(positions, dtype=np.float64)
    if points.shape != mesh.nodes.shape:
        raise MeshError(
            f"positions must have shape {mesh.nodes.shape} (one row per node); got {points.shape}"
        )
    fixed = np.zeros(mesh.node_count, dtype=np.int32)
    fixed[mesh.fixed_nodes] = 1
    out_point_data: dict[str, NDArray] = {"fixed": fixed}
    if positions is not None:
        out_point_data["displacement"] = points - mesh.nodes
    for key, values in (point_data or {}).items():
        values = np.asarray(values)
        if values.shape[0] != mesh.node_count:
            raise MeshError(
                f"point_data[{key!r}] has {values.shape[0]} rows; expected one per node "
                f"({mesh.node_count})"
            )
        out_point_data[key] = values
    cell_data: dict[str, list[NDArray]] = {"region": [mesh.region.astype(np.int32)]}
    field_data: dict[str, NDArray] = {}
    if path.suffix.lower() == ".msh":
        # gmsh wants physical and geometrical tags on every cell, positive.
        cell_data["gmsh:physical"] = [(mesh.region + 1).astype(np.int32)]
        cell_data["gmsh:geometrical"] = [(mesh.region + 1).astype(np.int32)]
        field_data = {
            name: np.array([label + 1, 3]) for label, name in enumerate(mesh.region_names)
        }
    out = meshio.Mesh(
        points=points,
        cells=[("tetra", mesh.tets.astype(np.int64))],
        point_data=out_point_data,
        cell_data=cell_data,
        field_data=field_data,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    with contextlib.redirect_stdout(io.StringIO()):
        if path.suffix.lower() == ".msh":
            # meshio 5.3 writes ASCII gmsh 4.1 data blocks it cannot read back; binary is safe.
            meshio.write(path, out, file_format="gmsh", binary=True)
        else:
            meshio.write(path, out)
    return path


def save_mesh_npz(mesh: TetMesh, path: str | Path) -> Path:
    """Store a complete mesh in one ``.npz`` file, atomically (write a temporary, rename).

    A reader never sees a half-written file, and two processes generating the same mesh at
    once both end with a valid file.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays: dict[str, NDArray] = {
        "format": np.array(_NPZ_FORMAT),
        "nodes": mesh.nodes,
        "tets": mesh.tets,
        "region": mesh.region,
        "fixed_nodes": mesh.fixed_nodes,
        "region_names": np.array(json.dumps(list(mesh.region_names))),
        "name": np.array(mesh.name),
        "metadata": np.array(json.dumps(mesh.metadata, default=_json_default)),
    }
    if mesh.collision_surface is not None:
        arrays["collision_vertices"] = mesh.collision_surface.rest_vertices
        arrays["collision_triangles"] = mesh.collision_surface.triangles
    if mesh.landmarks is not None:
        arrays["landmark_names"] = np.array(json.dumps(list(mesh.landmarks.names)))
        arrays["landmark_positions"] = mesh.landmarks.rest_positions
    handle, temporary = tempfile.mkstemp(prefix=path.name, suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(handle, "wb") as stream:
            np.savez(stream, **arrays)  # type: ignore[arg-type]
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def load_mesh_npz(path: str | Path) -> TetMesh:
    """Read a mesh written by :func:`save_mesh_npz` (embeddings are recomputed).

    Metadata lists come back as numpy arrays, so metadata that held arrays round-trips.

    Raises:
        MeshError: the file is missing, not such a file, or of another format version.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: data[key] for key in data.files}
    except (OSError, ValueError) as error:
        raise MeshError(f"cannot read mesh archive {str(path)!r}: {error}") from error
    if int(arrays.get("format", -1)) != _NPZ_FORMAT:
        raise MeshError(
            f"{str(path)!r} is not a probegym mesh archive of format {_NPZ_FORMAT}; "
            "delete it to regenerate"
        )
    mesh = TetMesh(
        nodes=arrays["nodes"],
        tets=arrays["tets"],
        region=arrays["region"],
        fixed_nodes=arrays["fixed_nodes"],
        region_names=tuple(json.loads(str(arrays["region_names"]))),
        name=str(arrays["name"]),
        metadata={
            key: np.asarray(value) if isinstance(value, list) else value
            for key, value in json.loads(str(arrays["metadata"])).items()
        },
    )
    if "collision_vertices" in arrays:
        mesh = mesh.with_collision_surface(
            arrays["collision_vertices"], arrays["collision_triangles"]
        )
    if "landmark_positions" in arrays:
        names = tuple(json.loads(str(arrays["landmark_names"])))
        mesh = mesh.with_landmarks(names, arrays["landmark_positions"])
    return mesh


def _json_default(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"metadata value of type {type(value).__name__} is not JSON-serialisable")
