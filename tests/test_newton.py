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


def _quadratic_with_missing_curvature():
    """½ xᵀ A x − bᵀ x (minimum `A⁻¹ b`, the independent truth) with a curvature matrix
    that misses most of `A` along two of its eigenvectors (`B` there 1/20 of `A`), as the
    Fisher information misses the second-order term of a likelihood whose model does not
    fit exactly: the valley a polish crawls along."""
    rng = np.random.default_rng(3)
    Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    A = Q @ np.diag([50.0, 20.0, 8.0, 3.0, 0.5, 0.2]) @ Q.T
    B = A - 0.95 * (0.5 * np.outer(Q[:, 4], Q[:, 4]) + 0.2 * np.outer(Q[:, 5], Q[:, 5]))
    b = rng.normal(size=6)
    calls = []

    def f(x):
        calls.append(1)
        return 0.5 * x @ A @ x - b @ x, A @ x - b, B
    return f, np.linalg.solve(A, b), calls


def test_the_secant_correction_supplies_the_curvature_the_matrix_misses():
    """With the curvature 20× too small along two directions, plain steps overshoot
    there and the damping's backtracks crawl (more than 40 evaluations, measured 59);
    the structured secant update (Dennis, Gay and Welsch) learns the missing part from
    the gradients and reaches the minimum, to 1e-6, in at most 20 (measured 14)."""
    solver = dict(min_curvature=1e-6, max_step=100.0, tol=1e-14)
    found = {}
    for secant in (False, True):
        f, truth, calls = _quadratic_with_missing_curvature()
        sol = newton(f, np.zeros(6), TruncatedNewton(**solver, secant=secant), max_steps=200)
        found[secant] = (len(calls), sol.converged, np.max(np.abs(sol.value - truth)))
    assert found[True][1] and found[True][2] < 1e-6 and found[True][0] <= 20, found
    assert found[False][0] > 40, found
