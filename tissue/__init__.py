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
policy is :func:`configure_threads`, which the command line and the environments call (an
environment keeps a policy already in force; a tissue applies the defaults if no one called
it). A tissue under 40,000 unknowns (every phantom level up to 26,220 tets) steps to the same
bits on any number of threads; above, the FE methods' last digits follow the thread count.
"""

import tissue.pbd  # noqa: F401  (PBD, a tissue backend of its own, registers its strategy)
from tissue.contact.base import ContactModel
from tissue.contact.registry import (
    contact_class,
    contact_methods,
    register_contact,
    unregister_contact,
)
from tissue.contact.sleep import SLEEP_SPEED_M_S
from tissue.errors import ConfigError, MaterialError, MeshError, TissueInputError
from tissue.fem.material import NeoHookean, TissueMaterials
from tissue.lesions import Lesion
from tissue.model import Tissue, TissueState, make_tissue, pressing_direction
from tissue.probe import ProbeShape
from tissue.profile import Profile
from tissue.spec import PUBLISHED_SCENE, TissueSpec
from tissue.status import StepStatus
from tissue.step_result import StepDiagnostics, TissueStep
from tissue.surface_mesh import SurfaceMesh
from tissue.threads import ThreadPolicy, configure_threads

__all__ = [
    "PUBLISHED_SCENE",
    "SLEEP_SPEED_M_S",
    "ConfigError",
    "ContactModel",
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
    "contact_class",
    "contact_methods",
    "make_tissue",
    "pressing_direction",
    "register_contact",
    "unregister_contact",
]
