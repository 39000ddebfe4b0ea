"""Output-error Jacobians by forward sensitivities (`thermojax.dynamics._sensitivity`).

Truths, independent of the code under test:

- `jax.jacfwd` of the residuals the fit defines (`_output_error._oe_flat`: the blocked simulator
  through `ExactHold`, the official discretization, plain autodiff);
- central finite differences of the same residuals;
- `numpy.linalg.solve`, `scipy.linalg.expm` and `scipy.linalg.expm_frechet`, and
  `jax.jvp` of `jax.scipy.linalg.expm` (autodiff, scaled as Higham 2005);
- `jax.jacfwd` and central differences for `jax.grad` through the sensitivity path.

The problem is the six-node IMU (FOH chamber temperature, ZOH power) with two runs of
different lengths and sample periods (so one is padded), dropped samples, and the PCB's
initial temperature estimated per run (so the initial state depends on the parameters
in two ways: the steady state of the others and the free entry).
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import thermojax as tj
from thermojax.fitting import _output_error
from thermojax.fitting import _problem as problem_module
from thermojax.model import free_parameters
from thermojax.dynamics import _sensitivity
from thermojax.measurements._data import Dataset, Experiment
from thermojax.dynamics import _discretize
from thermojax.model._model import ThermalModel
from thermojax.model._parameters import FreeIndex
from thermojax.model._spec import Parameter

from helpers import CONFIGS


def _problem():
    truth = tj.load_model(CONFIGS / "imu6.toml")
    nodes = tuple(dataclasses.replace(n, initial=Parameter(24.0, False)) if n.name == "pcb"
                  else n for n in truth.nodes)
    spec = truth.replace(nodes=nodes)
    net = tj.ThermalNetwork.from_spec(truth)
    rng = np.random.default_rng(3)
    runs = []
    for n, dt in ((300, 1.0), (170, 2.0)):
        ts = np.arange(n) * dt
        chamber = 25.0 + 0.05 * ts + 2.0 * np.sin(ts / 97.0)
        power = 0.05 + 0.05 * ((ts >= 60) & (ts < 180))
        u = np.stack([chamber, power], axis=1)
        y = np.asarray(tj.simulate(net, u, ts).outputs) + 0.01 * rng.standard_normal((n, 3))
        y[rng.random(y.shape) < 0.05] = np.nan  # dropped samples
        runs.append(Experiment(ts, u, y, f"run{dt:g}"))
    data = Dataset.from_experiments(runs)
    model = ThermalModel.from_spec(spec)
    k = len(model.initial_nodes)
    run_initial = jnp.broadcast_to(model.initial[np.array(model.initial_nodes)],
                                   (data.n_runs, k))
    template = problem_module.FitState(model, run_initial, jnp.zeros(0))
    mask, names = problem_module._masks(spec, model, data.n_runs, "output_error")
    index = FreeIndex(mask)
    theta_true = free_parameters(template, index)
    # Away from the truth (every parameter ~20 % off, initial temperatures 1 °C off),
    # so that residuals and all their derivatives are far from zero.
    step = np.where([nm.endswith(".initial") for nm in names], 1.0,
                    0.2 * np.cos(np.arange(len(names))))
    theta = theta_true + jnp.asarray(step)
    problem = problem_module._Problem(template, index, data, jnp.asarray([0.01, 0.02, 0.015]),
                            theta_true, jnp.full(len(names), 0.3))
    return theta, problem, names


@pytest.fixture(scope="module")
def problem():
    return _problem()


@pytest.fixture(scope="module")
def sensitivities(problem):
    """Residuals and Jacobian as the solver sees them (padded to whole blocks, with the
    prior rows as a second leaf), and the predictions."""
    theta, prob, _ = problem
    return jax.jit(_output_error._oe_blocks_jacobian)(theta, prob)


def _flat(sensitivities, prob):
    """The data rows (padding dropped) and prior rows in the order of `_output_error._oe_flat`,
    and the Jacobian transposed."""
    ((r, prior), (J, prior_j), _) = sensitivities
    r, J = jnp.stack(r, axis=-1), jnp.stack(J, axis=2)
    T = prob.data.outputs.shape[1]
    P = prior_j.shape[-1]
    return (np.concatenate([np.ravel(r[:, :T]), prior]),
            np.concatenate([np.asarray(J[:, :T]).reshape(-1, P), prior_j]).T)


def test_jacobian_equals_jacfwd(problem, sensitivities):
    """Every column agrees with `jax.jacfwd` of the official residuals to ~1e-12 of that
    column's size (1e-10 asserted), the residuals to roundoff."""
    theta, prob, names = problem
    r, Jt = _flat(sensitivities, prob)
    r_ref = jax.jit(_output_error._oe_flat)(theta, prob)
    J_ref = np.asarray(jax.jit(jax.jacfwd(_output_error._oe_flat))(theta, prob))
    assert Jt.shape == J_ref.T.shape
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-11 * float(jnp.max(jnp.abs(r_ref))))
    scale = np.max(np.abs(J_ref), axis=0)
    err = np.max(np.abs(np.asarray(Jt).T - J_ref), axis=0) / scale
    assert np.all(err < 1e-10), dict(zip(names, err))
    assert np.all(scale > 0)  # every parameter (and both initial temperatures) moves something


def test_jacobian_against_finite_differences(problem, sensitivities):
    """Central differences of the official residuals along random directions."""
    theta, prob, _ = problem
    _, Jt = _flat(sensitivities, prob)
    f = jax.jit(_output_error._oe_flat)
    rng = np.random.default_rng(0)
    for _ in range(3):
        v = jnp.asarray(rng.standard_normal(theta.shape[0]))
        h = 1e-5
        fd = (f(theta + h * v, prob) - f(theta - h * v, prob)) / (2 * h)
        Jv = v @ Jt
        assert float(jnp.linalg.norm(fd - Jv) / jnp.linalg.norm(Jv)) < 1e-6


def test_predictions_and_fast_residuals(problem, sensitivities):
    """The predictions returned with the Jacobian are the blocked simulator's, and the
    solver's residual function equals the official one."""
    theta, prob, _ = problem
    ((r_blocks, prior), _, y) = sensitivities
    model, run_initial = problem_module._model_of(theta, prob)
    y_ref = tj.simulate_dataset(model, prob.data, run_initial)
    np.testing.assert_allclose(y, y_ref, rtol=0, atol=1e-10)
    fast, fast_prior = jax.jit(_output_error._oe_blocks)(theta, prob)
    fast, r_blocks = jnp.stack(fast, axis=-1), jnp.stack(r_blocks, axis=-1)
    np.testing.assert_allclose(fast, r_blocks, rtol=0, atol=1e-9)
    np.testing.assert_allclose(fast_prior, prior, rtol=0, atol=0)
    T = prob.data.outputs.shape[1]
    assert fast.shape[1] % _sensitivity._BLOCK == 0 and np.all(np.asarray(fast[:, T:]) == 0)
    np.testing.assert_allclose(np.concatenate([np.ravel(fast[:, :T]), fast_prior]),
                               jax.jit(_output_error._oe_flat)(theta, prob), rtol=0, atol=1e-9)


def reference_expm(M):
    """`jax.scipy.linalg.expm`, differentiated by plain autodiff, with the scaling of
    Higham (2005) applied first (`‖M‖₁ / 2^s <= θ13`: JAX's own stops at `2 θ13`)."""
    norm = jax.lax.stop_gradient(jnp.linalg.norm(M, 1))
    s = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / _discretize._THETA13)), 0, 64)
    E = jax.scipy.linalg.expm(M * 2.0 ** (-s))
    return jax.lax.fori_loop(0, 64, lambda i, E: jnp.where(i < s, E @ E, E), E)


def test_expm_derivative_matches_autodiff():
    """The written-out Padé derivative equals `jax.jvp` of `reference_expm`, for
    matrices that need no squaring and for ones that need several."""
    rng = np.random.default_rng(1)
    for scale in (0.3, 4.0, 60.0):
        M = jnp.asarray(rng.standard_normal((10, 10)) * scale / 3)
        dM = jnp.asarray(rng.standard_normal((10, 10)))
        E, dE = jax.jvp(_discretize._expm, (M,), (dM,))
        E_ref, dE_ref = jax.jvp(reference_expm, (M,), (dM,))
        np.testing.assert_allclose(E, E_ref, rtol=0, atol=1e-13 * float(jnp.max(jnp.abs(E_ref))))
        np.testing.assert_allclose(dE, dE_ref, rtol=0,
                                   atol=1e-12 * float(jnp.max(jnp.abs(dE_ref))))


def test_small_solve_pivots():
    """`_solve_small` (Gauss-Jordan, partial pivoting) on a matrix that needs pivoting."""
    rng = np.random.default_rng(2)
    A = rng.standard_normal((7, 7))
    A[0, 0] = 1e-14  # a zero leading pivot without row exchanges
    B = rng.standard_normal((7, 3))
    np.testing.assert_allclose(_discretize._solve_small(jnp.asarray(A), jnp.asarray(B)),
                               np.linalg.solve(A, B), rtol=1e-11, atol=1e-12)


def test_reverse_mode_gradient_of_residual_sum_of_squares(problem):
    """`jax.grad` (reverse mode, through the exponential's transposed derivative, the
    blocked recurrences and the small steady-state solve) of the solver's residual sum of
    squares equals `jax.jacfwd` and central differences."""
    theta, prob, names = problem

    def ssr(t):
        per_output, _ = _output_error._oe_blocks(t, prob)
        return sum(jnp.sum(r ** 2) for r in per_output)

    g_rev = np.asarray(jax.jit(jax.grad(ssr))(theta))
    g_fwd = np.asarray(jax.jit(jax.jacfwd(ssr))(theta))
    assert np.all(np.isfinite(g_rev)) and np.all(g_fwd != 0)
    # two exact derivatives of the same function, summed in other orders: roundoff only
    np.testing.assert_allclose(g_rev, g_fwd, rtol=1e-10, atol=1e-12 * np.abs(g_fwd).max())
    f = jax.jit(ssr)
    rng = np.random.default_rng(1)
    for _ in range(3):
        v = rng.standard_normal(theta.shape[0])
        h = 1e-5
        fd = (f(theta + h * v) - f(theta - h * v)) / (2 * h)
        # central differences: O(h²) truncation and eps/h rounding, ~1e-8 relative
        assert abs(float(fd) - g_rev @ v) < 1e-6 * np.abs(g_rev).max() * np.abs(v).sum()
