"""The contact strategies by name: a new strategy is one module plus one registration.

A strategy is a :class:`~tissue.contact.base.ContactModel` subclass that carries its own
facts as class attributes (``name``, ``label``, ``colour``, ``params_type``,
``penetration_bound_m``, ``has_tangent``) and is registered under its name::

    from tissue.contact import ContactModel, register_contact

    @register_contact
    class MyContact(ContactModel):
        name = "mine"
        label = "Mine"
        params_type = MyParams
        penetration_bound_m = 0.001
        ...

``tissue.TissueSpec(contact="mine")``, the command line's ``--contact mine``, the study and
the environments then take it like the built-in ones. Method names are validated strings
(:func:`contact_method`), not a closed enum.
"""

from __future__ import annotations

import math
import re
from typing import TYPE_CHECKING

from tissue.errors import ConfigError

if TYPE_CHECKING:
    from tissue.contact.base import ContactModel

#: The registered strategies, by name, in registration order.
CONTACT_MODELS: dict[str, type[ContactModel]] = {}

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


def register_contact(cls: type[ContactModel]) -> type[ContactModel]:
    """Register ``cls`` under ``cls.name`` (a class decorator; returns ``cls``).

    Raises:
        ConfigError: the name is not a lowercase identifier, another class holds it, or a
            fact the registry needs is missing or out of range.
    """
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not _NAME.match(name):
        raise ConfigError(
            f"{cls.__name__}.name must be a lowercase identifier such as 'lm'; got {name!r}"
        )
    held = CONTACT_MODELS.get(name)
    if held is not None and held is not cls:
        raise ConfigError(
            f"contact method {name!r} is already registered to {held.__module__}."
            f"{held.__qualname__}; choose another name or unregister_contact({name!r}) first"
        )
    for fact in ("label", "params_type", "penetration_bound_m"):
        if getattr(cls, fact, None) is None:
            raise ConfigError(f"{cls.__name__} must set the class attribute {fact!r}")
    bound = cls.penetration_bound_m
    if not (isinstance(bound, (int, float)) and math.isfinite(bound) and bound > 0):
        raise ConfigError(f"{cls.__name__}.penetration_bound_m must be > 0 [m]; got {bound!r}")
    CONTACT_MODELS[name] = cls
    return cls


def unregister_contact(name: str) -> None:
    """Remove the strategy ``name`` (a test's or a plug-in's); unknown names are an error."""
    contact_class(name)
    del CONTACT_MODELS[name]


def contact_methods() -> tuple[str, ...]:
    """The registered method names, in registration order."""
    return tuple(CONTACT_MODELS)


def contact_method(value: object) -> str:
    """``value`` as a registered method name (case-insensitive); an error listing them."""
    name = value.lower() if isinstance(value, str) else value
    if not isinstance(name, str) or name not in CONTACT_MODELS:
        valid = ", ".join(repr(known) for known in CONTACT_MODELS)
        raise ConfigError(f"unknown contact method {value!r}; choose one of {valid}")
    return name


def contact_class(value: object) -> type[ContactModel]:
    """The strategy class registered as ``value`` (a name)."""
    return CONTACT_MODELS[contact_method(value)]


def contact_choice(value: object) -> type[ContactModel]:
    """``value``, a registered method's name or its class, as the class: the one place a
    spec's ``contact`` is validated (:class:`tissue.TissueSpec`); an error listing the
    registered names."""
    if isinstance(value, type):
        registered = CONTACT_MODELS.get(str(getattr(value, "name", "")))
        if registered is not None and registered is value:
            return registered
    return contact_class(value)
