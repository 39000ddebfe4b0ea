"""The damped, truncated Newton minimiser of the Kalman stage (`fitting._newton`)."""

from __future__ import annotations

import numpy as np

from thermojax.fitting._newton import TruncatedNewton, newton


def _parabola(bad=(1.2, 3.0), nan_at_start=False):
    """(x − 1)², minimum 0 at x = 1, with a curvature a quarter of the true one (so the
    first steps overshoot) and a gradient that overflows to NaN on `bad`, where the value
    itself stays finite: an exponential run far out, whose derivatives overflow first."""
    visited = []

    def f(x):
        x0 = float(x[0])
        visited.append(x0)
        g = 2.0 * (x0 - 1.0)
        if bad[0] < x0 < bad[1] or nan_at_start:
            g = np.nan
        return (x0 - 1.0) ** 2, np.array([g]), np.array([[0.5]])
    return f, visited


def test_a_trial_with_non_finite_derivatives_is_shortened_not_taken():
    """The damping's trials reach x = 1.33 (value 0.11, below the start's 1, gradient
    NaN): taken, the next step's eigendecomposition would fail on it. Counted as an
    infinite value, it is shortened, and the steps end at the minimum."""
    f, visited = _parabola()
    sol = newton(f, np.array([0.0]), TruncatedNewton(min_curvature=0.1, max_step=10.0,
                                                     tol=1e-12), max_steps=200)
    assert any(1.2 < x < 3.0 for x in visited)  # the bad region was tried
    assert sol.converged and abs(sol.value[0] - 1.0) < 1e-5 and sol.loss < 1e-10


def test_a_start_with_non_finite_derivatives_takes_no_step():
    """No step can be computed there: the start comes back as it is, not converged, its
    value infinite (the caller's fit then fails or starts elsewhere), never a
    `LinAlgError` from the eigendecomposition."""
    f, visited = _parabola(nan_at_start=True)
    sol = newton(f, np.array([0.5]))
    assert visited == [0.5] and sol.value.tolist() == [0.5]
    assert not sol.converged and sol.num_steps == 0 and sol.loss == np.inf
