"""Structured tetrahedral blocks: test specimens for analytic checks and quick experiments."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tissue.errors import MeshError
from tissue.mesh import TetMesh
from tissue.mesh_io import nodes_on_plane

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


def centred_ticks(
    half_length_m: float, finest_m: float, coarsest_m: float, growth: float = 1.25
) -> NDArray[np.float64]:
    """Coordinates from -half_length to +half_length, finest at 0 and growing outwards [m].

    Cells start at ``finest_m`` around 0 and grow geometrically by ``growth`` up to
    ``coarsest_m`` (for contact tests: fine under the indenter, coarse far away).
    """
    if not 0 < finest_m <= coarsest_m < half_length_m or growth < 1.0:
        raise MeshError(
            "need 0 < finest_m <= coarsest_m < half_length_m and growth >= 1; got "
            f"{finest_m}, {coarsest_m}, {half_length_m}, {growth}"
        )
    widths = []
    total, width = 0.0, finest_m
    while total < half_length_m:
        widths.append(width)
        total += width
        width = min(width * growth, coarsest_m)
    half = np.cumsum(widths)
    half *= half_length_m / half[-1]  # land exactly on the boundary
    return np.concatenate([-half[::-1], [0.0], half])
