"""Has the probe passed through the tissue? A check made after every step.

Contact strategies keep points (skin vertices, boundary nodes) out of the probe. A probe
moving far in one step, or tissue flowing around it, can leave every such point outside the
probe while the tissue's surface cuts through it: the probe is then behind the surface, and
the tissue it should press is not pressed (the force falls to zero or pulls). Splitting a
step's motion (:meth:`tissue.contact.base.ContactModel.step`) prevents most of it; this check
reports what remains.

The test: five points on the face's centre line, inside the probe's body half its thinnest
dimension behind the face (the depth a step's sub-motion never exceeds), are tested for lying
inside the deformed volume (its boundary faces, a closed surface) by casting a ray from each
and counting the faces it crosses (odd: inside; Moller & Trumbore 1997 ray-triangle
intersection). When half of them or more are inside *and* the tissue does not push the probe
back (its force along the pressing direction is under 1 mN), the probe has passed through:
the step is ``tunnelled``. Both halves matter: where the tissue wraps a deeply pressed probe,
a coarse boundary face can bridge over its body from one side to the other (the published
scene's level-4 poses; sticking prescribed displacement on a 45-degree flank), yet the face
still presses the tissue; and a probe in the air or just touching has no samples inside.
The volume's boundary, not the collision surface: a fine collision surface embedded in a
coarse volume can fold over the probe where a method holds the boundary nodes, while the
volume is pressed as it should be. Skin that is only a little inside the probe is reported
as the step's skin penetration.

Limitations: the samples lie on the face's centre line; a probe that passes through the
tissue with its side or its back is not seen, nor one that still feels a push.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from tissue.probe import Probe

# Samples are inset this far from the face's outline [m]: between skin vertices wrapped
# round the face's rounded rim, skin triangles cut chords into the probe's corners.
_INSET_M = 0.003
_SAMPLES = 5


def face_samples(probe: Probe) -> NDArray[np.float64]:
    """The check's sample points in the probe frame [m], (at most 5, 3): on the face's
    centre line, :data:`_INSET_M` inside its outline, half the probe's thinnest dimension
    behind the face (the depth a step's sub-motion never exceeds). None where the probe is
    too small to hold one."""
    low, high = probe.shape.local_bounds_m()
    depth = 0.5 * float(np.min(high - low))
    xs = np.linspace(low[0], high[0], 4 * _SAMPLES + 1)
    line = np.column_stack([xs, np.full(xs.size, -depth), np.zeros(xs.size)])
    distance, _ = probe.shape.signed_distance(line)
    inside = line[distance <= -_INSET_M]
    if inside.shape[0] == 0:
        return inside
    picks = np.unique(np.round(np.linspace(0, inside.shape[0] - 1, _SAMPLES)).astype(int))
    return inside[picks]


def skin_behind_probe(
    probe: Probe,
    samples_probe: NDArray[np.float64],
    surface_vertices: NDArray[np.float64],
    triangles: NDArray[np.int64],
) -> bool:
    """Whether at least half the sample points (probe frame [m], (s, 3)) lie inside the
    closed surface (vertices [m] (v, 3), outward triangles (t, 3)) with the probe at its
    pose. Half, not any: one face bridging over a deep probe's body holds one or two."""
    if samples_probe.shape[0] == 0:
        return False
    points = probe.to_world_frame(samples_probe)
    # Along the probe's -y axis: out through its back, away from the tissue it presses.
    direction = -probe.pressing_direction_world()
    inside = int(_count_inside(points, direction, surface_vertices, triangles))
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
