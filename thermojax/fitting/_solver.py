"""A Gauss-Newton solver for grey-box fits whose data cannot determine every direction.

Thermal networks measured at a few nodes always have such directions (a fast,
unsensed proof mass: its capacitance and conductance move together without
changing any reading). Plain Gauss-Newton takes enormous steps along them;
Levenberg-Marquardt damps them but crawls. `TruncatedGaussNewton` solves the
Gauss-Newton step by SVD (through the eigendecomposition of `JᵀJ`) and leaves
out every direction whose singular value is below `min_singular_value` (with
residuals weighted by their noise std,
`1/s` is the data's std along that direction, in parameter units: for
log-parameters, `s < 1` means the data cannot pin it within a factor e). So
the identifiable part converges quadratically, the rest stays where it
started, and the identifiability report reads the same threshold. Steps are
damped as in Levenberg-Marquardt (far from the optimum a full Gauss-Newton
step can cut a weakly coupled node off the network, a basin it never leaves)
and capped at `max_step` in the max norm (log units: a factor e per step).
Near the optimum the weakly identifiable directions of such networks lie along
curved valleys, where damped steps crawl (tens of steps of a few per cent
each); every step therefore carries a geodesic-acceleration correction
(Transtrum and Sethna: the second-order change of the residuals along the step,
from one extra residual evaluation), which lets the damping fall up to ten times
per accepted step instead of three. It stops when the Gauss-Newton model
predicts a cost decrease below `tol` on the identifiable part: a criterion in
likelihood units, blind to directions that cannot move.

Any optimistix least-squares solver (`optx.LevenbergMarquardt`, ...) may be
passed to `fit` instead.
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._newton import TruncatedNewton


class GaussNewtonSolution(eqx.Module):
    """What `gauss_newton` returns: the parameters, and how the solve went.

    `residuals`, `grams`, `jacobian` and `aux` are those of the last Jacobian evaluation,
    taken at `value` (the solver always ends on an evaluation at its final point).
    """

    value: Float[Array, " params"]
    cost: Float[Array, ""]  # ½ Σ r², at `value`
    num_steps: Int[Array, ""]  # Jacobian evaluations (Gauss-Newton iterations)
    converged: Bool[Array, ""]  # the identifiable part's predicted decrease fell below tolerance
    num_truncated: Int[Array, ""]  # directions left out at the last step
    residuals: object  # the residuals (a pytree of arrays, as `fn` returns them)
    grams: object  # JᵀJ of each leaf of the residuals (the same pytree, leaves (params, params))
    aux: object = None  # what `jac` returned besides residuals and Jacobian, at `value`
    num_evaluations: Int[Array, ""] = None  # residual evaluations (trial points)
    weights: object = None  # `reweight`'s last weights (residuals and grams carry them)
    jacobian: object = None  # the last Jacobian, each leaf (rows, params), weighted alike
    hint: object = None  # with `hinted`: the hint at `value` (what its Jacobian reused)


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
    - `initial_damping`: the first step's damping `λ`, relative to the largest
      squared singular value (1e-3: cautious, for a start far from the optimum;
      a warm start near the optimum can use far less).
    - `acceleration`: add the geodesic-acceleration correction (Transtrum and
      Sethna 2012) to every step, at the price of one more residual evaluation
      per trial step; a step whose correction is larger than `max_acceleration`
      times the velocity (in norm) is rejected as too curved.

    The iteration limit is `gauss_newton`'s `max_steps`, as in optimistix.
    """

    min_singular_value: float = 1.0
    max_step: float = 1.0
    tol: float = 1e-4
    max_backtracks: int = eqx.field(static=True, default=30)
    initial_damping: float = 1e-3
    acceleration: bool = eqx.field(static=True, default=True)
    max_acceleration: float = 0.75


def _flat_rows(J):
    """A Jacobian pytree with each leaf as a (rows, params) matrix."""
    return jax.tree.map(lambda x: x.reshape(-1, x.shape[-1]), J)


def _grams(J):
    """`JᵀJ` of each leaf of a flat-rows Jacobian pytree."""
    return jax.tree.map(lambda x: x.T @ x, J)


def _jt_dot(J, r):
    """`Jᵀ r` for residual-shaped `r`: (params,)."""
    return sum(ri.reshape(-1) @ x for x, ri in
               zip(jax.tree.leaves(J), jax.tree.leaves(r), strict=True))


def _j_dot(J, v, like):
    """`J v`, shaped like the residuals `like`."""
    return jax.tree.map(lambda x, r: (x @ v).reshape(r.shape), J, like)


def _half_sum_squares(r):
    c = 0.5 * sum(jnp.sum(x ** 2) for x in jax.tree.leaves(r))
    return jnp.where(jnp.isfinite(c), c, jnp.inf)


def _capped(dx, max_step):
    """`dx` scaled down to at most `max_step` in the max norm."""
    return dx * jnp.minimum(1.0, max_step / jnp.maximum(jnp.max(jnp.abs(dx)), 1e-300))


# Finite-difference step (relative to the velocity) of the directional second derivative.
_ACCEL_H = 0.1
# On an accepted step `λ` shrinks by at most this factor (Nielsen's rule allows 1/3; with
# the accelerated steps the quadratic model is trustworthy further out).
_MIN_DAMPING_FACTOR = 0.1


class _Linearization(eqx.Module):
    """The residuals at `theta` and the truncated SVD of their Jacobian,
    `J = U diag(s) Vᵀ` from the eigendecomposition of `JᵀJ`: what every trial step
    of one iteration reuses."""

    r: object  # residuals (pytree)
    J: object  # Jacobian, each leaf (rows, params)
    grams: object  # JᵀJ of each leaf (params, params)
    cost: Float[Array, ""]  # ½ Σ r²
    V: Float[Array, "params params"]
    s: Float[Array, " params"]  # singular values
    keep: Bool[Array, " params"]  # directions above `min_singular_value`
    Ur: Float[Array, " params"]  # Uᵀ r on the kept directions

    def project(self, x):
        """`Uᵀ x` on the kept directions, for residual-shaped `x`."""
        s_safe = jnp.where(self.keep, self.s, 1.0)
        return jnp.where(self.keep, (self.V.T @ _jt_dot(self.J, x)) / s_safe, 0.0)

    def velocity(self, lam, max_step):
        """The damped truncated Gauss-Newton step `v` (params,), its filter factors `f`
        and the cost decrease `½‖r‖² - ½‖r + J v‖²` it predicts."""
        f = jnp.where(self.keep, self.s / (self.s ** 2 + lam), 0.0)
        coef = f * self.Ur
        scale = jnp.minimum(1.0, max_step / jnp.maximum(jnp.max(jnp.abs(self.V @ coef)),
                                                        1e-300))
        predicted = jnp.sum(scale * coef * self.s * self.Ur - 0.5 * (scale * coef * self.s) ** 2)
        return -scale * (self.V @ coef), f, predicted


def _linearize(r, J, solver: TruncatedGaussNewton) -> _Linearization:
    J = _flat_rows(J)  # every use reads the same (rows, params) matrices
    grams = _grams(J)
    mu, V = jnp.linalg.eigh(sum(jax.tree.leaves(grams)))
    s = jnp.sqrt(jnp.maximum(mu, 0.0))
    keep = s > solver.min_singular_value
    lin = _Linearization(r, J, grams, _half_sum_squares(r), V, s, keep, jnp.zeros_like(s))
    return eqx.tree_at(lambda x: x.Ur, lin, lin.project(r))


def _acceleration(lin: _Linearization, v, f, r_probe, solver: TruncatedGaussNewton):
    """The accelerated, capped step `v + a/2` from the residuals `r_probe` at
    `theta + h v`, and whether it is too curved (`‖a‖/2 > max_acceleration ‖v‖`)."""
    r_vv = jax.tree.map(lambda a, b, c: (2.0 / _ACCEL_H) * ((a - b) / _ACCEL_H - c),
                        r_probe, lin.r, _j_dot(lin.J, v, lin.r))
    a = -(lin.V @ (f * lin.project(r_vv)))
    curved = (2.0 * jnp.linalg.norm(a) > solver.max_acceleration * jnp.linalg.norm(v)) \
        | ~jnp.all(jnp.isfinite(a))
    return _capped(v + 0.5 * a, solver.max_step), curved


def _trial_steps(fn, theta, args, lin: _Linearization, lam, first, n_eval, hint,
                 solver: TruncatedGaussNewton, evaluate_first: bool):
    """Trial steps from `theta` until one lowers the cost, one residual evaluation per
    pass (`fn(point, args) -> (residuals, its hint)`). With acceleration a trial takes two
    passes: a probe at `theta + h v` (for the directional second derivative), then the
    cost at `theta + v + a/2`. A failed trial raises `λ` (Nielsen: `λ ν`, `ν 2ν`). Returns
    the loop's final carry; its `hint` is the accepted point's (else `hint`).

    `first` (before any Jacobian; `lin` is a placeholder): no step; with
    `evaluate_first`, one evaluation at `theta` itself, accepted, for its hint."""
    accel = solver.acceleration

    def body(t):
        v, f, predicted = lin.velocity(t["lam"], solver.max_step)
        probe = t["probe"]
        step = jnp.where(probe, _ACCEL_H * v, t["dx"] if accel else v)
        r_pt, h_pt = fn(theta + jnp.where(first, 0.0, step), args)
        if accel:
            dx, curved = jax.lax.cond(probe, lambda _: _acceleration(lin, v, f, r_pt, solver),
                                      lambda _: (t["dx"], jnp.zeros((), bool)), None)
        else:
            dx, curved = v, jnp.zeros((), bool)
        # A trial ends after its cost evaluation, or after a probe that found the step
        # too curved (a failure).
        new_cost = jnp.where(probe, jnp.inf, _half_sum_squares(r_pt))
        rho = (lin.cost - new_cost) / jnp.maximum(predicted, 1e-300)
        success = first | (rho > 0)
        failed = (~probe | curved) & ~success
        j = t["j"] + failed
        return {
            "lam": jnp.where(failed, t["lam"] * t["nu"], t["lam"]),
            "nu": jnp.where(failed, 2 * t["nu"], t["nu"]),
            "j": j,
            "probe": failed if accel else probe,  # a new trial starts with a probe
            "dx": dx, "rho": rho,
            "over": success | (j > solver.max_backtracks),
            "n_eval": t["n_eval"] + 1,
            "hint": jax.tree.map(lambda a, b: jnp.where(success, a, b), h_pt, t["hint"]),
        }

    t0 = {"lam": lam, "nu": 2.0 * jnp.ones(()), "j": jnp.zeros((), int),
          "probe": ~first if accel else jnp.zeros((), bool),
          "dx": jnp.zeros_like(theta), "rho": -jnp.inf * jnp.ones(()),
          "over": first & (not evaluate_first),
          "n_eval": n_eval, "hint": hint}
    return jax.lax.while_loop(lambda t: ~t["over"], body, t0)


def _damping_after(lam, rho, accel: bool):
    """Nielsen's update of `λ` after an accepted step with gain ratio `rho`."""
    return lam * jnp.maximum(_MIN_DAMPING_FACTOR if accel else 1 / 3,
                             1 - (2 * jnp.minimum(rho, 1.0) - 1) ** 3)


def _weighted(w, r):
    """Each leaf of `r` times its weight in `w` (a pytree prefix of `r`); `w` None: `r`."""
    return r if w is None else jax.tree.map(lambda wi, x: wi * x, w, r)


def gauss_newton(fn: Callable, theta0: Float[Array, " params"], args,
                 solver: TruncatedGaussNewton = TruncatedGaussNewton(),
                 jac: Callable | None = None, max_steps=100,
                 reweight: Callable | None = None, hinted: bool = False
                 ) -> GaussNewtonSolution:
    """Minimise `½‖fn(theta, args)‖²`: truncated Gauss-Newton steps with geodesic
    acceleration, damped Levenberg-Marquardt style (Nielsen's update of `λ`) and capped.

    **Arguments:**

    - `fn`: residuals `fn(theta, args)`, a pytree of arrays (e.g. data rows and prior
      rows, each in the layout that is cheapest to produce).
    - `theta0`: the start (params,).
    - `solver`: the settings.
    - `jac`: `jac(theta, args) -> (r, J, aux)`: the residuals, their Jacobian (the same
      pytree, each leaf (*rows, params) as `jax.jacfwd` gives it) and anything wanted at
      the solution (`aux`, e.g. predictions); default `jax.jacfwd(fn)`, `aux = None`.
    - `max_steps`: Jacobian evaluations at most (an int or an integer array: a traced
      limit does not recompile); the last one only evaluates.
    - `reweight`: `reweight(r) -> w`, weights (a pytree prefix of the residuals: one
      scalar per block) computed from the residuals at the start of every iteration and
      held through its trial steps, which then minimise `½‖w r‖²`. With `w_k =
      sqrt(N_k / ‖r_k‖²)` this maximises the likelihood profiled over each block's noise
      std, `-Σ_k (N_k/2) log ‖r_k‖²`: since `log` is concave, a step that lowers the
      weighted cost lowers the profiled one (a majorize-minimize step), and a point where
      the weighted step predicts no decrease is a stationary point of the profiled
      likelihood. One solve replaces fit / re-estimate the stds / refit passes.
    - `hinted`: `fn` returns `(residuals, hint)` and `jac` takes the hint at the same
      point as a third argument: what the residuals computed that the Jacobian reuses
      (simulated states); the hint of each accepted point is kept for its Jacobian.

    **Returns:** a `GaussNewtonSolution`, ending on an evaluation at its `value`
    (with `reweight`, its residuals, grams and cost weighted by the last `weights`).

    Each iteration takes one Jacobian and the eigendecomposition of `JᵀJ`; trial steps
    reuse them, each costing one or two residual evaluations. `fn` and `jac` each appear
    once in the traced program (compile time grows with every copy: with `hinted`, the
    start's hint comes from the trial loop's own `fn`, as a first evaluation without a
    step). Pure and jittable.
    """
    if jac is None:
        def jac(theta, args):
            J, r = jax.jacfwd(lambda t: (fn(t, args),) * 2, has_aux=True)(theta)
            return r, J, None

    if hinted:
        fn_hint, jac_hint = fn, jac
    else:
        def fn_hint(theta, args):
            return fn(theta, args), None

        def jac_hint(theta, args, _hint):
            return jac(theta, args)

    # `jax.jit` (nested: inlined by XLA) keeps each function's trace, so the shapes taken
    # below and the loop's calls trace it once (tracing the Jacobian is much of the time
    # a fit takes when its compiled program is cached).
    evaluated = jax.jit(lambda theta: fn_hint(theta, args))

    @jax.jit
    def linearized(theta, hint):
        """The Jacobian at `theta` (with its point's `hint`), weighted by `reweight`."""
        r, J, aux = jac_hint(theta, args, hint)
        w = None if reweight is None else reweight(r)
        return _linearize(_weighted(w, r), _weighted(w, J), solver), aux, w

    def zeros(x):
        return jnp.zeros(x.shape, x.dtype)

    hint_like = jax.eval_shape(evaluated, theta0)[1]
    lin_like, aux_like, w_like = jax.eval_shape(linearized, theta0, hint_like)

    # Each iteration: trial steps from the last linearization, then the Jacobian at the
    # accepted point. The first has no linearization yet: its "trial" evaluates `fn` at
    # the start (for the hint), so that `fn` appears once in the traced program.
    def body(c):
        theta, k, lin, w = c["theta"], c["k"], c["lin"], c["w"]
        first = k == 0

        def weighted_fn(x, a):
            r_x, h_x = evaluated(x)
            return _weighted(w, r_x), h_x

        t = _trial_steps(weighted_fn, theta, args, lin, c["lam"], first, c["n_eval"],
                         c["hint"], solver, evaluate_first=hinted)
        better = first | (t["rho"] > 0)
        theta = jnp.where(better & ~first, theta + t["dx"], theta)
        lam = jnp.where(better & ~first,
                        _damping_after(t["lam"], t["rho"], solver.acceleration), t["lam"])
        # No better point: the last Jacobian was the solution's, the loop ends on it.
        lin, aux, w = jax.lax.cond(better, lambda _: linearized(theta, t["hint"]),
                                   lambda _: (lin, c["aux"], w), None)
        done = (0.5 * jnp.sum(lin.Ur ** 2) < solver.tol) & jnp.isfinite(lin.cost)
        # The last allowed iteration only evaluates (the solution ends on an evaluation).
        stop = done | (k + 1 >= max_steps) | ~jnp.isfinite(lin.cost)
        return {
            "theta": theta, "k": k + better, "lin": lin, "w": w, "aux": aux,
            "lam": jnp.where(first, solver.initial_damping * jnp.max(lin.s) ** 2, lam),
            "finished": stop | ~better, "converged": done, "n_out": jnp.sum(~lin.keep),
            "n_eval": t["n_eval"], "hint": t["hint"],
        }

    false = jnp.zeros((), bool)
    init = {"theta": theta0, "k": jnp.zeros((), int), "lam": jnp.ones(()), "finished": false,
            "converged": false, "n_out": jnp.zeros((), int),
            "lin": jax.tree.map(zeros, lin_like), "aux": jax.tree.map(zeros, aux_like),
            "w": jax.tree.map(zeros, w_like), "n_eval": jnp.zeros((), int),
            "hint": jax.tree.map(zeros, hint_like)}
    c = jax.lax.while_loop(lambda c: ~c["finished"], body, init)
    lin = c["lin"]
    return GaussNewtonSolution(c["theta"], lin.cost, c["k"], c["converged"], c["n_out"],
                               lin.r, lin.grams, c["aux"], c["n_eval"], c["w"], lin.J,
                               c["hint"] if hinted else None)


def traced_settings(solver, max_steps: int):
    """`(solver, max_steps)`, for a truncated solver (`TruncatedGaussNewton`,
    `TruncatedNewton`) as arrays, so that other tolerances, dampings or limits share one
    compilation; an optimistix solver's unchanged (optimistix wants a static limit)."""
    if not isinstance(solver, (TruncatedGaussNewton, TruncatedNewton)):
        return solver, max_steps
    return (jax.tree.map(lambda x: jax.device_put(np.asarray(x, float)), solver),
            jax.device_put(np.asarray(max_steps)))
