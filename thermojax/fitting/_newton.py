"""A damped, truncated Newton minimiser for likelihoods that are not sums of squares.

The Kalman prediction-error likelihood (`log det S` terms) is minimised with
its exact Hessian (forward-over-reverse autodiff: the fit has tens of
parameters, so the Hessian costs a few gradients). Like `TruncatedGaussNewton`,
the step is taken only along eigen-directions whose curvature exceeds
`min_curvature` (with log-parameters, curvature 1 is a std of one log unit,
a factor e): the identifiable part converges quadratically, directions the data
cannot determine stay at their starting values, and the stopping rule is the
predicted decrease of `-log L` on the identifiable part. Negative curvature
far from the optimum is taken by its magnitude; steps are damped as in
Levenberg-Marquardt (Nielsen's update, starting nearly undamped: the Kalman fit
starts at the output-error optimum) and capped at `max_step`.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


class TruncatedNewton(eqx.Module):
    """Settings of `newton`: `min_curvature`, `max_step` (parameter units), `tol` (in
    `-log L`: 1e-2 is two orders below any likelihood-ratio threshold, and lets a
    process noise whose optimum is zero stop creeping towards it). The iteration limit
    is `newton`'s `max_steps`, as in optimistix."""

    min_curvature: float = 1.0
    max_step: float = 1.0
    tol: float = 1e-2
    max_backtracks: int = eqx.field(static=True, default=30)


class NewtonSolution(eqx.Module):
    """What `newton` returns: the parameters, `-log L` there, steps taken, convergence."""

    value: Float[Array, " params"]
    loss: Float[Array, ""]
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]


def newton(fn: Callable, theta0: Float[Array, " params"], args,
           solver: TruncatedNewton = TruncatedNewton(), max_steps=100) -> NewtonSolution:
    """Minimise the scalar `fn(theta, args)` from `theta0` (params,) in at most `max_steps`
    Newton steps (an int or an integer array: a traced limit does not recompile). Pure
    and jittable."""

    def loss_of(theta):
        v = fn(theta, args)
        return jnp.where(jnp.isfinite(v), v, jnp.inf)

    def cond(carry):
        return (carry[2] < max_steps) & ~carry[3]

    def body(carry):
        theta, loss, k, _, _, lam = carry
        g = jax.grad(fn)(theta, args)
        H = jax.hessian(fn)(theta, args)
        mu, V = jnp.linalg.eigh(0.5 * (H + H.T))
        curv = jnp.abs(mu)
        keep = curv > solver.min_curvature
        Vg = jnp.where(keep, V.T @ g, 0.0)
        predicted_newton = 0.5 * jnp.sum(jnp.where(keep, Vg ** 2 / jnp.where(keep, curv, 1.0),
                                                   0.0))
        done = predicted_newton < solver.tol

        def trial(lam):
            coef = jnp.where(keep, Vg / (curv + lam), 0.0)
            dx = -(V @ coef)
            size = jnp.max(jnp.abs(dx))
            dx = dx * jnp.minimum(1.0, solver.max_step / jnp.maximum(size, 1e-300))
            predicted = -(g @ dx + 0.5 * dx @ (H @ dx))
            new = loss_of(theta + dx)
            return dx, new, (loss - new) / jnp.maximum(jnp.abs(predicted), 1e-300)

        def ls_cond(c):
            return (c[2] <= 0) & (c[5] < solver.max_backtracks)

        def ls_body(c):
            _, _, _, lam, nu, j = c
            lam = lam * nu
            dx, new, rho = trial(lam)
            return dx, new, rho, lam, 2 * nu, j + 1

        dx, new, rho = trial(lam)
        dx, new, rho, lam, _, _ = jax.lax.while_loop(
            ls_cond, ls_body, (dx, new, rho, lam, 2.0 * jnp.ones(()), jnp.zeros((), int)))
        better = (rho > 0) & ~done
        lam = jnp.where(better, lam * jnp.maximum(1 / 3, 1 - (2 * jnp.minimum(rho, 1.0) - 1) ** 3),
                        lam)
        theta = jnp.where(better, theta + dx, theta)
        loss = jnp.where(better, new, loss)
        return theta, loss, k + 1, done | ~better, done, lam

    false = jnp.zeros((), bool)
    init = (theta0, loss_of(theta0), jnp.zeros((), int), false, false, jnp.full((), 1e-3))
    theta, loss, k, _, converged, _ = jax.lax.while_loop(cond, body, init)
    return NewtonSolution(theta, loss, k, converged)
