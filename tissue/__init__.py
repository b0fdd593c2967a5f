"""probegym's finite-element tissue simulator: the front door.

Knows nothing of MuJoCo, Gymnasium or torch. Everything outside ``tissue`` (the
environments, the viewer, the command line, a user's script) drives it through these names::

    import tissue

    t = tissue.make_tissue(tissue.TissueSpec(mesh=1363, contact="lm", profile="robust"))
    position, quat = t.touching_pose(t.lesions[0].rest_centre_m)
    t.reset(position, quat)
    for k in range(1, 51):  # 10 mm along the probe's +y axis at 0.01 m/s
        s = t.step(position + 0.0002 * k * tissue.pressing_direction(quat), quat)
    print(s.status, s.force_world_n, s.lesion_centroids_world_m[0])

The probe frame: origin at the centre of the contact face, +y the pressing direction, x the
face's long axis (the image's lateral axis), z its short axis (elevation); quaternions are
(w, x, y, z). Units are SI. Importing this package sets nothing process-wide: the thread
policy is :func:`configure_threads`, which the command line and the environments call (and
which a tissue applies with its defaults if no one did).
"""

from tissue.contact.base import ContactMethod
from tissue.errors import ConfigError, MaterialError, MeshError, TissueInputError
from tissue.fem.material import NeoHookean, TissueMaterials
from tissue.lesions import Lesion
from tissue.model import (
    StepDiagnostics,
    Tissue,
    TissueState,
    TissueStep,
    make_tissue,
    pressing_direction,
)
from tissue.probe import ProbeShape
from tissue.spec import PUBLISHED_SCENE, Profile, TissueSpec
from tissue.status import StepStatus
from tissue.surface_mesh import SurfaceMesh
from tissue.threads import ThreadPolicy, configure_threads

__all__ = [
    "PUBLISHED_SCENE",
    "ConfigError",
    "ContactMethod",
    "Lesion",
    "MaterialError",
    "MeshError",
    "NeoHookean",
    "ProbeShape",
    "Profile",
    "StepDiagnostics",
    "StepStatus",
    "SurfaceMesh",
    "ThreadPolicy",
    "Tissue",
    "TissueInputError",
    "TissueMaterials",
    "TissueSpec",
    "TissueState",
    "TissueStep",
    "configure_threads",
    "make_tissue",
    "pressing_direction",
]
