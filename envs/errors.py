"""Bad input to the environments: one family with the tissue's (``tissue.TissueInputError``)."""

from __future__ import annotations

import tissue


class EnvConfigError(tissue.ConfigError):
    """A keyword argument or setting an environment cannot take: the message names the
    value, what was expected and how to fix it."""
