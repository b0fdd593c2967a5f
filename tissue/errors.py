"""Exceptions for bad input to the tissue simulator.

Physical failures at run time (divergence, inversion) are never raised: they are reported
as a :class:`tissue.status.StepStatus`. These exceptions are for input a user can fix.
"""

from collections.abc import Iterable


class TissueInputError(ValueError):
    """Bad input: the message says what was given, what was expected and how to fix it."""


class MeshError(TissueInputError):
    """A mesh that cannot be simulated (wrong shape, degenerate or inverted tets, mm units)."""


class MaterialError(TissueInputError):
    """Material parameters outside their physical range."""


class ConfigError(TissueInputError):
    """A configuration value or name that is not valid."""


def check_setting_names(given: Iterable[str], valid: Iterable[str], what: str) -> None:
    """Raise :class:`ConfigError` naming the ``what`` settings in ``given`` that are not in
    ``valid`` (both iterables of names), with the valid ones listed."""
    valid_names = sorted(valid)
    unknown = sorted(set(given) - set(valid_names))
    if unknown:
        raise ConfigError(f"unknown {what} setting(s) {unknown}; valid settings: {valid_names}")
