"""Output-error Jacobians of nonlinear models (`thermojax.dynamics._nonlinear_sensitivity`).

Truths, independent of the code under test: `jax.jacfwd` of the official residuals
(`_output_error._oe_flat`: the ETD2 scan of `_nonlinear`, plain forward autodiff through
every substep), and central finite differences of the same residuals.

The problem: the six-node IMU with every nonlinear kind at once (radiation to the
chamber, a temperature-dependent link and capacitance, a link following a
zero-order-hold input column), zero-order-hold power, two runs of different lengths and sample periods,
dropped samples, a sensor gain, and the PCB's initial temperature estimated per run.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import thermojax as tj
from thermojax.dynamics._nonlinear import dataset_outputs_nonlinear
from thermojax.fitting import _output_error
from thermojax.fitting import _problem as problem_module
from thermojax.measurements._data import Dataset, Experiment
from thermojax.model._model import ThermalModel
from thermojax.model._parameters import free_parameters
from thermojax.model._spec import Parameter

from helpers import CONFIGS

NONLINEAR = """
[[effects]]
kind = "radiation"
where = ["housing", "T_chamber"]
coefficient = 4e-10

[[effects]]
kind = "conductance_temperature"
where = ["pcb", "asic"]
alpha = 0.004

[[effects]]
kind = "capacitance_temperature"
where = ["bulkhead"]
beta = 0.002

[[effects]]
kind = "conductance_input"
where = ["housing", "T_chamber", "air_speed"]
coefficient = 0.08
hold = "zoh"

[[effects]]
kind = "sensor_gain"
where = ["T_pcb"]
gain = 0.01
"""


def _spec():
    text = (CONFIGS / "imu6.toml").read_text() + NONLINEAR
    spec = tj.parse_model(text)
    # the PCB's start estimated per run; every other node at the first sample's
    # equilibrium, as the runs below are made
    nodes = tuple(dataclasses.replace(n, initial=Parameter(24.0, False)) if n.name == "pcb"
                  else dataclasses.replace(n, steady=True) for n in spec.nodes)
    return spec.replace(nodes=nodes)


@pytest.fixture(scope="module")
def problem():
    spec = _spec()
    rng = np.random.default_rng(5)
    truth = ThermalModel.from_spec(spec)
    experiments = []
    for n, dt in ((330, 1.0), (180, 2.0)):
        ts = np.arange(n) * dt
        chamber = 25.0 + 0.1 * ts + 3.0 * np.sin(ts / 57.0)
        power = 0.05 + 0.05 * ((ts >= 40) & (ts < 150))
        speed = 0.5 + 2.5 * ((ts // 50) % 3) / 2  # m/s, steps every 50 s
        columns = {"T_chamber": chamber, "P_asic": power, "air_speed": speed}
        u = np.stack([columns[c] for c in spec.input_columns], axis=1)
        data = Dataset.from_experiments([Experiment(ts, u, np.zeros((n, 3)))])
        y = np.asarray(dataset_outputs_nonlinear(truth, data))[0]
        y = y + 0.01 * rng.standard_normal(y.shape)
        y[rng.random(y.shape) < 0.05] = np.nan
        experiments.append(Experiment(ts, u, y, f"run{dt:g}"))
    prep = problem_module.prepare(spec, experiments, "output_error")
    theta_true = free_parameters(prep.template, prep.index)
    names = prep.names
    # Away from the truth so that residuals and their derivatives are far from zero:
    # 1 °C on initial temperatures, about 20 % on every other parameter.
    shift = 0.2 * np.cos(np.arange(len(names)))
    step = np.where([nm.endswith(".initial") for nm in names], 1.0,
                    np.where([problem_module._is_log(nm) for nm in names], shift,
                             shift * np.abs(np.asarray(theta_true))))
    theta = theta_true + jnp.asarray(step)
    prob = problem_module.make_problem(prep.template, prep.index, prep.data,
                                       [0.01, 0.02, 0.015], theta_true, 0.3)
    return theta, prob, names


def _flat(sens, prob):
    ((r, prior), (J, prior_j), _) = sens
    r, J = jnp.stack(r, axis=-1), jnp.stack(J, axis=2)
    T = prob.data.outputs.shape[1]
    P = prior_j.shape[-1]
    return (np.concatenate([np.ravel(r[:, :T]), prior]),
            np.concatenate([np.asarray(J[:, :T]).reshape(-1, P), prior_j]))


def test_problem_is_nonlinear_with_every_kind(problem):
    theta, prob, names = problem
    model, _ = problem_module._model_of(theta, prob)
    assert model.is_nonlinear
    for kind in ("radiation", "conductance_temperature", "capacitance_temperature",
                 "conductance_input", "sensor_gain"):
        assert any(kind in nm for nm in names), (kind, names)
    assert sum(nm.endswith(".initial") for nm in names) == 2  # the PCB, per run


def test_nonlinear_jacobian_equals_jacfwd_of_the_scan(problem):
    """Every column equals `jax.jacfwd` of the official residuals to 1e-10 of its size."""
    theta, prob, names = problem
    r, J = _flat(jax.jit(_output_error._oe_blocks_jacobian)(theta, prob), prob)
    r_ref = np.asarray(jax.jit(_output_error._oe_flat)(theta, prob))
    J_ref = np.asarray(jax.jit(jax.jacfwd(_output_error._oe_flat))(theta, prob))
    np.testing.assert_allclose(r, r_ref, rtol=0, atol=1e-11 * np.abs(r_ref).max())
    scale = np.abs(J_ref).max(axis=0)
    assert np.all(scale > 0)  # every parameter moves some reading
    err = np.abs(J - J_ref).max(axis=0) / scale
    assert np.all(err < 1e-10), dict(zip(names, err))


def test_nonlinear_jacobian_against_finite_differences(problem):
    theta, prob, _ = problem
    _, J = _flat(jax.jit(_output_error._oe_blocks_jacobian)(theta, prob), prob)
    f = jax.jit(_output_error._oe_flat)
    rng = np.random.default_rng(0)
    for _ in range(3):
        v = jnp.asarray(rng.standard_normal(theta.shape[0]))
        h = 1e-5
        fd = np.asarray((f(theta + h * v, prob) - f(theta - h * v, prob)) / (2 * h))
        Jv = J @ np.asarray(v)
        assert np.linalg.norm(fd - Jv) / np.linalg.norm(Jv) < 1e-6


def test_jacobian_from_the_residuals_states_is_the_same(problem):
    """The Gauss-Newton solve hands the Jacobian the node temperatures its residual
    evaluation simulated at the same point (`_oe_blocks_and_states`): the result is the
    Jacobian it computes from its own simulation, to roundoff."""
    theta, prob, _ = problem
    (r, _), states = jax.jit(_output_error._oe_blocks_and_states)(theta, prob)
    assert states.shape[:2] == prob.data.ts.shape
    own = _flat(jax.jit(_output_error._oe_blocks_jacobian)(theta, prob), prob)
    given = _flat(jax.jit(_output_error._oe_blocks_jacobian)(theta, prob, states), prob)
    for a, b in zip(given, own):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())
    r = np.stack(r, axis=-1)[:, :prob.data.outputs.shape[1]].ravel()
    np.testing.assert_allclose(r, own[0][:r.size], rtol=0, atol=1e-12 * np.abs(r).max())


def test_one_evaluation_program_equals_the_scan_and_the_solves(problem):
    """`weighted_residuals_and_jacobian` from a program of its own (a Kalman fit's score
    tests) gives the data rows of the official residuals and of `jax.jacfwd` of them,
    the free run's node temperatures, and the same arrays as the solve's evaluation."""
    from thermojax.dynamics._nonlinear import dataset_states_nonlinear

    theta, prob, _ = problem
    r, J, states = _output_error.weighted_residuals_and_jacobian(theta, prob,
                                                                 own_program=True)
    n = r.size
    r_ref = np.asarray(jax.jit(_output_error._oe_flat)(theta, prob))[:n]
    J_ref = np.asarray(jax.jit(jax.jacfwd(_output_error._oe_flat))(theta, prob))[:n]
    np.testing.assert_allclose(r.ravel(), r_ref, rtol=0, atol=1e-11 * np.abs(r_ref).max())
    np.testing.assert_allclose(J.reshape(n, -1), J_ref, rtol=0,
                               atol=1e-10 * np.abs(J_ref).max())
    model, run_initial = problem_module._model_of(theta, prob)
    x_ref = np.asarray(dataset_states_nonlinear(model, prob.data, run_initial))
    np.testing.assert_allclose(states, x_ref, rtol=0, atol=1e-10)
    for a, b in zip((r, J, states), _output_error.weighted_residuals_and_jacobian(theta, prob)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())
