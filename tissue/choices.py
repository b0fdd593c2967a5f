"""Closed sets of names (methods, modes, laws) that parse with a helpful error."""

from __future__ import annotations

from enum import Enum
from typing import TypeVar

from tissue.errors import ConfigError, TissueInputError

ChoiceT = TypeVar("ChoiceT", bound="Choice")


class Choice(str, Enum):
    """A string-valued enum whose :meth:`parse` names the bad value and lists the valid ones.

    Subclasses override :meth:`noun` (what the set is called in messages) and, if needed,
    :meth:`error` (the exception raised).
    """

    @classmethod
    def noun(cls) -> str:
        return cls.__name__

    @classmethod
    def error(cls) -> type[TissueInputError]:
        return ConfigError

    @classmethod
    def parse(cls: type[ChoiceT], value: str | ChoiceT) -> ChoiceT:
        """The member named ``value``; an error listing the valid names otherwise."""
        try:
            return cls(value)
        except ValueError:
            valid = ", ".join(repr(member.value) for member in cls)
            raise cls.error()(f"unknown {cls.noun()} {value!r}; choose one of {valid}") from None
