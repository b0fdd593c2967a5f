"""The rigid probe: tool geometry with an exact signed distance, and its pose.

The probe never deforms; it moves. Contact strategies ask it one question, the signed
distance from points (tissue surface vertices) to its surface with the direction that
pushes a penetrating point out, and hand back contact forces for the wrench.

Frame convention (every shape): the probe frame's origin is the centre of the contact face
(or the point of first contact of a round shape), the face lies in the y = 0 plane, the
body extends to y < 0 (the handle side), and the probe presses along its +y axis. So the
probe's position is where it touches the skin, and the world image of the probe's +y axis
is the pressing direction. For the default linear probe face, x is the long axis (the US
image's lateral axis) and z the short one (elevation), as in ``us_probe_collision.stl``.

Shapes (:class:`ProbeShape`, in :mod:`tissue.probe.shape`):

- :class:`LinearProbeFace` (default): the linear probe's face, a rounded slab about
  52.9 x 2.7 x 13.2 mm (x, y, z) whose extents match the published collision STL.
- :class:`BoxProbe`, :class:`SphereProbe`, :class:`CylinderProbe`: analytic shapes with
  exact signed distances (the cylinder is a flat circular punch, axis along y); these and
  the face are in :mod:`tissue.probe.analytic`, their compiled SDFs in
  :mod:`tissue.probe.sdf`.
- :class:`MeshProbe` (:mod:`tissue.probe.mesh`): any closed triangle mesh, exact
  point-triangle distance (numba), the sign from the nearest face's normal or, near edges
  and vertices, the winding number.

Build one from a command-line spec with :func:`parse_probe_spec` (:mod:`tissue.probe.spec`);
pose it with :class:`Probe` (:mod:`tissue.probe.pose`). A pose is probe-to-world
(p_world = R p_probe + position), which is how the published
``ground_truth/tumorN/Transform*.txt`` files read: with them the probe moves along its own
+y axis into the phantom from level 0 to level 4. Quaternions are (w, x, y, z), MuJoCo's
convention (:mod:`tissue.probe.rotation`).
"""

from tissue.probe.analytic import (
    FACE_CORNER_RADIUS_M,
    FACE_EDGE_RADIUS_M,
    FACE_LENGTH_M,
    FACE_THICKNESS_M,
    FACE_WIDTH_M,
    PROBE_BODY_DEPTH_M,
    BoxProbe,
    CylinderProbe,
    LinearProbeFace,
    SphereProbe,
    linear_probe,
)
from tissue.probe.mesh import MeshProbe, load_probe_mesh
from tissue.probe.pose import Probe
from tissue.probe.rotation import matrix_to_quat, quat_to_matrix, unit_quat_to_matrix
from tissue.probe.shape import PROBE_SPEC_FORMS, ProbeShape
from tissue.probe.spec import parse_probe_spec

__all__ = [
    "FACE_CORNER_RADIUS_M",
    "FACE_EDGE_RADIUS_M",
    "FACE_LENGTH_M",
    "FACE_THICKNESS_M",
    "FACE_WIDTH_M",
    "PROBE_BODY_DEPTH_M",
    "PROBE_SPEC_FORMS",
    "BoxProbe",
    "CylinderProbe",
    "LinearProbeFace",
    "MeshProbe",
    "Probe",
    "ProbeShape",
    "SphereProbe",
    "linear_probe",
    "load_probe_mesh",
    "matrix_to_quat",
    "parse_probe_spec",
    "quat_to_matrix",
    "unit_quat_to_matrix",
]
