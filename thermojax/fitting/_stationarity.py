"""First-order conditions at the end of a truncated solve, and the way out when they fail.

`TruncatedGaussNewton` leaves out every direction the data pin less than a factor e (its
singular value of the weighted Jacobian below `min_singular_value`) and stops when the
rest predicts no decrease. At an optimum that is harmless: along such a direction the
gradient is noise, `γ = s z` with `z` of order 1. Far from the optimum it is not: a
boundary conductance 1000× too high makes its node follow the boundary within a fraction
of a sample, the data then barely see the conductance (`s` of 0.07), and the solve stops
"converged" with the node predicted worse than by its own mean, although the gradient
along that direction is 65 of its own standard deviations (`z = γ / s`: the score test
along one direction, `z²` χ²₁ at a stationary point).

`violations` finds those directions: `z² > SCORE_Z2` and a step of at most `max_step`
along each (the quadratic model, capped as the solver caps its steps) predicting a
decrease of more than `GAIN` in −log L. `escape` walks along them alone (the identifiable
part is left to the solver, the flat directions where they are) while −log L falls; the
fit then solves again from there and keeps whichever is better. A fit that still has
such a direction is not converged, and its message names it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

#: z² of the score along a left-out direction above which the end is not stationary
#: (10 standard deviations: far beyond the noise of any fit's flat directions).
SCORE_Z2 = 100.0
#: −log L a capped step along the direction must be predicted to gain as well (less is
#: of no consequence to any decision the fit serves).
GAIN = 0.5
#: Steps `escape` takes at most (each a Jacobian evaluation).
MAX_ESCAPE_STEPS = 40


@dataclass(frozen=True)
class Violation:
    """A left-out direction along which the end of a solve is not stationary."""

    leading: str  # the free parameter with the largest weight in the direction
    z2: float  # the score statistic γ² / s²
    gain: float  # −log L a step of at most `max_step` is predicted to gain
    step: np.ndarray  # (free,) that step, in the solver's parameters

    def describe(self) -> str:
        return (f"the likelihood still falls along {self.leading} (gradient "
                f"{np.sqrt(self.z2):.0f} of its standard deviations; a step predicts "
                f"{self.gain:.1f} lower -log L)")


def violations(jacobian: np.ndarray, residuals: np.ndarray, names: list[str],
               min_singular_value: float = 1.0, max_step: float = 1.0) -> list[Violation]:
    """The left-out directions whose first-order condition fails, largest gain first.

    **Arguments:**

    - `jacobian`: (rows, free) of the weighted residuals (each row divided by its noise
      std), at the point tested.
    - `residuals`: (rows,) weighted residuals there; −log L is `½ Σ r²` up to constants,
      its gradient `Jᵀ r`.
    - `names`: the free parameters' names (free,).
    - `min_singular_value`, `max_step`: the solver's (a direction is left out below the
      first; a step changes no parameter by more than the second).
    """
    jacobian = np.asarray(jacobian, float).reshape(-1, len(names))
    residuals = np.asarray(residuals, float).reshape(-1)
    if not names or not np.all(np.isfinite(residuals)) or not np.all(np.isfinite(jacobian)):
        return []
    s2, vectors = np.linalg.eigh(jacobian.T @ jacobian)
    s2 = np.maximum(s2, 0.0)
    gamma = vectors.T @ (jacobian.T @ residuals)  # gradient along each direction
    found = []
    for i in np.flatnonzero(s2 < min_singular_value ** 2):
        v = vectors[:, i]
        z2 = gamma[i] ** 2 / s2[i] if s2[i] > 0 else np.inf
        length = min(abs(gamma[i]) / s2[i] if s2[i] > 0 else np.inf,
                     max_step / np.max(np.abs(v)))
        gain = length * abs(gamma[i]) - 0.5 * length ** 2 * s2[i]
        if z2 > SCORE_Z2 and gain > GAIN:
            found.append(Violation(names[int(np.argmax(np.abs(v)))], float(z2), float(gain),
                                   -np.sign(gamma[i]) * length * v))
    return sorted(found, key=lambda f: -f.gain)


def escape(theta: np.ndarray, at: Callable, names: list[str], min_singular_value: float = 1.0,
           max_step: float = 1.0, say=lambda _msg: None) -> tuple[np.ndarray, int]:
    """Walk from `theta` along the directions `violations` finds, while −log L falls.

    `at(theta) -> (nll, jacobian, residuals)` evaluates a point (−log L with the noise
    stds at their ML values, and the weighted Jacobian and residuals there). Each step
    moves along every violating direction at once, halved up to five times until −log L
    falls. **Returns:** `(theta, steps taken)`; `theta` unchanged when none was.
    """
    theta = np.asarray(theta, float)
    nll, jacobian, residuals = at(theta)
    taken = 0
    for _ in range(MAX_ESCAPE_STEPS):
        found = violations(jacobian, residuals, names, min_singular_value, max_step)
        if not found:
            break
        step = sum(f.step for f in found)
        step *= min(1.0, max_step / np.max(np.abs(step)))
        for _halving in range(6):
            trial = at(theta + step)
            if np.isfinite(trial[0]) and trial[0] < nll:
                break
            step = step / 2
        else:
            break
        theta = theta + step
        nll, jacobian, residuals = trial
        taken += 1
        if taken == 1:
            say(f"the solve stopped where {found[0].describe()}: moving along it")
    return theta, taken
