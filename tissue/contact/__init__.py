"""Probe-tissue contact strategies behind one interface, chosen by name.

A strategy is a :class:`ContactModel` subclass stating its facts as class attributes and
registered by name (:mod:`tissue.contact.registry`): a new strategy is one module plus one
registration. The finite-element strategies here (penalty, Lagrange multipliers, prescribed
displacement) register when this package is imported; PBD, a tissue backend of its own,
registers from :mod:`tissue.pbd`, which ``import tissue`` loads.
"""

from __future__ import annotations

from typing import Any

from tissue.contact.base import ContactModel
from tissue.contact.lagrange import LagrangeContact, LagrangeParams
from tissue.contact.penalty import PenaltyContact, PenaltyParams
from tissue.contact.prescribed import PrescribedContact, PrescribedParams
from tissue.contact.registry import (
    CONTACT_MODELS,
    contact_choice,
    contact_class,
    contact_method,
    contact_methods,
    register_contact,
    unregister_contact,
)
from tissue.sim.solvers import SERIAL_STEP_UNKNOWNS
from tissue.threads import one_thread_below, thread_policy


def make_contact_model(
    method: str | type[ContactModel], mesh, probe_shape, **kwargs: Any
) -> ContactModel:
    """Build the contact model registered as ``method`` (:func:`contact_methods`): its name,
    or its class as a spec resolved it (``ResolvedTissue.contact_type``).

    Keyword arguments go to the model (``materials``, ``config``, ``params``).
    """
    model_class = contact_choice(method)
    thread_policy()
    # Built under the step's thread rule, as TissueSimulator is (tissue.threads): a small
    # tissue's build then gives the same bits on any number of threads.
    node_count = int(getattr(mesh, "node_count", 0))
    with one_thread_below(3 * node_count, SERIAL_STEP_UNKNOWNS):
        return model_class(mesh, probe_shape, **kwargs)


__all__ = [
    "CONTACT_MODELS",
    "ContactModel",
    "LagrangeContact",
    "LagrangeParams",
    "PenaltyContact",
    "PenaltyParams",
    "PrescribedContact",
    "PrescribedParams",
    "contact_choice",
    "contact_class",
    "contact_method",
    "contact_methods",
    "make_contact_model",
    "register_contact",
    "unregister_contact",
]
