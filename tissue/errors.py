"""Exceptions for bad input to the tissue simulator.

Physical failures at run time (divergence, inversion) are never raised: they are reported
as a :class:`tissue.status.StepStatus`. These exceptions are for input a user can fix.
"""


class TissueInputError(ValueError):
    """Bad input: the message says what was given, what was expected and how to fix it."""


class MeshError(TissueInputError):
    """A mesh that cannot be simulated (wrong shape, degenerate or inverted tets, mm units)."""


class MaterialError(TissueInputError):
    """Material parameters outside their physical range."""


class ConfigError(TissueInputError):
    """A configuration value or name that is not valid."""
