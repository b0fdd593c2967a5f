"""Has the probe passed through the skin? A check made after every step.

Contact strategies keep points (skin vertices, boundary nodes) out of the probe. A probe
moving far in one step, or tissue flowing around it, can leave every such point outside the
probe while a skin *triangle* cuts through it: the probe is then behind the skin, and the
tissue it should press is not pressed (the force falls to zero or pulls). Splitting a step's
motion (:meth:`tissue.contact.base.ContactModel.step`) prevents most of it; this check reports
what remains.

The test: sample points inside the probe's body, half its thinnest dimension behind the face
(the depth the step's sub-motions never exceed; deeper on a skin coarser than that, see
:func:`face_samples`) and inset from its outline, are tested for
being inside the deformed skin (a closed triangle surface) by casting a ray from each and
counting the skin triangles it crosses (odd: inside; Moller & Trumbore 1997 ray-triangle
intersection). Points behind the face yet inside the tissue mean the skin lies behind the
probe's mid-plane there: where half the samples or more are, the step is ``tunnelled``.
Skin that is only a little inside the probe (less than that depth) is not flagged: it is
reported as the step's skin penetration.

Limitations: the samples lie on the face's centre line (five along its length); a probe that passes
through the skin with its side or its back is not seen. The skin must be closed (the
phantom's and the published scene's collision surfaces are; a volume's boundary is).
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.probe import Probe

# Samples are inset this far from the face's outline [m]: between skin vertices wrapped
# round the face's rounded rim, skin triangles cut chords into the probe's corners.
_INSET_M = 0.003
_GRID = (5, 1)


def face_samples(probe: Probe, skin_edge_m: float) -> NDArray[np.float64]:
    """The check's sample points in the probe frame [m], (k, 3): a line along the face, at
    half the probe's thinnest dimension behind the face or at the skin's mean edge length
    ``skin_edge_m`` [m] if that is deeper, keeping the points at least
    max(:data:`_INSET_M`, half an edge) inside the probe's outline. A skin triangle bridging
    from a vertex on the face to one up the probe's side cuts into the probe's corner by a
    few millimetres (measured: 3.5-6 mm for 9.5 mm triangles round the linear face's end);
    the depth and the inset keep such chords away from the samples. None where that depth
    lies beyond the probe's back: a probe thinner than the skin's triangles cannot be told
    from one the skin drapes over."""
    bounds = probe.shape.local_bounds_m()
    low, high = bounds
    depth = max(0.5 * float(np.min(high - low)), skin_edge_m)
    if depth >= -low[1]:
        return np.zeros((0, 3))
    xs = np.linspace(low[0], high[0], 4 * _GRID[0] + 1)
    zs = np.linspace(low[2], high[2], 4 * _GRID[1] + 1)
    grid = np.array([(x, -depth, z) for x in xs for z in zs])
    distance, _ = probe.shape.signed_distance(grid)
    inside = grid[distance <= -max(_INSET_M, 0.5 * skin_edge_m)]
    if inside.shape[0] == 0:
        return inside
    # At most _GRID points each way, spread evenly over those kept (the outermost included).
    chosen = np.ones(inside.shape[0], dtype=bool)
    for axis, count in ((0, _GRID[0]), (2, _GRID[1])):
        values = np.unique(inside[:, axis])
        if count == 1:
            picks = values[[(values.size - 1) // 2]]  # the middle one
        else:
            picks = values[np.unique(np.round(np.linspace(0, values.size - 1, count)).astype(int))]
        chosen &= np.isin(inside[:, axis], picks)
    return inside[chosen]


def skin_behind_probe(
    probe: Probe,
    samples_probe: NDArray[np.float64],
    skin_vertices: NDArray[np.float64],
    triangles: NDArray[np.int64],
) -> bool:
    """Whether at least half the sample points (probe frame [m], (s, 3)) lie inside the
    closed skin (vertices [m] (v, 3), outward triangles (t, 3)) with the probe at its pose.

    Half, not any: where the skin wraps both sides of a deep probe, one coarse skin triangle
    can bridge from one side to the other over the probe's body and hold one or two samples
    (measured on the published scene's level-4 poses: 10 mm triangles across the 13.2 mm
    face, 1 sample of 15); a probe that passed through the skin has its face behind it."""
    if samples_probe.shape[0] == 0:
        return False
    points = probe.to_world_frame(samples_probe)
    # Along the probe's -y axis: out through its back, away from the tissue it presses.
    direction = -probe.pressing_direction_world()
    inside = int(_count_inside(points, direction, skin_vertices, triangles))
    return 2 * inside >= samples_probe.shape[0]


@numba.njit(cache=True)
def _count_inside(points, direction, vertices, triangles):  # pragma: no cover - compiled
    inside = 0
    for s in range(points.shape[0]):
        crossings = 0
        ox, oy, oz = points[s, 0], points[s, 1], points[s, 2]
        dx, dy, dz = direction[0], direction[1], direction[2]
        for t in range(triangles.shape[0]):
            a = triangles[t, 0]
            b = triangles[t, 1]
            c = triangles[t, 2]
            e1x = vertices[b, 0] - vertices[a, 0]
            e1y = vertices[b, 1] - vertices[a, 1]
            e1z = vertices[b, 2] - vertices[a, 2]
            e2x = vertices[c, 0] - vertices[a, 0]
            e2y = vertices[c, 1] - vertices[a, 1]
            e2z = vertices[c, 2] - vertices[a, 2]
            px = dy * e2z - dz * e2y
            py = dz * e2x - dx * e2z
            pz = dx * e2y - dy * e2x
            det = e1x * px + e1y * py + e1z * pz
            if abs(det) < 1e-30:
                continue
            inv = 1.0 / det
            sx = ox - vertices[a, 0]
            sy = oy - vertices[a, 1]
            sz = oz - vertices[a, 2]
            u = (sx * px + sy * py + sz * pz) * inv
            if u < 0.0 or u > 1.0:
                continue
            qx = sy * e1z - sz * e1y
            qy = sz * e1x - sx * e1z
            qz = sx * e1y - sy * e1x
            v = (dx * qx + dy * qy + dz * qz) * inv
            if v < 0.0 or u + v > 1.0:
                continue
            if (e2x * qx + e2y * qy + e2z * qz) * inv > 0.0:
                crossings += 1
        if crossings % 2 == 1:
            inside += 1
    return inside
