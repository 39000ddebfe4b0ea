"""Output error on long logs: the normal equations summed stretch by stretch.

The forward path (`_output_error`) holds the residuals' Jacobian, one number per sensor
reading and free parameter, 2.6 copies of it at its peak (`_size.JACOBIAN_COPIES`):
10⁶ samples of three sensors and 22 free parameters take 1.4 GB, 10⁷ would take 14 GB.
A Gauss-Newton step needs only sums over the samples: `JᵀJ` (P, P), `Jᵀr` (P,) and
`Σ r²`. Here each run is cut into stretches of `STRETCH` samples, each simulated from the
last one's end state together with that state's tangents along every parameter
(`dynamics._sensitivity.chunk_outputs_and_tangents`, the forward path's own blocked
recurrence), and only its per-sensor sums are kept. The memory is one stretch's Jacobian
whatever the log's length; the time grows like the samples.

The steps are `TruncatedGaussNewton`'s (the SVD of the weighted Jacobian from the
eigendecomposition of `JᵀJ`, directions below `min_singular_value` left out, damped as in
Levenberg-Marquardt, capped at `max_step`), without the geodesic acceleration, which
needs `Jᵀ` of a second residual and so a second pass per trial. The estimated noise stds
are set to their ML values at each linearization and held through its trial steps (the
likelihood profiled over them, as `_output_error._ml_weights`).
"""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._blocked import _BLOCK
from ..dynamics._sensitivity import chunk_outputs, chunk_outputs_and_tangents, dataset_maps, \
    map_tangents
from ..model._parameters import free_parameters
from ._likelihood import output_error_nll_from_sums
from ._problem import Prepared, Solution, _check_finite, _model_of, make_problem, \
    output_error_solution
from ._solver import TruncatedGaussNewton, _damping_after, _Linearization

#: Samples per stretch (a whole number of blocks): with three sensors and 22 free
#: parameters its Jacobian is 35 MB.
STRETCH = 2 ** 16
#: The report's words for this path.
METHOD = ("Gauss-Newton on normal equations summed over stretches of the log (the "
          "residuals' Jacobian never held whole)")


@jax.jit
def _small_parts(theta, problem):
    """Each run's blocked maps and start with their tangents along every parameter, and
    the output offset with its tangents (`map_tangents`)."""
    return map_tangents(lambda t: _model_of(t, problem), theta, problem.data)


@jax.jit
def _maps(theta, problem):
    """`(maps, z0)` of every run and the output offset (p,): `_small_parts` without
    tangents."""
    model, run_initial = _model_of(theta, problem)
    return dataset_maps(model, problem.data, run_initial), model.output_offset()


@jax.jit
def _stretch_sums(maps, dmaps, offset, doffset, s, ds, u, y, mask):
    """One stretch's per-sensor sums `(Σ r² (p,), JᵀJ (p, P, P), Jᵀr (p, P))` of the
    unweighted residuals `r = y - ŷ` (°C, zero where `mask` is False), and the next
    stretch's start with its tangents. `u` (samples, m), `y`, `mask` (samples, p), whole
    blocks."""
    yp, dy, s_next, ds_next = chunk_outputs_and_tangents(maps, dmaps, s, ds, u)
    r = jnp.where(mask, y - (yp + offset[None, :]), 0.0)
    J = jnp.where(mask[..., None], -(dy + doffset.T[None]), 0.0)
    return (jnp.sum(r ** 2, axis=0), jnp.einsum("tka,tkb->kab", J, J),
            jnp.einsum("tka,tk->ka", J, r), s_next, ds_next)


@jax.jit
def _stretch_cost(maps, offset, s, u, y, mask):
    """One stretch's `Σ r²` per sensor (p,), its predictions (samples, p) °C and the next
    stretch's start."""
    yp, s_next = chunk_outputs(maps, s, u)
    yp = yp + offset[None, :]
    return jnp.sum(jnp.where(mask, y - yp, 0.0) ** 2, axis=0), yp, s_next


def _stretches(prep: Prepared, stretch: int):
    """`(run, first sample, inputs, readings, mask)` of every stretch of every run, each
    `stretch` samples long, rounded up to whole blocks (a run's last one padded with its
    last input, unmeasured); a run shorter than `stretch` is one stretch of its whole
    blocks."""
    stretch = -(-stretch // _BLOCK) * _BLOCK
    data = prep.data
    inputs, outputs, mask = (np.asarray(a) for a in (data.inputs, data.outputs, data.mask))
    for r, T in enumerate(data.lengths):
        size = min(stretch, -(-T // _BLOCK) * _BLOCK)
        for a in range(0, T, size):
            b = min(a + size, T)
            pad = size - (b - a)
            u = np.concatenate([inputs[r, a:b], np.repeat(inputs[r, b - 1:b], pad, 0)])
            y = np.concatenate([outputs[r, a:b], np.zeros((pad, outputs.shape[2]))])
            m = np.concatenate([mask[r, a:b], np.zeros((pad, mask.shape[2]), bool)])
            yield r, a, u, y, m


def _pick(tree, r):
    return jax.tree.map(lambda x: x[r], tree)


def normal_equations(theta, problem, prep: Prepared, stretch: int):
    """At `theta`: `(Σ r² (p,), JᵀJ (p, P, P), Jᵀr (p, P))` per sensor over every run, of
    the unweighted residuals (°C), one stretch at a time."""
    ((maps, z0), offset), ((dmaps, dz0), doffset) = _small_parts(theta, problem)
    ss = gram = grad = 0.0
    start = {}
    for r, a, u, y, m in _stretches(prep, stretch):
        s, ds = start.get(r, (z0[r], dz0[r]))
        ss_k, gram_k, grad_k, s, ds = _stretch_sums(_pick(maps, r), _pick(dmaps, r),
                                                    offset, doffset, s, ds, u, y, m)
        start[r] = (s, ds)
        ss, gram, grad = ss + ss_k, gram + gram_k, grad + grad_k
    return np.asarray(ss), np.asarray(gram), np.asarray(grad)


def sum_of_squares(theta, problem, prep: Prepared, stretch: int,
                   predictions: bool = False):
    """At `theta`: `Σ r²` per sensor (p,) over every run (°C²); with `predictions`, also
    the free-run predictions (runs, times, p) °C."""
    (maps, z0), offset = _maps(theta, problem)
    data = prep.data
    ss = 0.0
    out = (np.zeros((len(data.lengths), data.outputs.shape[1], data.outputs.shape[2]))
           if predictions else None)
    start = {}
    for r, a, u, y, m in _stretches(prep, stretch):
        ss_k, yp, start[r] = _stretch_cost(_pick(maps, r), offset, start.get(r, z0[r]), u,
                                           y, m)
        ss = ss + ss_k
        if predictions:
            b = min(a + u.shape[0], data.lengths[r])
            out[r, a:b] = np.asarray(yp[:b - a])
    ss = np.asarray(ss)
    return (ss, out) if predictions else ss


def _ml_stds(ss, counts, prep: Prepared) -> np.ndarray:
    """Each estimated sensor's ML noise std `sqrt(Σ r² / N)` (floored at 1e-12 °C), the
    fixed ones the file's (p,)."""
    ml = np.sqrt(ss / np.maximum(counts, 1))
    return np.where(prep.fixed_sigma, prep.sigma, np.maximum(ml, 1e-12))


def _linearization(ss, gram, grad, sigma, solver: TruncatedGaussNewton) -> _Linearization:
    """The truncated SVD of the residuals weighted by `sigma`, from their normal equations
    (no residuals or Jacobian: `velocity` needs only these)."""
    w2 = 1.0 / sigma ** 2
    H = np.einsum("k,kab->ab", w2, gram)
    g = np.einsum("k,ka->a", w2, grad)
    mu, V = np.linalg.eigh(H)
    s = np.sqrt(np.maximum(mu, 0.0))
    keep = s > solver.min_singular_value
    Ur = np.where(keep, (V.T @ g) / np.where(keep, s, 1.0), 0.0)
    return _Linearization(None, None, H, 0.5 * float(np.sum(w2 * ss)), V, s, keep, Ur)


def fit_normal_equations(prep: Prepared, max_steps: int, say,
                         solver: TruncatedGaussNewton | None = None,
                         stretch: int | None = None) -> tuple[Solution, str]:
    """The output-error stage of a linear model without bias columns (one start: the
    file's values) on normal equations summed stretch by stretch: a `Solution` like
    `_output_error.fit_output_error`'s, and the method in words for the report. Each
    iteration takes one pass with the Jacobian and one cost pass per trial step; progress
    is said after each. `stretch`: samples per stretch (default `STRETCH`)."""
    solver = solver or TruncatedGaussNewton()
    stretch = -(-(stretch or STRETCH) // _BLOCK) * _BLOCK
    theta0 = free_parameters(prep.template, prep.index)
    problem = make_problem(prep.template, prep.index, prep.data, prep.sigma, theta0)
    counts = prep.mask().sum(axis=(0, 1))
    n_stretches = sum(-(-T // stretch) for T in prep.data.lengths)
    say(f"normal equations summed over {n_stretches} stretch(es) of up to {stretch:,} "
        "samples per pass")
    theta = np.asarray(theta0)
    t0 = time.perf_counter()
    ss, gram, grad = normal_equations(jax.device_put(theta), problem, prep, stretch)
    sigma = _ml_stds(ss, counts, prep)
    lin = _linearization(ss, gram, grad, sigma, solver)
    lam = solver.initial_damping * float(np.max(lin.s)) ** 2
    steps, evaluations, converged = 0, 0, False
    while True:
        converged = 0.5 * float(np.sum(lin.Ur ** 2)) < solver.tol
        if converged or steps >= max_steps - 1:
            break
        nu, accepted = 2.0, False
        for _ in range(solver.max_backtracks + 1):
            v, _, predicted = lin.velocity(lam, solver.max_step)
            v = np.asarray(v)
            trial = sum_of_squares(jax.device_put(theta + v), problem, prep, stretch)
            evaluations += 1
            cost = 0.5 * float(np.sum(trial / sigma ** 2))
            rho = (lin.cost - cost) / max(float(predicted), 1e-300)
            if np.isfinite(cost) and rho > 0:
                accepted = True
                break
            lam, nu = lam * nu, 2 * nu
        if not accepted:
            break
        theta = theta + v
        lam = float(_damping_after(lam, rho, False))
        steps += 1
        ss, gram, grad = normal_equations(jax.device_put(theta), problem, prep, stretch)
        sigma = _ml_stds(ss, counts, prep)
        lin = _linearization(ss, gram, grad, sigma, solver)
        say(f"long log: step {steps}, -log L "
            f"{output_error_nll_from_sums(ss, counts, sigma):.2f} "
            f"({time.perf_counter() - t0:.0f} s)")
    _check_finite(theta, theta0, prep.names)
    ss, predictions = sum_of_squares(jax.device_put(theta), problem, prep, stretch,
                                     predictions=True)
    nll = output_error_nll_from_sums(ss, counts, sigma)
    sol = output_error_solution(prep, theta, theta0, sigma, lin.grams, nll, steps + 1,
                                converged, predictions, evaluations)
    return sol, METHOD
