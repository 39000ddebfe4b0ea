"""Long logs: output error on normal equations summed stretch by stretch
(thermojax.fitting._normal_equations) against `jax.jacfwd` of the whole log's residuals,
against the forward path's optimum and the generated truth, and the path choice
(thermojax.fitting._size)."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import thermojax as tj
from helpers import chain_data
from thermojax.dynamics._sensitivity import dataset_outputs
from thermojax.fitting import _normal_equations, _size
from thermojax.fitting._problem import _model_of, make_problem, prepare
from thermojax.measurements._data import Experiment
from thermojax.model._parameters import free_parameters

CHAIN = chain_data()


def _chain_runs(n, seed=0):
    """A start 20 % off the generated chain of `n` nodes, two runs of 300 and 211 samples
    (one simulated run cut in two; lengths not multiples of the stretch), and the truth by
    name."""
    C, G, Gb = CHAIN.chain_truth(n, seed)
    ts, U, Y, _ = CHAIN.chain_run(n, n_times=511, dt=2.0, seed=seed)
    rng = np.random.default_rng(seed + 7)
    start = tj.parse_model(CHAIN.chain_text(n, C * np.exp(0.2 * rng.standard_normal(n)),
                                            G * np.exp(0.2 * rng.standard_normal(n - 1)),
                                            Gb * 1.2))
    runs = [Experiment(ts[:300], U[:300], Y[:300], "first"),
            Experiment(ts[300:] - ts[300], U[300:], Y[300:], "second")]
    truth = {**{f"nodes.n{i}.capacitance": c for i, c in enumerate(C)},
             **{f"links.n{i}-n{i + 1}.conductance": g for i, g in enumerate(G)}}
    return start, runs, truth


def test_stretch_sums_equal_the_whole_logs_normal_equations():
    start, runs, _ = _chain_runs(5)
    runs[1].outputs[40:60, 0] = np.nan   # unmeasured readings inside a stretch
    prep = prepare(start, runs, "output_error")
    theta = free_parameters(prep.template, prep.index)
    problem = make_problem(prep.template, prep.index, prep.data, prep.sigma, theta)
    data = prep.data

    def residuals(t):   # every run simulated whole (runs, T, p), zero where unmeasured
        model, run_initial = _model_of(t, problem)
        return jnp.where(data.mask, data.outputs - dataset_outputs(model, data, run_initial),
                         0.0)

    r = np.asarray(residuals(theta))
    J = np.asarray(jax.jacfwd(residuals)(theta))          # (runs, T, p, P)
    # stretches of 32 samples: 10 and 7 per run, the last of each partly padding
    ss, gram, grad = _normal_equations.normal_equations(theta, problem, prep, 32)
    np.testing.assert_allclose(ss, (r ** 2).sum(axis=(0, 1)), rtol=1e-10)
    want_gram = np.einsum("rtka,rtkb->kab", J, J)
    np.testing.assert_allclose(gram, want_gram, rtol=1e-9, atol=1e-9 * np.abs(want_gram).max())
    want_grad = np.einsum("rtka,rtk->ka", J, r)
    np.testing.assert_allclose(grad, want_grad, rtol=1e-9, atol=1e-9 * np.abs(want_grad).max())
    ss_only, predictions = _normal_equations.sum_of_squares(theta, problem, prep, 32,
                                                            predictions=True)
    np.testing.assert_allclose(ss_only, ss, rtol=1e-12)
    model, run_initial = _model_of(theta, problem)
    want = np.asarray(dataset_outputs(model, data, run_initial))
    for k, T in enumerate(data.lengths):
        np.testing.assert_allclose(predictions[k, :T], want[k, :T], rtol=0, atol=1e-10)


@pytest.fixture(scope="module")
def both_fits():
    start, runs, truth = _chain_runs(6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # runs shorter than the slowest mode: on purpose
        forward = tj.fit(start, runs, jacobian="forward", restart_plateaus=False)
        lines = []
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(_normal_equations, "STRETCH", 64)   # 5 + 4 stretches
            summed = tj.fit(start, runs, jacobian="normal_equations", restart_plateaus=False,
                            progress=lines.append)
    return forward, summed, truth, lines


def test_normal_equations_and_forward_reach_the_same_optimum(both_fits):
    forward, summed, _, lines = both_fits
    assert forward.converged and summed.converged
    assert summed.method.startswith("Gauss-Newton on normal equations")
    assert any("9 stretch(es) of up to 64 samples" in line for line in lines)
    assert summed.nll == pytest.approx(forward.nll, abs=1e-2)
    for name in forward.free_names:
        f, s = forward.parameters[name], summed.parameters[name]
        assert abs(f["value"] - s["value"]) < 0.05 * f["std"], name
        assert s["std"] == pytest.approx(f["std"], rel=0.01), name
    for column in forward.rmse:
        assert summed.rmse[column] == pytest.approx(forward.rmse[column], rel=1e-3)


def test_normal_equations_fit_recovers_the_generated_chain(both_fits):
    _, summed, truth, _ = both_fits
    z = [(summed.parameters[k]["value"] - v) / summed.parameters[k]["std"]
         for k, v in truth.items()]
    assert np.max(np.abs(z)) < 3.5   # 11 parameters
    assert summed.parameters["sensors.T0.noise"]["value"] == pytest.approx(0.01, rel=0.1)


def test_long_logs_take_the_normal_equations_and_are_not_refused():
    # the six-node IMU, 22 free parameters, 3 sensors: 2·10⁶ samples hold a 2.7 GB
    # Jacobian, 10⁶ samples 1.4 GB: forward (faster) where it fits, else not
    assert _size.choose_path(6, 22, True, available=24e9, n_samples=2 * 10 ** 6,
                             n_readings=6 * 10 ** 6) == "normal_equations"
    assert _size.choose_path(6, 22, True, available=24e9, n_samples=10 ** 6,
                             n_readings=3 * 10 ** 6) == "forward"
    assert _size.choose_path(6, 22, True, available=1.5e9, n_samples=10 ** 6,
                             n_readings=3 * 10 ** 6) == "normal_equations"
    assert _size.choose_path(6, 22, False, available=24e9, n_samples=10 ** 6,
                             n_readings=3 * 10 ** 6) == "forward"
    # 10⁷ samples: the forward path (14 GB) refused on a 12 GB machine, this one not
    with pytest.raises(tj.InputError, match="sensor readings"):
        _size.check_fit_size(6, 22, available=12e9, n_readings=3 * 10 ** 7)
    cost = _size.check_fit_size(6, 22, available=12e9, path="normal_equations",
                                n_readings=3 * 10 ** 7)
    assert cost.bytes < 0.2 * _size.fit_cost(6, 22, 3 * 10 ** 7).bytes


def test_normal_equations_refuse_what_they_cannot_fit():
    start, runs, _ = _chain_runs(3)
    with pytest.raises(tj.InputError, match="jacobian='normal_equations'"):
        tj.fit(start, runs, likelihood="kalman", jacobian="normal_equations")
    with pytest.raises(tj.InputError, match="expected one of"):
        tj.fit(start, runs, jacobian="reverse")


def test_an_invisible_node_on_a_long_log_is_said_not_refitted(monkeypatch):
    # where the data cannot see a node, a fit on summed normal equations says so instead
    # of refitting the whole log from a visible start (measured on 2·10⁶ samples of the
    # six-node IMU: a restart crawled over 100 steps for nothing); the detector itself is
    # tested in test_plateau.py
    from thermojax.fitting import _fit
    from thermojax.fitting._plateau import Invisible

    start, runs, _ = _chain_runs(3)
    monkeypatch.setattr(_fit, "invisible_nodes",
                        lambda *a: [Invisible("n1", 0.01, 2.0, 600.0)])
    lines = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = tj.fit(start, runs, jacobian="normal_equations", progress=lines.append)
    assert "'n1'" in result.message and "not refitted" in result.message
    assert not any("refitting from a time constant" in line for line in lines)
