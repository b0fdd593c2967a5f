"""Probe-tissue contact strategies behind one interface, chosen by name.

A new strategy is one module plus one entry in :data:`CONTACT_MODELS`.
"""

from __future__ import annotations

from typing import Any

from tissue.contact.base import ContactMethod, ContactModel, ContactResult
from tissue.contact.lagrange import LagrangeContact, LagrangeParams
from tissue.contact.penalty import PenaltyContact, PenaltyParams
from tissue.contact.prescribed import PrescribedContact, PrescribedParams
from tissue.sim.solvers import SERIAL_STEP_UNKNOWNS
from tissue.threads import one_thread_below, thread_policy

# name -> (model class, its parameter dataclass)
CONTACT_MODELS: dict[ContactMethod, tuple[type[ContactModel], type]] = {
    ContactMethod.PENALTY: (PenaltyContact, PenaltyParams),
    ContactMethod.LM: (LagrangeContact, LagrangeParams),
    ContactMethod.PRESCRIBED: (PrescribedContact, PrescribedParams),
}


def make_contact_model(
    method: str | ContactMethod, mesh, probe_shape, **kwargs: Any
) -> ContactModel:
    """Build the contact model named ``method`` (penalty, lm, prescribed, pbd).

    Keyword arguments go to the model (``materials``, ``config``, ``params``).
    """
    method = ContactMethod.parse(method)
    if method is ContactMethod.PBD and method not in CONTACT_MODELS:
        from tissue.pbd import PBDConfig, PBDContact

        CONTACT_MODELS[method] = (PBDContact, PBDConfig)
    model_class, _ = CONTACT_MODELS[method]
    thread_policy()
    # Built under the step's thread rule, as TissueSimulator is (tissue.threads): a small
    # tissue's build then gives the same bits on any number of threads.
    node_count = int(getattr(mesh, "node_count", 0))
    with one_thread_below(3 * node_count, SERIAL_STEP_UNKNOWNS):
        return model_class(mesh, probe_shape, **kwargs)


__all__ = [
    "CONTACT_MODELS",
    "ContactMethod",
    "ContactModel",
    "ContactResult",
    "make_contact_model",
]
