"""Structured tetrahedral blocks: test specimens for analytic checks and quick experiments."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from tissue.errors import MeshError
from tissue.mesh import TetMesh
from tissue.mesh.io import nodes_on_plane

# Kuhn (Freudenthal) split of the unit cube into six positively oriented tets that share the
# main diagonal 0-7; neighbouring cubes then agree on every face, so the mesh is conforming.
_CUBE_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]]
)
_KUHN_TETS = np.array(
    [[0, 1, 3, 7], [0, 3, 2, 7], [0, 2, 6, 7], [0, 6, 4, 7], [0, 4, 5, 7], [0, 5, 1, 7]]
)


def block_mesh(
    size_m: tuple[float, float, float],
    divisions: tuple[int, int, int],
    origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    fix: str | None = "z=min",
    grading: tuple[float, float, float] = (1.0, 1.0, 1.0),
    ticks_m: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> TetMesh:
    """A box of size_m [m] split into divisions cubes, each cut into six tets.

    Args:
        size_m: edge lengths along x, y, z [m].
        divisions: cells along x, y, z (each >= 1).
        origin_m: the corner with the smallest coordinates [m].
        fix: nodes held fixed: ``"z=min"`` style (axis and side), or None for none.
        grading: per axis, the ratio of the last cell's size to the first's (1 = uniform),
            to refine near the origin side.
        ticks_m: explicit node coordinates per axis [m], increasing (overrides size_m,
            divisions, origin_m and grading), e.g. from :func:`centred_ticks`.

    Returns:
        a TetMesh with one region ("tissue").
    """
    if ticks_m is not None:
        axes = [np.asarray(t, dtype=np.float64) for t in ticks_m]
        if any(t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0) for t in axes):
            raise MeshError("ticks_m must be three increasing coordinate arrays of >= 2 values")
        divisions = (axes[0].size - 1, axes[1].size - 1, axes[2].size - 1)
    else:
        if any(d < 1 for d in divisions):
            raise MeshError(f"divisions must be >= 1 along every axis; got {divisions}")
        if any(not s > 0 for s in size_m):
            raise MeshError(f"size_m must be positive along every axis; got {size_m}")
        axes = _graded_axes(size_m, divisions, origin_m, grading)
    nx, ny, nz = (d + 1 for d in divisions)
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def index(i, j, k):
        return (i * ny + j) * nz + k

    cells = np.meshgrid(
        np.arange(divisions[0]), np.arange(divisions[1]), np.arange(divisions[2]), indexing="ij"
    )
    i, j, k = (c.reshape(-1) for c in cells)
    corners = np.stack([index(i + a, j + b, k + c) for a, b, c in _CUBE_CORNERS], axis=1)
    tets = corners[:, _KUHN_TETS].reshape(-1, 4)
    fixed = np.zeros(0, dtype=np.int64) if fix is None else nodes_on_plane(grid, fix)
    return TetMesh(
        nodes=grid,
        tets=tets,
        region=np.zeros(tets.shape[0], dtype=np.int64),
        fixed_nodes=fixed,
        name=f"block {divisions} cells",
    )


def _graded_axes(size_m, divisions, origin_m, grading) -> list[NDArray[np.float64]]:
    axes = []
    for length, count, ratio, start in zip(size_m, divisions, grading, origin_m, strict=True):
        if ratio == 1.0:
            ticks = np.linspace(0.0, 1.0, count + 1)
        else:
            widths = ratio ** (np.arange(count) / max(count - 1, 1))
            ticks = np.concatenate([[0.0], np.cumsum(widths) / widths.sum()])
        axes.append(start + length * ticks)
    return axes


def graded_ticks(
    length_m: float,
    finest_m: float,
    coarsest_m: float,
    growth: float = 1.25,
    uniform_m: float = 0.0,
) -> NDArray[np.float64]:
    """Coordinates from 0 to ``length_m``, finest at 0 and growing away from it [m].

    Cells of ``finest_m`` cover ``[0, uniform_m]`` (rounded up to whole cells), then grow
    geometrically by ``growth`` up to ``coarsest_m``; the graded cells are scaled slightly so
    that the last tick lands exactly on ``length_m`` (the uniform cells keep their size).
    For contact tests: fine under the indenter, coarse far away.
    """
    if not 0 < finest_m <= coarsest_m < length_m or growth < 1.0 or not 0.0 <= uniform_m < length_m:
        raise MeshError(
            "need 0 < finest_m <= coarsest_m < length_m, 0 <= uniform_m < length_m and "
            f"growth >= 1; got {finest_m}, {coarsest_m}, {length_m}, {uniform_m}, {growth}"
        )
    uniform_count = math.ceil(uniform_m / finest_m - 1e-9)
    uniform = finest_m * np.arange(uniform_count + 1)
    if uniform[-1] >= length_m - finest_m:
        raise MeshError(
            f"the uniform part ({uniform[-1]} m) leaves no room for graded cells before "
            f"{length_m} m"
        )
    start = float(uniform[-1])
    graded = _grown_ticks(length_m - start, finest_m, coarsest_m, growth)
    return np.concatenate([uniform, start + graded[1:]])


def _grown_ticks(length: float, first: float, cap: float, growth: float) -> NDArray[np.float64]:
    """Ticks from 0 to ``length``: widths from ``first`` times ``growth`` per cell up to
    ``cap``, all scaled by the one factor that makes the last tick land on ``length``."""
    widths = []
    total, width = 0.0, first
    while total < length:
        widths.append(width)
        total += width
        width = min(width * growth, cap)
    ticks = np.concatenate([[0.0], np.cumsum(widths)])
    return ticks * (length / ticks[-1])


def centred_ticks(
    half_length_m: float,
    finest_m: float,
    coarsest_m: float,
    growth: float = 1.25,
    uniform_half_m: float = 0.0,
) -> NDArray[np.float64]:
    """Coordinates from -half_length to +half_length, finest at 0 and growing outwards [m].

    Cells of ``finest_m`` cover ``[-uniform_half_m, uniform_half_m]`` (rounded up to whole
    cells), then grow geometrically by ``growth`` up to ``coarsest_m`` (for contact tests:
    fine under the indenter, coarse far away); see :func:`graded_ticks`.
    """
    if not 0 < finest_m <= coarsest_m < half_length_m or growth < 1.0:
        raise MeshError(
            "need 0 < finest_m <= coarsest_m < half_length_m and growth >= 1; got "
            f"{finest_m}, {coarsest_m}, {half_length_m}, {growth}"
        )
    half = graded_ticks(half_length_m, finest_m, coarsest_m, growth, uniform_half_m)
    return np.concatenate([-half[:0:-1], half])


# Faces of the core's buried boundary (sides and bottom of the half cube), each as the grid
# axis held at its first (0) or last (-1) index. The two other axes span the face in
# increasing global order, so the shell cells built on it split along the same face
# diagonals as their neighbours, across the core's edges too.
_CORE_FACES = ((0, 0), (0, -1), (1, 0), (1, -1), (2, 0))
# Coarsening stops before the shells' side faces would have fewer cells than this in depth
# (8 across the base): coarser grids resolve the far field's angular variation poorly.
_MIN_SIDE_CELLS = 4


def half_space_mesh(
    finest_m: float,
    core_half_m: float,
    extent_m: float,
    growth: float = 1.3,
    fix: str | None = "z=min",
    symmetric: bool = True,
    coarsen_ratio: float | None = None,
) -> TetMesh:
    """A graded block standing in for an elastic half-space under a small indenter.

    The free surface is the plane z = 0 and the block fills x, y in [-extent, extent],
    z in [-extent, 0]. A uniform core of cells about ``finest_m`` covers
    x, y in [-core_half, core_half], z in [-core_half, 0] (put the contact there); around it,
    shells that are scaled copies of the core's buried boundary grow outwards, their radial
    thickness starting at the core's cell size and growing by ``growth`` per shell, until
    ``extent_m``. So the cells grow with the distance from the contact in every direction,
    and a block hundreds of contact radii wide costs tens of thousands of tets instead of the
    hundreds of thousands a tensor-product graded grid (:func:`block_mesh` with ticks) needs.

    Every shell cell is a convex frustum split like the core's cubes (Kuhn), along face
    diagonals its neighbours share: the mesh is conforming. With ``coarsen_ratio``, the
    shells' grid on the faces is also halved each time the shell's half size passes
    ``core_half_m`` times the next power of ``coarsen_ratio``, while the face cell counts
    stay even and at least 8 across the base: a layer of transition cells, each a frustum
    from 2 x 2 fine quads to one coarse quad split into tets about a point at its centre,
    joins the two grids. A core of 16 cells across coarsens once, of 32 twice.

    Args:
        finest_m: largest cell size in the core [m].
        core_half_m: half width (and depth) of the uniform core [m].
        extent_m: half width (and depth) of the block [m], > core_half_m.
        growth: ratio of successive shells' radial thickness (>= 1).
        fix: nodes held fixed: a plane spec such as ``"z=min"`` (the base), ``"outer"``
            for the whole buried boundary (base and sides), or None.
        symmetric: mirror each cell's split by the parity of its index (see
            :func:`_split_hexes`), so the mesh is symmetric about x = 0 and y = 0.
        coarsen_ratio: (> 1) halve the shells' face grid at these radius ratios; None keeps
            the core's face grid all the way out.

    Returns:
        a TetMesh with one region ("tissue").
    """
    if not (0 < finest_m <= core_half_m < extent_m) or growth < 1.0:
        raise MeshError(
            "need 0 < finest_m <= core_half_m < extent_m and growth >= 1; got "
            f"{finest_m}, {core_half_m}, {extent_m}, {growth}"
        )
    if coarsen_ratio is not None and not coarsen_ratio > 1.0:
        raise MeshError(f"coarsen_ratio must be > 1 (or None); got {coarsen_ratio}")
    half_cells = math.ceil(core_half_m / finest_m - 1e-9)
    cell = core_half_m / half_cells
    across = np.linspace(-core_half_m, core_half_m, 2 * half_cells + 1)
    depth = np.linspace(-core_half_m, 0.0, half_cells + 1)
    core_nodes = np.stack(np.meshgrid(across, across, depth, indexing="ij"), axis=-1)
    shape = core_nodes.shape[:3]
    core_nodes = core_nodes.reshape(-1, 3)
    grid_index = np.arange(core_nodes.shape[0]).reshape(shape)
    cells = np.meshgrid(*(np.arange(n - 1) for n in shape), indexing="ij")
    i, j, k = (c.reshape(-1) for c in cells)
    core_hexes = np.stack([grid_index[i + a, j + b, k + c] for a, b, c in _CUBE_CORNERS], axis=1)
    tets = [_split_hexes(core_hexes, np.stack([i, j, k], axis=1), symmetric)]
    # Shell radii (half sizes): the first shell is one core cell thick, then each grows.
    radii = core_half_m + _grown_ticks(extent_m - core_half_m, cell, extent_m, growth)
    # The core's buried faces as 2D arrays of core node ids; a layer's nodes are the scaled
    # copies of the face nodes on its grid (every ``stride``-th node of the core's).
    faces = []
    for axis, end in _CORE_FACES:
        index: list[slice | int] = [slice(None)] * 3
        index[axis] = end
        faces.append(grid_index[tuple(index)])
    points = [core_nodes]
    count = core_nodes.shape[0]
    inner_ids = np.arange(count)  # core node id -> global id on the current layer
    stride, coarsened = 1, 0
    for layer in range(1, radii.size):
        coarsen = (
            coarsen_ratio is not None
            and radii[layer - 1] >= core_half_m * coarsen_ratio ** (coarsened + 1)
            and all((n - 1) % (2 * stride) == 0 for face in faces for n in face.shape)
            and (shape[2] - 1) // (2 * stride) >= _MIN_SIDE_CELLS
        )
        outer_stride = 2 * stride if coarsen else stride
        members = np.unique(
            np.concatenate([f[::outer_stride, ::outer_stride].ravel() for f in faces])
        )
        outer_ids = np.full(core_nodes.shape[0], -1, dtype=np.int64)
        outer_ids[members] = count + np.arange(members.size)
        points.append(core_nodes[members] * (radii[layer] / core_half_m))
        count += members.size
        for face in faces:
            inner = inner_ids[face[::stride, ::stride]]
            outer = outer_ids[face[::outer_stride, ::outer_stride]]
            if coarsen:
                centres, cone = _transition_cells(
                    inner, outer, np.concatenate(points), count, symmetric
                )
                points.append(centres)
                count += centres.shape[0]
                tets.append(cone)
            else:
                hexes, index_ab = _frustums(inner, outer)
                layer_index = np.full((hexes.shape[0], 1), layer - 1)
                tets.append(_split_hexes(hexes, np.hstack([index_ab, layer_index]), symmetric))
        inner_ids, stride = outer_ids, outer_stride
        coarsened += int(coarsen)
    nodes = np.concatenate(points)
    all_tets = np.concatenate(tets)
    # Mirrored splits and faces mirrored across the core make some tets left-handed.
    a, b, c, d = (nodes[all_tets[:, k]] for k in range(4))
    negative = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) < 0.0
    all_tets[negative] = all_tets[negative][:, [0, 1, 3, 2]]
    if fix is None:
        fixed = np.zeros(0, dtype=np.int64)
    elif fix == "outer":
        fixed = inner_ids[inner_ids >= 0]
    else:
        fixed = nodes_on_plane(nodes, fix)
    return TetMesh(
        nodes=nodes,
        tets=all_tets,
        region=np.zeros(all_tets.shape[0], dtype=np.int64),
        fixed_nodes=fixed,
        name=f"half-space block ({2 * half_cells} core cells, {radii.size - 1} shells)",
    )


def _frustums(
    inner: NDArray[np.int64], outer: NDArray[np.int64]
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Hexahedra between two node grids of one shape, corners in Kuhn order (a + 2 b + 4 w,
    a and b along the grid, w outwards), (h, 8); and each one's cell index (a, b), (h, 2)."""
    nu, nv = inner.shape[0] - 1, inner.shape[1] - 1
    corners = [
        grid[a : a + nu, b : b + nv].ravel()
        for grid in (inner, outer)
        for b in (0, 1)
        for a in (0, 1)
    ]
    u, v = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    return np.stack(corners, axis=1), np.stack([u.ravel(), v.ravel()], axis=1)


def _transition_cells(
    inner: NDArray[np.int64],
    outer: NDArray[np.int64],
    nodes: NDArray[np.float64],
    first: int,
    symmetric: bool,
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Tets joining a fine node grid to the grid of every other node, one layer out.

    Each cell spans 2 x 2 fine quads (inner) and one coarse quad (outer). Its faces are
    triangulated as its neighbours triangulate them: the fine quads and the coarse quad along
    the diagonals :func:`_split_hexes` gives them in the shells on either side (with
    ``symmetric``, the main diagonal where the quad's two index parities agree; else always
    the main one), each side face as three triangles with the fine edge's midpoint joined to
    both coarse corners. The cell is a convex frustum, so a point at its centre joined to
    those 22 triangles fills it with tets.

    Args:
        inner: fine grid of global node ids, (2 m + 1, 2 n + 1).
        outer: coarse grid, (m + 1, n + 1).
        nodes: all node positions so far [m], for the centres.
        first: the global id the first centre gets.
        symmetric: whether the shells' splits are mirrored by index parity.

    Returns:
        the centres [m], (m n, 3), and the tets, (22 m n, 4).
    """
    m, n = outer.shape[0] - 1, outer.shape[1] - 1
    grid_u, grid_v = np.meshgrid(np.arange(m), np.arange(n), indexing="ij")
    uu, vv = grid_u.ravel(), grid_v.ravel()

    def fine(du: int, dv: int) -> NDArray[np.int64]:
        return inner[2 * uu + du, 2 * vv + dv]

    def coarse(du: int, dv: int) -> NDArray[np.int64]:
        return outer[uu + du, vv + dv]

    triangles = []
    for qu in (0, 1):  # the four fine quads
        for qv in (0, 1):
            c00, c10 = fine(qu, qv), fine(qu + 1, qv)
            c01, c11 = fine(qu, qv + 1), fine(qu + 1, qv + 1)
            main = ((2 * uu + qu) % 2 == (2 * vv + qv) % 2) | (not symmetric)
            triangles += _split_quad(c00, c10, c01, c11, main)
    main = (uu % 2 == vv % 2) | (not symmetric)
    triangles += _split_quad(coarse(0, 0), coarse(1, 0), coarse(0, 1), coarse(1, 1), main)
    sides = (
        ((0, 0), (0, 1), (0, 2), (0, 0), (0, 1)),  # a = 0
        ((2, 0), (2, 1), (2, 2), (1, 0), (1, 1)),  # a = 1
        ((0, 0), (1, 0), (2, 0), (0, 0), (1, 0)),  # b = 0
        ((0, 2), (1, 2), (2, 2), (0, 1), (1, 1)),  # b = 1
    )
    for f0, fm, f1, o0, o1 in sides:
        i0, im, i1 = fine(*f0), fine(*fm), fine(*f1)
        j0, j1 = coarse(*o0), coarse(*o1)
        triangles += [(i0, im, j0), (im, j1, j0), (im, i1, j1)]
    corner_ids = np.stack(
        [fine(0, 0), fine(2, 0), fine(0, 2), fine(2, 2)]
        + [coarse(0, 0), coarse(1, 0), coarse(0, 1), coarse(1, 1)],
        axis=1,
    )
    centres = nodes[corner_ids].mean(axis=1)
    apex = first + np.arange(uu.size)
    cone = [np.stack([apex, *triangle], axis=1) for triangle in triangles]
    return centres, np.concatenate(cone)


def _split_quad(c00, c10, c01, c11, main):
    """Two triangles of quads (corners by (a, b)), along 00-11 where ``main``, else 10-01."""
    first = (c00, c10, np.where(main, c11, c01))
    second = (np.where(main, c00, c10), c11, c01)
    return [first, second]


def _split_hexes(
    hexes: NDArray[np.int64], cell_index: NDArray[np.int64], symmetric: bool
) -> NDArray[np.int64]:
    """Six tets per hexahedron (corners in Kuhn order, (h, 8)), (6 h, 4).

    With ``symmetric``, each cell's Kuhn split is mirrored along every axis where its integer
    cell index (``cell_index``, (h, 3)) is odd: neighbours still share face diagonals (both
    mirror by the indices they share), and a grid plane with the same number of cells on
    either side (x = 0 and y = 0 of :func:`half_space_mesh`) is a mirror plane of the mesh,
    without the single preferred diagonal direction of a plain Kuhn split.
    """
    if not symmetric:
        return hexes[:, _KUHN_TETS].reshape(-1, 4)
    mask = (cell_index % 2) @ np.array([1, 2, 4])
    local = _KUHN_TETS[None, :, :] ^ mask[:, None, None]  # (h, 6, 4) corner numbers
    rows = np.arange(hexes.shape[0])[:, None, None]
    return hexes[rows, local].reshape(-1, 4)
