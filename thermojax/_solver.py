"""A Gauss-Newton solver for grey-box fits whose data cannot determine every direction.

Thermal networks measured at a few nodes always have such directions (a fast,
unsensed proof mass: its capacitance and conductance move together without
changing any reading). Plain Gauss-Newton takes enormous steps along them;
Levenberg-Marquardt damps them but crawls. `TruncatedGaussNewton` solves the
Gauss-Newton step by SVD and leaves out every direction whose singular value
is below `min_singular_value` (with residuals weighted by their noise std,
`1/s` is the data's std along that direction, in parameter units: for
log-parameters, `s < 1` means the data cannot pin it within a factor e). So
the identifiable part converges quadratically, the rest stays where it
started, and the identifiability report reads the same threshold. Steps are
damped as in Levenberg-Marquardt (far from the optimum a full Gauss-Newton
step can cut a weakly coupled node off the network, a basin it never leaves)
and capped at `max_step` in the max norm (log units: a factor e per step). It stops when the
Gauss-Newton model predicts a cost decrease below `tol` on the identifiable
part: a criterion in likelihood units, blind to directions that cannot move.

Any optimistix least-squares solver (`optx.LevenbergMarquardt`, ...) may be
passed to `fit` instead.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


class GaussNewtonSolution(eqx.Module):
    """What `gauss_newton` returns: the parameters, and how the solve went."""

    value: Float[Array, " params"]
    cost: Float[Array, ""]  # ½ Σ r², at `value`
    num_steps: Int[Array, ""]
    converged: Bool[Array, ""]  # the identifiable part's predicted decrease fell below tolerance
    num_truncated: Int[Array, ""]  # directions left out at the last step


class TruncatedGaussNewton(eqx.Module):
    """Settings of `gauss_newton`.

    **Arguments:**

    - `min_singular_value`: directions whose singular value of the weighted
      Jacobian is below this are not moved (1: the data pin them within less
      than one unit of the parameter, a factor e for a log-parameter).
    - `max_step`: largest change of any parameter per step (parameter units).
    - `tol`: stop when the Gauss-Newton model predicts a cost decrease below
      `tol` (cost ½χ²: `tol = 1e-4` is a change of 1e-4 in -log L, far below
      any statistical meaning).
    - `max_steps`: give up after this many steps (`converged` False).
    """

    min_singular_value: float = 1.0
    max_step: float = 1.0
    tol: float = 1e-4
    max_steps: int = eqx.field(static=True, default=100)
    max_backtracks: int = eqx.field(static=True, default=30)


def gauss_newton(fn: Callable, theta0: Float[Array, " params"], args,
                 solver: TruncatedGaussNewton = TruncatedGaussNewton()) -> GaussNewtonSolution:
    """Minimise `½‖fn(theta, args)‖²`: truncated Gauss-Newton steps, damped
    Levenberg-Marquardt style (Nielsen's update of the damping `λ`) and capped.

    Each step takes one Jacobian and its SVD; rejected trial steps reuse them
    (only residuals are re-evaluated). Pure and jittable.
    """

    def cost_of(theta):
        r = fn(theta, args)
        c = 0.5 * jnp.sum(r ** 2)
        return jnp.where(jnp.isfinite(c), c, jnp.inf)

    def cond(carry):
        return (carry[2] < solver.max_steps) & ~carry[3]

    def body(carry):
        theta, cost, k, _, _, _, lam = carry
        J, r = jax.jacfwd(lambda t: (fn(t, args),) * 2, has_aux=True)(theta)
        U, s, Vt = jnp.linalg.svd(J, full_matrices=False)
        keep = s > solver.min_singular_value
        Ur = jnp.where(keep, U.T @ r, 0.0)
        predicted_gn = 0.5 * jnp.sum(Ur ** 2)
        done = predicted_gn < solver.tol
        lam = jnp.where(k == 0, 1e-3 * jnp.max(s) ** 2, lam)

        def trial(lam):
            coef = jnp.where(keep, s / (s ** 2 + lam), 0.0) * Ur
            dx = -(Vt.T @ coef)
            size = jnp.max(jnp.abs(dx))
            scale = jnp.minimum(1.0, solver.max_step / jnp.maximum(size, 1e-300))
            dx = dx * scale
            # ½‖r‖² - ½‖r + J dx‖² in the SVD basis (dx = -scale Σ coef v).
            predicted = jnp.sum(scale * coef * s * Ur - 0.5 * (scale * coef * s) ** 2)
            new_cost = cost_of(theta + dx)
            return dx, new_cost, (cost - new_cost) / jnp.maximum(predicted, 1e-300)

        def ls_cond(c):
            _, _, rho, _, nu, j = c
            return (rho <= 0) & (j < solver.max_backtracks)

        def ls_body(c):
            _, _, _, lam, nu, j = c
            lam = lam * nu
            dx, new_cost, rho = trial(lam)
            return dx, new_cost, rho, lam, 2 * nu, j + 1

        dx, new_cost, rho = trial(lam)
        dx, new_cost, rho, lam, _, _ = jax.lax.while_loop(
            ls_cond, ls_body, (dx, new_cost, rho, lam, 2.0 * jnp.ones(()), jnp.zeros((), int)))
        better = (rho > 0) & ~done
        lam = jnp.where(better, lam * jnp.maximum(1 / 3, 1 - (2 * rho - 1) ** 3), lam)
        theta = jnp.where(better, theta + dx, theta)
        cost = jnp.where(better, new_cost, cost)
        return theta, cost, k + 1, done | ~better, done, jnp.sum(~keep), lam

    false = jnp.zeros((), bool)
    init = (theta0, cost_of(theta0), jnp.zeros((), int), false, false, jnp.zeros((), int),
            jnp.ones(()))
    theta, cost, k, _, converged, n_out, _ = jax.lax.while_loop(cond, body, init)
    return GaussNewtonSolution(theta, cost, k, converged, n_out)
