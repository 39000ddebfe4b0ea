"""The steady-state Kalman gain in JAX by structured doubling (`kalman_gain_doubling`):
traceable and vmapped over a chunk's units, where each unit's own-model observer needs
the gain of its own parameters (`Study.observer_of`)."""

from __future__ import annotations


def kalman_gain_doubling(Phi, C, Qd, R, iterations: int = 48):
    """Filter-form steady-state Kalman gain `L = P Cᵀ (C P Cᵀ + R)⁻¹`, with `P` the
    predicted covariance of the DARE `P = Φ P Φᵀ − Φ P Cᵀ (C P Cᵀ + R)⁻¹ C P Φᵀ + Qd`,
    by the structured doubling algorithm (fixed iteration count: traceable, vmaps;
    convergence is quadratic, 48 doublings cover 2^48 steps of the recursion). Agrees
    with `steady_state_kalman` (SciPy's `solve_discrete_are`) to roundoff."""
    import jax
    import jax.numpy as jnp

    n = Phi.shape[0]
    I = jnp.eye(n, dtype=Phi.dtype)
    A0 = Phi.T
    G0 = C.T @ jnp.linalg.solve(R, C)
    H0 = 0.5 * (Qd + Qd.T)

    def body(_, carry):
        A, G, H = carry
        W = I + G @ H
        WA = jnp.linalg.solve(W, A)
        WG = jnp.linalg.solve(W, G)
        A_new = A @ WA
        G_new = G + A @ WG @ A.T
        H_new = H + A.T @ H @ WA
        return A_new, 0.5 * (G_new + G_new.T), 0.5 * (H_new + H_new.T)

    _, _, P = jax.lax.fori_loop(0, iterations, body, (A0, G0, H0))
    S = C @ P @ C.T + R
    return jnp.linalg.solve(S, C @ P).T
