"""Output error for large networks: residuals by the exponential times a vector,
gradients by reverse mode, steps matrix-free.

A fit of a large network (many nodes, many free parameters) takes this path instead of
the forward sensitivities (`_output_error`, whose Jacobian carries one `2n × 2n` block
per parameter: memory like `P (2n)²`, time like `P n³`):

- residuals from `dynamics._taylor_hold`: the same exact discretization, summed as the
  exponential of the sparse generator times each sample's state (`O(T (n + e))` per
  simulation, `e` links); its series terms are kept for the products (`runs · T · d · n`
  numbers), or, beyond `_KEPT_BYTES`, each sample period is checkpointed and recomputed
  (one state per sample kept);
- the Gauss-Newton steps matrix-free (`_matrix_free`): a forward and a reverse
  (adjoint) product per CG iteration, so a step's cost does not grow with the number of
  parameters and the memory is that of the simulation, not of a Jacobian
  (samples × parameters);
- the Fisher information `JᵀJ` from the same products (`information`, `P²` numbers): the
  Jacobian's columns `J e_i` by forward products in batches and one matrix product where
  the Jacobian fits in `_JACOBIAN_BYTES`, else `JᵀJ e_i` by forward and reverse pairs
  (half the speed, memory of the simulation only); the CG solves' preconditioner
  (refreshed every `_REFRESH_STEPS` steps) and, at the solution, the standard errors and
  the identifiability report. Beyond `LOCAL_INFORMATION_ABOVE` parameters, where the
  Jacobian is too large to hold, the information of each parameter's sensitivities kept
  near the states it acts on, from a few hundred compressed products
  (`_local_information`; the method says so). Beyond `MAX_INFORMATION_PARAMS` only its
  diagonal is formed and the stds are conditional ones (the fit's `method` says so).

Which path a fit takes is `_size.choose_path` (for linear models without bias columns,
fitted by output error with the default solver): the adjoint one where the forward
sensitivities are predicted to take over a minute or not to fit in memory.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._blas_threads import every_blas_thread
from ..compilation._traced_cache import stored_jit
from ..dynamics._taylor_hold import (SparsePlan, gathered, model_outputs_taylor, plan_norm,
                                     sparse_plan)
from ._local_information import RADIUS, local_information
from ._matrix_free import MatrixFreeGaussNewton, matrix_free_gauss_newton
from ._problem import _model_of, _prior, _Problem
from . import _size

#: Parameters beyond which the information matrix (P² numbers, P products) is not formed.
MAX_INFORMATION_PARAMS = 6000
#: Parameters beyond which, where the Jacobian is too large to hold, the information is
#: the local one (`_local_information`).
LOCAL_INFORMATION_ABOVE = _size.LOCAL_INFORMATION_ABOVE
#: Bytes of kept series terms above which each sample period is checkpointed instead.
_KEPT_BYTES = 2e9
#: Directions per batch of products when the information matrix is formed.
_BATCH = 64
#: Bytes of the data residuals' Jacobian (rows × P) up to which the information is formed
#: from its columns (forward products only) rather than by forward and reverse pairs: on a
#: 200-node chain (80,000 rows, 601 parameters, 0.38 GB) 5.4 s against 10.5 s.
_JACOBIAN_BYTES = _size.ADJOINT_JACOBIAN_BYTES


class AdjointProblem(eqx.Module):
    """A `_Problem` with the static structure of its Taylor simulation."""

    problem: _Problem
    plan: SparsePlan = eqx.field(static=True)
    # recompute each sample period's series in reverse mode (`taylor_states`): set where
    # keeping every term would exceed `_KEPT_BYTES`
    checkpoint: bool = eqx.field(static=True, default=False)


def make_plan(problem: _Problem, theta0) -> SparsePlan:
    """The `SparsePlan` of `problem`'s model: non-zeros at `theta0` and at a perturbed
    point (a parameter that starts at zero still gets its entries), the norm bound with
    room for the parameters to move (`sparse_plan`'s margin)."""
    rng = np.random.default_rng(0)
    theta0 = np.asarray(theta0)
    systems = [jax.tree.map(np.asarray, _model_of(jax.device_put(t), problem)[0]
                            .linear_system())
               for t in (theta0, theta0 + 0.01 * rng.standard_normal(theta0.shape))]
    return sparse_plan(systems, float(np.max(np.asarray(problem.data.dt))))


def adjoint_eligible(prep, likelihood: str, solver) -> bool:
    """Whether a fit may take the adjoint path: output error with the default solver, a
    linear model, no bias columns."""
    return (likelihood == "output_error" and solver is None and prep.bias is None
            and not prep.template.model.is_nonlinear)


def adjoint_problem(problem: _Problem, theta0) -> AdjointProblem:
    """`problem` with its `SparsePlan`, checkpointed where keeping every series term of
    every sample would take more than `_KEPT_BYTES`."""
    plan = make_plan(problem, theta0)
    R, T, _ = problem.data.outputs.shape
    kept = 8.0 * R * T * plan.substeps * plan.degree * plan.a_cols.shape[0]
    return AdjointProblem(problem, plan, kept > _KEPT_BYTES)


def _initial(model, system, u0, r0):
    """A run's initial state: its estimated starts where every node has one (no solve),
    else `ThermalModel.initial_state`."""
    n = system.A.shape[0]
    if len(model.initial_nodes) == n and not model.added_nodes:
        idx = np.array(model.initial_nodes)
        values = model.initial[idx] if r0 is None else r0
        return jnp.zeros(n, system.A.dtype).at[idx].set(values)
    return model.initial_state(system, u0, r0)


def adjoint_outputs(theta, ap: AdjointProblem):
    """Free-run sensor readings (runs, T, p) °C of every run at `theta`."""
    problem = ap.problem
    model, run_initial = _model_of(theta, problem)
    system = model.linear_system()
    data = problem.data
    inputs = data.inputs.astype(system.A.dtype)

    def one(u, dt, r0):
        x0 = _initial(model, system, u[0], r0)
        return model_outputs_taylor(model, system, ap.plan, x0, u, dt, ap.checkpoint)

    if run_initial is None or run_initial.shape[1] == 0:
        return jax.vmap(lambda u, dt: one(u, dt, None))(inputs, data.dt)
    return jax.vmap(one)(inputs, data.dt, run_initial)


def adjoint_residuals(theta, ap: AdjointProblem):
    """Weighted data residuals (runs, T, p), zero where nothing was measured, then the
    prior rows (free,) appended as one flat vector."""
    problem = ap.problem
    data = problem.data
    y = adjoint_outputs(theta, ap)
    r = jnp.where(data.mask, data.outputs - y, 0.0) / problem.sigma[None, None, :]
    return jnp.concatenate([r.reshape(-1), _prior(theta, problem)])


def _ml_weights(r, ap: AdjointProblem, estimated):
    """Per-residual weights holding each estimated output's noise std at its ML value
    (`_output_error._ml_weights` in this layout; the prior rows weight 1)."""
    problem = ap.problem
    R, T, p = problem.data.outputs.shape
    data_r = r[:R * T * p].reshape(R, T, p)
    counts = jnp.maximum(jnp.sum(problem.data.mask, axis=(0, 1), dtype=r.dtype), 1.0)
    floor = counts * (1e-12 / problem.sigma) ** 2
    w = jnp.where(estimated, jnp.sqrt(counts / jnp.maximum(jnp.sum(data_r ** 2, (0, 1)),
                                                           floor)), 1.0)
    return jnp.concatenate([jnp.broadcast_to(w, (R, T, p)).reshape(-1),
                            jnp.ones(r.shape[0] - R * T * p, r.dtype)])


@stored_jit
def solve_adjoint(theta0, ap: AdjointProblem, V, mu, solver: MatrixFreeGaussNewton,
                  max_steps, estimated):
    """The matrix-free solve from `theta0`, preconditioned by the curvature `V diag(mu)
    Vᵀ` (`information` at the start, weighted by `ap`'s stds): `(theta, steps, converged, products, evals,
    stds (outputs,), norm)`, `stds` the weights' noise stds, `norm` the Taylor series'
    `‖A dt‖₁` at the solution (the plan must bound it)."""
    sol = matrix_free_gauss_newton(adjoint_residuals, theta0, ap, V, mu, solver, max_steps,
                                   lambda r: _ml_weights(r, ap, estimated))
    p = ap.problem.sigma.shape[0]
    stds = ap.problem.sigma / sol.weights[:p]
    model = _model_of(sol.value, ap.problem)[0]
    norm = plan_norm(model.linear_system(), ap.plan, jnp.max(ap.problem.data.dt))
    return (sol.value, sol.num_steps, sol.converged, sol.num_products, sol.num_evaluations,
            stds, norm)


@stored_jit
def _evaluate(theta, ap: AdjointProblem):
    """`(weighted data residuals (runs, T, p), predictions (runs, T, p) °C)`."""
    problem = ap.problem
    y = adjoint_outputs(theta, ap)
    r = jnp.where(problem.data.mask, problem.data.outputs - y, 0.0) / problem.sigma[None, None, :]
    return r, y


def evaluate(theta, ap: AdjointProblem):
    """At `theta`: the weighted data residuals and the predictions, as NumPy arrays."""
    r, y = _evaluate(theta, ap)
    return np.asarray(r), np.asarray(y)


def _data_linearization(theta, ap: AdjointProblem):
    """The weighted data residuals' linearization at `theta` (`jax.linearize`: `v -> J v`,
    rows of every run, the prior's left out)."""
    def data_r(t):
        return adjoint_residuals(t, ap)[:-theta.shape[0]]

    return jax.linearize(data_r, theta)[1]


@stored_jit
def _information_columns(theta, ap: AdjointProblem, directions):
    """`JᵀJ V` (P, k) of the data residuals for directions `V` (P, k): one forward and
    one reverse product per column, batched."""
    lin = _data_linearization(theta, ap)
    transposed = jax.linear_transpose(lin, theta)
    return jax.vmap(lambda v: transposed(lin(v))[0], in_axes=1, out_axes=1)(directions)


@stored_jit
def _jacobian_columns(theta, ap: AdjointProblem, directions):
    """`J V` (rows, k) of the data residuals for directions `V` (P, k): batched forward
    products."""
    return jax.vmap(_data_linearization(theta, ap), in_axes=1, out_axes=1)(directions)


@stored_jit
def _column_norms(theta, ap: AdjointProblem, directions):
    """`‖J v‖²` (k,) of the data residuals for directions `V` (P, k), batched forward
    products."""
    lin = _data_linearization(theta, ap)
    return jax.vmap(lambda v: jnp.sum(lin(v) ** 2), in_axes=1)(directions)


def _batches(P: int):
    """Unit directions (P, _BATCH) in batches covering `0..P-1` (the last one padded with
    zeros: one compiled shape) and the count of real ones in each."""
    eye = np.eye(P)
    for start in range(0, P, _BATCH):
        cols = eye[:, start:start + _BATCH]
        k = cols.shape[1]
        if k < _BATCH:
            cols = np.concatenate([cols, np.zeros((P, _BATCH - k))], axis=1)
        yield start, k, jax.device_put(cols)


def jacobian_diagonal(theta, ap: AdjointProblem) -> np.ndarray:
    """The diagonal of `JᵀJ` (P,) of the weighted data residuals: each parameter's squared
    column norm, by batched forward products (the solve's Jacobi preconditioner)."""
    out = np.empty(theta.shape[0])
    for start, k, cols in _batches(theta.shape[0]):
        out[start:start + k] = np.asarray(_column_norms(theta, ap, cols))[:k]
    return out


def information(theta, ap: AdjointProblem, say=None) -> np.ndarray | None:
    """The Fisher information `JᵀJ` (P, P) of the weighted data residuals at `theta` from
    matrix-free products (`_BATCH` directions at a time): the Jacobian's columns, then one
    product, where it fits in `_JACOBIAN_BYTES`, else forward and reverse pairs; None
    beyond `MAX_INFORMATION_PARAMS`."""
    P = theta.shape[0]
    if P > MAX_INFORMATION_PARAMS:
        return None
    rows = int(np.prod(ap.problem.data.outputs.shape))
    if 8.0 * rows * P <= _JACOBIAN_BYTES:
        J = np.empty((rows, P))
        for start, k, cols in _batches(P):
            J[:, start:start + k] = np.asarray(_jacobian_columns(theta, ap, cols))[:, :k]
        with every_blas_thread():   # nothing else runs meanwhile
            return J.T @ J
    out = np.empty((P, P))
    for start, k, cols in _batches(P):
        out[:, start:start + k] = np.asarray(_information_columns(theta, ap, cols))[:, :k]
    return 0.5 * (out + out.T)


def with_plan_for(ap: AdjointProblem, norm: float) -> AdjointProblem:
    """`ap` with a plan whose series bounds `norm` (again with a factor 2 of room)."""
    from ..dynamics._taylor_hold import taylor_plan

    plan = ap.plan
    bigger = SparsePlan(plan.a_cols, plan.a_real, plan.c_cols, plan.c_real,
                        *taylor_plan(2.0 * norm), 2.0 * norm, plan.offsets)
    return AdjointProblem(ap.problem, bigger, ap.checkpoint)


#: How the report names the path (`FitResult.method`).
METHOD = ("adjoint: residuals by the exponential of the sparse generator times the state, "
          "matrix-free Gauss-Newton steps (forward and reverse products inside a "
          "preconditioned conjugate-gradient solve)")


def fit_adjoint(prep, max_steps: int, say, solver: MatrixFreeGaussNewton | None = None,
                outer: int = 4):
    """The output-error stage of a large linear network by the adjoint path: a
    `Solution` like `_output_error.fit_output_error`'s (one start: the file's values),
    and the method in words for the report.

    Passes with the noise stds held fixed, each started where the last ended, the
    estimated stds set to their ML values between passes until they settle (`outer`
    passes at most: the optimistix solvers' scheme in `_output_error._reweighted`). Held
    fixed within a pass, the weights leave the curvature's shape alone, so the
    information matrix at a pass's start preconditions its CG solves well: on a 50-node
    chain the ML weights moved inside the solve took 2.6 times the products. Each pass's
    information comes from `P` forward and reverse products in batches
    (`information`); the last one serves the standard errors when its pass moved no
    parameter by more than `_REUSE_STD` of its std, else the information is formed again
    at the solution. Beyond `MAX_INFORMATION_PARAMS` the passes are preconditioned by the
    diagonal of `JᵀJ` only and it is the information reported: each std is then the
    parameter's conditional std (the others held at their values), a lower bound, and the
    method says so."""
    from ..model._parameters import free_parameters
    from ._likelihood import ml_sigma, output_error_nll
    from ._problem import _check_finite, make_problem, output_error_solution

    solver = solver or MatrixFreeGaussNewton()
    theta0 = free_parameters(prep.template, prep.index)
    P = theta0.shape[0]
    mask, estimated = prep.mask(), ~prep.fixed_sigma
    fixed = jax.device_put(np.zeros(estimated.shape, bool))
    sigma = prep.sigma
    ap = adjoint_problem(make_problem(prep.template, prep.index, prep.data, sigma, theta0),
                         theta0)
    say(f"adjoint path: {P} free parameters, {ap.plan.degree}-term series in "
        f"{ap.plan.substeps} substep(s) per sample period"
        + (", diagonal products" if ap.plan.offsets is not None else ""))
    theta, total, evals, kind, note, H, H_sigma = theta0, 0, 0, "exact", "", None, None
    structure = {}   # what every information of this fit shares (`_information_or_diagonal`)
    for it in range(outer):
        ap = AdjointProblem(make_problem(prep.template, prep.index, prep.data, sigma, theta0),
                            ap.plan, ap.checkpoint)
        pass_steps = 0
        while True:
            # a pass whose weights moved little from the last information's starts
            # preconditioned by it (the solve needs a good preconditioner, not the exact one)
            if not (pass_steps == 0 and H is not None
                    and np.all(np.abs(np.log(sigma / H_sigma)) < _REUSE_WEIGHTS)):
                start, H_sigma = theta, sigma  # where and with which weights H is taken
                H, kind, note = _information_or_diagonal(theta, ap, structure)
            mu, V = np.linalg.eigh(H) if kind != "diagonal" else (np.diag(H), np.eye(P))
            limit = min(_REFRESH_STEPS, max_steps - pass_steps)
            theta, steps, ok, products, n_eval, _, norm = solve_adjoint(
                theta, ap, *jax.device_put((V, mu)), solver,
                jax.device_put(np.asarray(limit)), fixed)
            total, evals, pass_steps = total + int(steps), evals + int(n_eval), \
                pass_steps + int(steps)
            say(f"adjoint pass {it + 1}: {pass_steps} steps, {int(products)} forward and "
                f"reverse product pairs in the last {int(steps)}, "
                f"{'converged' if bool(ok) else 'not yet converged'}")
            if float(norm) > ap.plan.norm:
                say("the parameters moved past the series' bound; solving again with more "
                    "terms")
                ap = with_plan_for(ap, float(norm))
                continue
            if bool(ok) or pass_steps >= max_steps or int(steps) == 0:
                break
        _check_finite(theta, theta0, prep.names)
        r, y = evaluate(theta, ap)
        new = np.where(estimated, np.maximum(ml_sigma(r * sigma, mask), 1e-12), sigma)
        settled = np.all(np.abs(np.log(new / sigma)) < 1e-3)
        if estimated.any():
            say(f"adjoint pass {it + 1}: noise std {np.array2string(new[:4], precision=4)}"
                + (" ..." if new.size > 4 else ""))
        sigma_used, sigma = sigma, new
        if settled:
            break
    final = AdjointProblem(make_problem(prep.template, prep.index, prep.data, sigma, theta0),
                           ap.plan, ap.checkpoint)
    nll = output_error_nll(r * sigma_used, mask, sigma)
    # the last information, at the final stds (they moved by under 1e-3 when settled),
    # where the steps since moved every parameter well inside its std
    moved = np.abs(np.asarray(theta) - np.asarray(start))
    if kind != "diagonal":   # the stds from H: `pinv(H)`'s diagonal by its eigenvectors
        inverse = np.where(mu > 1e-15 * mu.max(), 1.0 / np.where(mu > 0, mu, 1.0), 0.0)
        std = np.sqrt(np.sum(V ** 2 * inverse[None, :], axis=1))
    if kind != "diagonal" and settled and np.all(np.abs(np.log(sigma / H_sigma)) < 1e-3) \
            and np.all(moved < _REUSE_STD * std):
        info = H
    else:
        info, kind, note = _information_or_diagonal(theta, final, structure)
    sol = output_error_solution(prep, theta, theta0, sigma, info, nll, total, bool(ok), y,
                                evals)
    return sol, METHOD + note


#: Steps between fresh informations inside a pass: the one at a pass's start
#: preconditions CG well only near it (a 100-node chain from 20 % off: 47 steps of ~50 CG
#: iterations each from one information; from a fresh one, 3-5 iterations).
_REFRESH_STEPS = 3
#: A pass that moved every parameter by less than this fraction of its std leaves its
#: starting information as the solution's.
_REUSE_STD = 0.1
#: A pass whose noise stds all moved by less than this (log) from those of the last
#: information starts with it as the preconditioner: on a 200-node chain the second pass's
#: stds moved 3 % and its solve took 16 products more instead of an information (601).
_REUSE_WEIGHTS = np.log(1.25)


@stored_jit
def _moved_rows(theta, ap, directions):
    """`(k, n)`: for each direction (k, P), the summed absolute tangent of each state's
    row of `A` (the plan's non-zeros) and of `B`, and of its start in every run."""
    problem, plan = ap.problem, ap.plan
    data = problem.data

    def parts(t):
        model, run_initial = _model_of(t, problem)
        system = model.linear_system()
        u0 = data.inputs[:, 0].astype(system.A.dtype)
        if run_initial is None or run_initial.shape[1] == 0:
            x0 = jax.vmap(lambda u: _initial(model, system, u, None))(u0)
        else:
            x0 = jax.vmap(lambda u, r: _initial(model, system, u, r))(u0, run_initial)
        return gathered(system.A, plan.a_cols, plan.a_real), system.B, x0

    def tangent(v):
        dA, dB, dx0 = jax.jvp(parts, (theta,), (v,))[1]
        return jnp.abs(dA).sum(1) + jnp.abs(dB).sum(1) + jnp.abs(dx0).sum(0)

    return jax.vmap(tangent)(directions)


def _acted_on(theta, ap: AdjointProblem) -> np.ndarray:
    """`(P, n)` bool: the states whose row of `A` or `B`, or whose start in some run,
    moves with each parameter (`_moved_rows`, `_TOUCH_BATCH` directions at a time)."""
    P = theta.shape[0]
    out = np.zeros((P, ap.plan.a_cols.shape[0]), bool)
    eye = np.eye(P)
    for start in range(0, P, _TOUCH_BATCH):
        block = eye[start:start + _TOUCH_BATCH]
        k = block.shape[0]
        if k < _TOUCH_BATCH:
            block = np.concatenate([block, np.zeros((_TOUCH_BATCH - k, P))])
        moved = np.asarray(_moved_rows(theta, ap, jax.device_put(block)))
        out[start:start + k] = moved[:k] > 0
    return out


#: Unit directions per batch when the states each parameter acts on are found.
_TOUCH_BATCH = 16


def _information_or_diagonal(theta, ap: AdjointProblem, structure: dict):
    """`(H, kind, note)`: the information at `theta` (`kind` "exact"); beyond
    `LOCAL_INFORMATION_ABOVE` parameters, where its Jacobian is too large to hold, the
    information of sensitivities kept within a radius (`_local_information`, "local");
    beyond `MAX_INFORMATION_PARAMS` the diagonal of `JᵀJ` as a diagonal matrix
    ("diagonal"). `note`: what the report's method adds about it. `structure`: what one
    fit's calls share (filled by the first): the states each parameter acts on (the
    network's structure, not the point) and the radius last needed, where the next
    call's tail check starts."""
    P = theta.shape[0]
    rows = int(np.prod(ap.problem.data.outputs.shape))
    if LOCAL_INFORMATION_ABOVE < P <= MAX_INFORMATION_PARAMS \
            and 8.0 * rows * P > _JACOBIAN_BYTES:
        if "acted_on" not in structure:
            structure["acted_on"] = _acted_on(theta, ap)
        H, radius, tail = local_information(
            lambda V: _jacobian_columns(theta, ap, V), structure["acted_on"], ap.plan,
            rows // ap.problem.data.outputs.shape[2], _BATCH,
            structure.get("radius", RADIUS))
        structure["radius"] = radius
        return H, "local", (
            f"; {P} free parameters: the information (stds, preconditioner) from each "
            f"parameter's sensitivities kept on the sensors within {radius} links of the "
            f"states it acts on (an approximation: of sampled parameters' sensitivities at "
            f"most {tail:.1e} of the norm lies beyond)")
    H = information(theta, ap)
    if H is None:
        return np.diag(jacobian_diagonal(theta, ap)), "diagonal", (
            f"; {P} free parameters: stds are conditional (each with the others held), "
            "from the diagonal of the information only")
    return H, "exact", ""
