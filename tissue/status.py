"""Step outcomes: a physical failure is reported as data, never raised."""

from __future__ import annotations

from enum import Enum


class StepStatus(str, Enum):
    """How a tissue step ended.

    ``OK`` and ``NOT_CONVERGED`` commit a finite state; ``PENETRATED`` commits a finite state
    in which the skin's surface lies inside the probe deeper than the contact method's bound
    allows (:meth:`tissue.contact.base.ContactModel.skin_depth`); ``INVERTED`` commits a
    finite state in which some tet has det F <= 0; ``TUNNELLED`` commits a finite state in
    which the probe has passed through the tissue (its face behind the tissue's surface, the
    tissue not pushing it back; see :mod:`tissue.contact.tunnelling`); ``DIVERGED`` and
    ``SOLVER_FAILED`` keep the state from before the step (nothing non-finite is ever
    stored).
    """

    OK = "ok"
    NOT_CONVERGED = "not_converged"
    PENETRATED = "penetrated"
    INVERTED = "inverted"
    TUNNELLED = "tunnelled"
    DIVERGED = "diverged"
    SOLVER_FAILED = "solver_failed"

    @property
    def is_failure(self) -> bool:
        """Whether the step counts as an instability (everything but ``OK``)."""
        return self is not StepStatus.OK


# When several problems occur in one step, the most severe is reported.
SEVERITY = {
    StepStatus.OK: 0,
    StepStatus.NOT_CONVERGED: 1,
    StepStatus.PENETRATED: 2,
    StepStatus.INVERTED: 3,
    StepStatus.TUNNELLED: 4,
    StepStatus.SOLVER_FAILED: 5,
    StepStatus.DIVERGED: 6,
}


def worst(*statuses: StepStatus) -> StepStatus:
    """The most severe of ``statuses``."""
    return max(statuses, key=SEVERITY.__getitem__)
