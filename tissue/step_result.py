"""What a tissue step returns, from the contact model to the front door: one record,
:class:`TissueStep`, with its :class:`StepDiagnostics`.

A contact model's step (:meth:`tissue.contact.base.ContactModel.step`) builds it; the front
door (:meth:`tissue.Tissue.step`) adds the lesions' centroids, which the tissue, not the
contact model, tracks. Low in the layers (it imports only :mod:`tissue.status`), so that every
layer that steps a tissue returns the same type."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from tissue.status import StepStatus


@dataclass(frozen=True)
class StepDiagnostics:
    """How a tissue step was solved.

    Attributes:
        iterations: Newton iterations (robust FE; every solve of the step, its
            augmentation rounds, re-settled node sets, undone attempts, halves, relaxation
            steps and sub-motions included), 1 (a paper FE step's one linear solve), or the
            substeps (PBD, over every sub-motion).
        linear_iterations: iterations of the linear solver (0 for direct solves).
        contact_count: contact points (or held nodes) carrying force at the step's end.
        sub_motions: tissue steps the probe's motion was split into (1: none; see
            :meth:`tissue.contact.base.ContactModel.step`).
        subdivisions: times a robust step was halved to converge.
        min_volume_ratio: the smallest det F of any tet after the step (None if unknown).
        compute_ms: wall time of the step [ms] (not deterministic: keep it out of
            anything compared between runs).
        details: the strategy's own figures (augmentation rounds, response rounds, ...);
            ``details.get("asleep")`` is 1.0 for a step that slept (no tissue work at all,
            ``iterations`` 0; see :attr:`tissue.TissueSpec.sleep_speed_m_s`), absent for
            a step that ran.
    """

    iterations: int
    linear_iterations: int
    contact_count: int
    sub_motions: int
    subdivisions: int
    min_volume_ratio: float | None
    compute_ms: float
    details: Mapping[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class TissueStep:
    """What one :meth:`Tissue.step` did. Frozen; arrays are the step's own.

    Attributes:
        status: ``ok`` or the instability met (:class:`tissue.status.StepStatus`); a
            failed step (diverged, solver failed) keeps the state from before it.
        time_s: simulated time after the step [s].
        force_world_n: force of the tissue on the probe [N], (3,), world frame.
        torque_world_nm: torque of those forces about the probe origin [N m], (3,).
        contact_points_world_m: where contact forces act [m], (k, 3).
        contact_forces_world_n: force on the probe at each [N], (k, 3).
        skin_penetration_m: the deepest point of the skin's surface (the collision
            surface's facets, not only its vertices) inside the probe's body [m], >= 0,
            measured the same way for every method
            (:meth:`tissue.contact.base.ContactModel.skin_depth`).
        landmarks_world_m: tracked points [m], (landmark_count, 3).
        lesion_centroids_world_m: deformed lesion centroids [m], (lesion_count, 3), or of
            the lesions :meth:`Tissue.track_lesions` chose, in its order; (0, 3) from a
            contact model's own step (the lesions are the tissue's, which adds them).
        diagnostics: how the step was solved.
        method_penetration_m: the deepest of the points the method itself keeps out of the
            probe (:meth:`tissue.contact.base.ContactModel.contact_points_world`) inside it
            [m], >= 0: the method's own measure, which its penetration bound judges.
    """

    status: StepStatus
    time_s: float
    force_world_n: NDArray[np.float64]
    torque_world_nm: NDArray[np.float64]
    contact_points_world_m: NDArray[np.float64]
    contact_forces_world_n: NDArray[np.float64]
    skin_penetration_m: float
    landmarks_world_m: NDArray[np.float64]
    lesion_centroids_world_m: NDArray[np.float64]
    diagnostics: StepDiagnostics
    method_penetration_m: float = 0.0

    @property
    def ok(self) -> bool:
        """Whether the step ended ``ok``."""
        return self.status is StepStatus.OK

    @property
    def contact_count(self) -> int:
        """Contact points carrying force at the step's end."""
        return int(self.contact_points_world_m.shape[0])


_Frozen = TypeVar("_Frozen")
# PBD gives both its substeps and its constraint iterations a substep: the substeps count.
_ITERATION_KEYS = ("newton_iterations", "substeps", "iterations")
_ASLEEP_DETAILS = MappingProxyType({"asleep": 1.0})
_TYPED_KEYS = {
    *_ITERATION_KEYS,
    "linear_iterations",
    "subdivisions",
    "min_volume_ratio",
    "sub_motions",
}


def frozen(cls: type[_Frozen], **fields: Any) -> _Frozen:
    """An instance of the frozen dataclass ``cls`` with ``fields`` (every one of its fields,
    by name), as its ``__init__`` would make it but without it: a frozen dataclass's
    ``__init__`` sets each field through ``object.__setattr__``, which costs a sleeping
    step (every free-air env step) about 2 us per instance. Only for a class without
    ``__post_init__`` or ``__slots__``, given every field (the sleep tests check that
    :class:`TissueStep` and :class:`StepDiagnostics` are such classes)."""
    instance = object.__new__(cls)
    instance.__dict__.update(fields)
    return instance


def asleep_diagnostics(compute_ms: float) -> StepDiagnostics:
    """A sleeping step's diagnostics (known but for its time [ms])."""
    return frozen(
        StepDiagnostics,
        iterations=0,
        linear_iterations=0,
        contact_count=0,
        sub_motions=1,
        subdivisions=0,
        min_volume_ratio=None,
        compute_ms=compute_ms,
        details=_ASLEEP_DETAILS,
    )


def iteration_key(diagnostics: Mapping[str, Any]) -> str:
    """The name a contact model's diagnostics give the step's iterations: the first of
    ``newton_iterations``, ``substeps`` (PBD, whose ``iterations`` are per substep) and
    ``iterations`` that they hold (``iterations`` if none)."""
    return next((key for key in _ITERATION_KEYS if key in diagnostics), "iterations")


def typed_diagnostics(
    diagnostics: Mapping[str, Any], contact_count: int, compute_ms: float
) -> StepDiagnostics:
    """A contact model's solver figures (its ``_advance``'s dictionary) as
    :class:`StepDiagnostics`: the iteration count under whichever name the method gives it
    (``newton_iterations``, ``iterations`` or PBD's ``substeps``), the typed fields, and every
    other finite number in ``details``."""
    if diagnostics.get("asleep"):  # a sleeping step's are known
        return asleep_diagnostics(compute_ms)
    iterations = diagnostics.get(iteration_key(diagnostics), 1)
    ratio = diagnostics.get("min_volume_ratio")
    details = {
        key: float(value)
        for key, value in diagnostics.items()
        if key not in _TYPED_KEYS
        and isinstance(value, (bool, int, float, np.integer, np.floating))
        and math.isfinite(float(value))
    }
    return StepDiagnostics(
        iterations=int(iterations),
        linear_iterations=int(diagnostics.get("linear_iterations", 0)),
        contact_count=contact_count,
        sub_motions=int(diagnostics.get("sub_motions", 1)),
        subdivisions=int(diagnostics.get("subdivisions", 0)),
        min_volume_ratio=None if ratio is None else float(ratio),
        compute_ms=float(compute_ms),
        details=details,
    )


def with_lesions(step: TissueStep, centroids: NDArray[np.float64]) -> TissueStep:
    """``step`` with the lesions' centroids [m], (lesion_count, 3), that the tissue tracks
    (the contact model's own step has none); the other fields are ``step``'s."""
    return frozen(TissueStep, **{**step.__dict__, "lesion_centroids_world_m": centroids})
