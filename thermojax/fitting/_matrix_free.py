"""Levenberg-Marquardt steps without a Jacobian: Jacobian-vector products inside a
preconditioned conjugate-gradient solve (lineax), for fits whose Jacobian is too large
to form.

Each iteration linearizes the residuals once (`jax.linearize`: one forward pass that
records what the products need) and transposes the linearization (`jax.linear_transpose`:
the reverse-mode, adjoint, product `Jᵀ s`). The damped Gauss-Newton step
`(JᵀJ + λ I) δ = -Jᵀ r` is solved by `lineax.CG` on the operator `v -> Jᵀ(J v) + λ v`:
one forward and one reverse product per CG iteration, each about the cost of one
simulation whatever the number of parameters. `J` (samples × outputs × parameters) is
never formed.

**Preconditioner.** Thermal networks make `JᵀJ` ill-conditioned (slow modes, weakly
coupled nodes): on a 25-node chain plain and Jacobi-preconditioned CG both needed more
than 200 iterations per step. CG is therefore preconditioned by a reference curvature
`H₀ = V diag(μ) Vᵀ` (the information matrix at the start, `_adjoint.information`):
`M = V diag(1/(μ + λ)) Vᵀ`. Where `JᵀJ` has moved little from `H₀`, CG converges in a
few iterations. Directions whose singular value `√μ` is below `min_singular_value` (the
data do not pin them: `TruncatedGaussNewton`'s rule) are left out of the step: the
operator is projected onto the kept directions, so those parameters stay where they
started.

Trial steps follow Levenberg-Marquardt (Nielsen's update of `λ`): a step that does not
lower the cost raises `λ` and is solved again from the same linearization. The solve
stops when the Gauss-Newton model predicts a decrease of the cost below `tol` (the cost
is `½χ²`, so `tol` is in units of `-log L`), as `TruncatedGaussNewton` does.

`reweight` holds estimated noise stds at their ML values as `gauss_newton`'s does: the
weights are set from the residuals at the start of each iteration and held through its
trial steps (a majorize-minimize step of the profiled likelihood).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int


class MatrixFreeGaussNewton(eqx.Module):
    """Settings of `matrix_free_gauss_newton`.

    **Arguments:**

    - `min_singular_value`: directions of the reference curvature whose singular value
      is below this are not moved (as `TruncatedGaussNewton`'s).
    - `tol`: stop when the step's predicted decrease of `½χ²` is below `tol` (`-log L`
      units).
    - `cg_rtol`: relative residual at which each CG solve stops.
    - `cg_max_steps`: CG iterations at most per solve (each one forward and one reverse
      product).
    - `initial_damping`: the first `λ`, relative to the largest reference curvature.
    - `max_step`: largest change of any parameter per step (log units for positive
      parameters, °C for starts).
    - `max_backtracks`: rejected trial steps at most per iteration.
    """

    min_singular_value: float = 1.0
    tol: float = 1e-4
    cg_rtol: float = 1e-3
    cg_max_steps: int = eqx.field(static=True, default=50)
    initial_damping: float = 1e-6
    max_step: float = 1.0
    max_backtracks: int = eqx.field(static=True, default=20)


class MatrixFreeSolution(eqx.Module):
    """What `matrix_free_gauss_newton` returns."""

    value: Float[Array, " params"]
    cost: Float[Array, ""]  # ½ Σ (w r)² at `value`, with the last weights
    num_steps: Int[Array, ""]  # linearizations (Gauss-Newton iterations)
    converged: Bool[Array, ""]
    num_products: Int[Array, ""]  # forward + reverse product pairs over all solves
    num_evaluations: Int[Array, ""]  # residual evaluations at trial points
    residuals: Array  # unweighted, at `value`
    weights: Array  # `reweight`'s last weights


# On an accepted step `λ` shrinks by at most this factor (Nielsen's rule: 1/3). The
# preconditioned steps are good far out: on a 100-node chain 1/3 took 46 steps.
_MIN_DAMPING_FACTOR = 0.1


def _capped(dx, max_step):
    return dx * jnp.minimum(1.0, max_step / jnp.maximum(jnp.max(jnp.abs(dx)), 1e-300))


def matrix_free_gauss_newton(fn: Callable, theta0: Float[Array, " params"], args,
                             V: Float[Array, "params params"], mu: Float[Array, " params"],
                             solver: MatrixFreeGaussNewton = MatrixFreeGaussNewton(),
                             max_steps=100, reweight: Callable | None = None
                             ) -> MatrixFreeSolution:
    """Minimise `½‖w · fn(theta, args)‖²` by preconditioned matrix-free
    Levenberg-Marquardt steps.

    **Arguments:**

    - `fn`: residuals `fn(theta, args)`, one array.
    - `theta0`: the start (params,).
    - `V`, `mu`: the reference curvature's eigenvectors (params, params) and eigenvalues
      (params,) (`jnp.linalg.eigh` of `JᵀJ` at or near `theta0`, weighted alike).
    - `solver`: the settings.
    - `max_steps`: linearizations at most.
    - `reweight`: `reweight(r) -> w`, weights broadcastable against the residuals, set at
      the start of every iteration (default 1).

    **Returns:** a `MatrixFreeSolution`. Pure and jittable.
    """
    mu = jnp.maximum(mu, 0.0)

    def weights(r):
        return jnp.ones((), r.dtype) if reweight is None else reweight(r)

    def half_ss(x):
        c = 0.5 * jnp.sum(x ** 2)
        return jnp.where(jnp.isfinite(c), c, jnp.inf)

    structure = jax.eval_shape(lambda: theta0)

    def body(c):
        theta = c["theta"]
        r, lin = jax.linearize(lambda t: fn(t, args), theta)
        w = weights(r)
        transposed = jax.linear_transpose(lin, theta)

        def J(v):
            return w * lin(v)

        def JT(s):
            return transposed(w * s)[0]

        # the reference curvature reweighted alike (by the mean squared weight of the
        # measured rows: the weights move the noise stds, all by similar factors)
        measured = r != 0
        s2 = jnp.sum(jnp.where(measured, jnp.broadcast_to(w, r.shape) ** 2, 0.0)) / \
            jnp.maximum(jnp.sum(measured), 1)
        mu_w = s2 * mu
        keep = jnp.sqrt(mu_w) > solver.min_singular_value

        def project(v):
            return V @ jnp.where(keep, V.T @ v, 0.0)

        rw = w * r
        cost = half_ss(rw)
        g = project(JT(rw))

        def trial(t):
            lam = t["lam"]

            def normal(v):
                pv = project(v)
                return project(JT(J(pv)) + lam * pv) + (v - pv)

            op = lx.FunctionLinearOperator(normal, structure, lx.positive_semidefinite_tag)
            precond = lx.FunctionLinearOperator(
                lambda v: V @ (jnp.where(keep, 1.0 / (mu_w + lam), 1.0) * (V.T @ v)),
                structure, lx.positive_semidefinite_tag)
            sol = lx.linear_solve(op, -g, lx.CG(rtol=solver.cg_rtol, atol=0.0,
                                                max_steps=solver.cg_max_steps),
                                  options={"preconditioner": precond}, throw=False)
            dx = _capped(project(sol.value), solver.max_step)
            predicted = -(g @ dx) - 0.5 * jnp.sum(J(dx) ** 2)
            new_cost = half_ss(w * fn(theta + dx, args))
            rho = (cost - new_cost) / jnp.maximum(predicted, 1e-300)
            ok = (rho > 0) & (new_cost < cost)
            return {"lam": jnp.where(ok, lam, lam * t["nu"]),
                    "nu": jnp.where(ok, 2.0, 2 * t["nu"]), "j": t["j"] + 1, "ok": ok,
                    "dx": dx, "rho": rho, "predicted": predicted,
                    "products": t["products"] + sol.stats["num_steps"] + 1,
                    "evals": t["evals"] + 1}

        lam0 = jnp.where(c["k"] == 0, solver.initial_damping * jnp.max(mu_w), c["lam"])
        t0 = {"lam": lam0, "nu": 2.0 * jnp.ones_like(lam0), "j": jnp.zeros((), int),
              "ok": jnp.zeros((), bool), "dx": jnp.zeros_like(theta),
              "rho": jnp.zeros_like(c["lam"]), "predicted": jnp.zeros_like(c["lam"]),
              "products": c["products"], "evals": c["evals"]}
        t = jax.lax.while_loop(lambda t: ~t["ok"] & (t["j"] < solver.max_backtracks),
                               trial, t0)
        theta = jnp.where(t["ok"], theta + t["dx"], theta)
        new_lam = jnp.where(t["ok"], t["lam"] * jnp.maximum(
            _MIN_DAMPING_FACTOR, 1 - (2 * jnp.minimum(t["rho"], 1.0) - 1) ** 3), t["lam"])
        # converged: the step predicted (nearly) nothing, taken or not
        done = t["predicted"] < solver.tol
        k = c["k"] + 1
        return {"theta": theta, "lam": new_lam, "k": k,
                "finished": done | ~t["ok"] | (k >= max_steps), "converged": done,
                "products": t["products"], "evals": t["evals"]}

    dtype = theta0.dtype
    init = {"theta": theta0, "lam": jnp.ones((), dtype),
            "k": jnp.zeros((), int), "finished": jnp.zeros((), bool),
            "converged": jnp.zeros((), bool), "products": jnp.zeros((), int),
            "evals": jnp.zeros((), int)}
    c = jax.lax.while_loop(lambda c: ~c["finished"], body, init)
    r = fn(c["theta"], args)
    w = weights(r)
    return MatrixFreeSolution(c["theta"], half_ss(w * r), c["k"], c["converged"],
                              c["products"], c["evals"], r, w)
