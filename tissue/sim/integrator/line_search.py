"""Newton's line search: backtracking with Armijo's condition, extrapolating a full step that
fell short, and the extrapolated first iterate of a step continuing the last."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from tissue.sim.integrator.config import IntegratorConfig
from tissue.sim.solvers import dot

# Armijo's sufficient-decrease constant: the customary 1e-4 (Nocedal & Wright, Numerical
# Optimization, 2nd ed., section 3.1), not a tuning choice.
_ARMIJO_C = 1e-4


def line_search(
    y,
    step,
    gradient,
    mismatch,
    evaluate,
    energy,
    dofs=None,
    targets=None,
    *,
    config: IntegratorConfig,
):
    """Backtracking Armijo search along ``step``, extrapolating a full step that fell short.

    ``evaluate(z)`` gives (energy [J], gradient [N], force scale [N]) at z; ``energy`` and
    ``gradient`` are its values at y; ``mismatch`` [m] how far the constrained ``dofs`` are
    from their ``targets``. Returns (y, energy, gradient, scale) at the accepted point, or
    None when no finite point was found. A full step puts the constrained dofs exactly on
    ``targets`` (y + (t - y) may miss t by an ulp, which would read as a constraint not yet
    met). A full step accepted with the energy still falling steeply at its end tries a longer
    one (``config.extrapolate_below``); the last evaluation is always at the returned point.
    """
    slope = dot(gradient, step)
    alpha = 1.0
    while alpha >= config.min_step_fraction:
        trial = y + alpha * step
        if alpha == 1.0 and dofs is not None and mismatch > 0.0:
            trial[dofs] = targets
        trial_energy, trial_gradient, trial_scale = evaluate(trial)
        if math.isfinite(trial_energy) and (
            # While constraints still move the boundary the energy may rightly rise: accept
            # any finite full step then; afterwards require sufficient decrease.
            mismatch > 0.0
            or slope >= 0.0
            or trial_energy <= energy + _ARMIJO_C * alpha * slope + 1e-14 * abs(energy)
        ):
            if alpha == 1.0 and mismatch == 0.0 and slope < 0.0:
                longer = _extrapolate(
                    y,
                    step,
                    slope,
                    trial,
                    trial_energy,
                    trial_gradient,
                    evaluate,
                    config,
                )
                if longer is not None:
                    return longer
            return trial, trial_energy, trial_gradient, trial_scale
        alpha *= 0.5
    # No decrease along the direction: keep the smallest step if it is finite.
    trial = y + config.min_step_fraction * step
    trial_energy, trial_gradient, trial_scale = evaluate(trial)
    if math.isfinite(trial_energy):
        return trial, trial_energy, trial_gradient, trial_scale
    return None


def _extrapolate(y, step, slope, accepted, energy, gradient, evaluate, config: IntegratorConfig):
    """The secant step past an accepted full step, if the energy still falls steeply there.

    ``slope`` [J] is the directional derivative along ``step`` at y; ``accepted`` = y +
    step, ``energy`` [J] and ``gradient`` [N] its evaluation. Returns (y', energy,
    gradient, scale) at y' = y + alpha step, alpha in [2, ``config.max_extrapolation``] (where
    the directional derivative, interpolated linearly from its values at 0 and 1,
    vanishes; the cap where it does not rise), when that energy is lower; else None,
    with ``accepted`` evaluated again if y' was tried (the contact terms report the
    last evaluation's forces).
    """
    end_slope = dot(gradient, step)
    if not end_slope < config.extrapolate_below * slope:
        return None
    rise = end_slope - slope  # > 0 where the energy is convex along the step
    alpha = config.max_extrapolation
    if rise > 0.0:
        alpha = min(alpha, -slope / rise)
    trial = y + alpha * step
    trial_energy, trial_gradient, trial_scale = evaluate(trial)
    if math.isfinite(trial_energy) and trial_energy < energy:
        return trial, trial_energy, trial_gradient, trial_scale
    evaluate(accepted)
    return None


def extrapolated_positions(
    x: NDArray[np.float64],
    v: NDArray[np.float64],
    h: float,
    previous_v: NDArray[np.float64],
    last_h: float,
) -> NDArray[np.float64]:
    """x + h v + h^2 (v - previous_v) / last_h [m], flat (3N,): where a step of ``h`` [s]
    from (x [m], v [m/s]) lands if it keeps the acceleration of the last step (``last_h``
    [s], which started at ``previous_v``). Newton's first iterate when continuing a step."""
    return (x + h * v + (h * h / last_h) * (v - previous_v)).reshape(-1)
