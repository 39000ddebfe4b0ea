"""The local information of a large network (`fitting._local_information`): each
parameter's sensitivities kept on the sensors within a radius of the nodes it acts on,
from compressed forward products. Against `JᵀJ` of the whole Jacobian that `jax.jacfwd`
forms from the same residuals: equal when the radius spans the network, close when it
spans the reach of the diffusion over the run; the colouring never shares a product
between overlapping footprints; a fit that uses it reaches the forward path's optimum and
says where its stds come from."""

from __future__ import annotations

import warnings

import jax
import numpy as np
import pytest

import thermojax as tj
from helpers import chain_data
from thermojax.fitting import _adjoint
from thermojax.fitting._local_information import (MAX_TAIL, _compressed, colouring,
                                                   footprints, local_information,
                                                   sensor_states)
from thermojax.fitting._problem import make_problem, prepare
from thermojax.measurements._data import Experiment
from thermojax.model._parameters import free_parameters

CHAIN = chain_data()


def _chain(n, seed=0, n_times=300):
    C, G, Gb = CHAIN.chain_truth(n, seed)
    ts, U, Y, _ = CHAIN.chain_run(n, n_times=n_times, dt=2.0, seed=seed)
    rng = np.random.default_rng(seed + 7)
    start = tj.parse_model(CHAIN.chain_text(n, C * np.exp(0.2 * rng.standard_normal(n)),
                                            G * np.exp(0.2 * rng.standard_normal(n - 1)),
                                            Gb * 1.2))
    return start, [Experiment(ts, U, Y, "chain")]


def _gram_and_problem(n, n_times=300):
    start, runs = _chain(n, n_times=n_times)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # a run shorter than the slowest mode: on purpose
        prep = prepare(start, runs, "output_error")
    theta = free_parameters(prep.template, prep.index)
    ap = _adjoint.adjoint_problem(make_problem(prep.template, prep.index, prep.data,
                                               prep.sigma, theta), theta)
    J = np.asarray(jax.jacfwd(
        lambda t: _adjoint.adjoint_residuals(t, ap)[:-theta.shape[0]])(theta))
    return J.T @ J, theta, ap


def _local(theta, ap, radius):
    R, T, _ = ap.problem.data.outputs.shape
    return local_information(lambda V: _adjoint._jacobian_columns(theta, ap, V),
                             _adjoint._acted_on(theta, ap), ap.plan, R * T, 8, radius)


def test_a_radius_spanning_the_network_gives_the_exact_information():
    want, theta, ap = _gram_and_problem(6)
    got, radius, tail = _local(theta, ap, radius=10)
    assert radius == 10 and tail == 0.0
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * np.abs(want).max())


def test_the_radius_grows_until_the_dropped_tails_are_small_and_the_stds_follow():
    # 80 nodes of ~5 s over 300 s: a parameter's sensitivities fade within ~15 links.
    # Measured on 40 nodes over 600 s: radius 12 drops 12 % of a column (stds off by
    # 40 %), 16 drops 5.6 % (4 %), 25 drops 0.7 % (2e-4)
    want, theta, ap = _gram_and_problem(80, n_times=150)
    got, radius, tail = _local(theta, ap, radius=6)
    assert radius > 6 and tail <= MAX_TAIL          # 6 drops a quarter: doubled
    std_want = np.sqrt(np.diag(np.linalg.inv(want)))
    std_got = np.sqrt(np.diag(np.linalg.inv(got)))
    assert np.max(np.abs(std_got / std_want - 1)) < 0.01
    # and the compression is real: far fewer forward products than parameters
    fp = footprints(_adjoint._acted_on(theta, ap), ap.plan.a_cols, ap.plan.a_real,
                    sensor_states(ap.plan), radius)
    R, T, _ = ap.problem.data.outputs.shape
    colour, _ = _compressed(lambda V: _adjoint._jacobian_columns(theta, ap, V), fp,
                            R * T, 8)
    assert colour.max() + 1 < 0.8 * theta.shape[0]


def test_footprints_on_a_chain_and_a_colouring_without_overlaps():
    # a 10-node chain, sensors on every node; parameter k acts on node k // 2
    n = 10
    a_cols = np.array([[max(i - 1, 0), i, min(i + 1, n - 1)] for i in range(n)])
    a_real = np.array([[i > 0, True, i < n - 1] for i in range(n)])
    acted = np.zeros((2 * n + 1, n), bool)
    for k in range(2 * n):
        acted[k, k // 2] = True                      # the last one acts on nothing: global
    fp = footprints(acted, a_cols, a_real, np.eye(n, dtype=bool), radius=1)
    for k in range(2 * n):
        i = k // 2
        assert set(np.flatnonzero(fp[k])) == {j for j in (i - 1, i, i + 1) if 0 <= j < n}
    assert fp[-1].all()
    colour = colouring(fp)
    for c in range(colour.max() + 1):
        members = fp[colour == c]
        assert (members.sum(0) <= 1).all()           # no sensor seen by two of one colour
    assert colour.max() + 1 <= 7                     # 6 for the chain, 1 for the global one


def test_a_fit_with_the_local_information_reaches_the_forward_optimum(monkeypatch):
    start, runs = _chain(16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # a run shorter than the slowest mode: on purpose
        forward = tj.fit(start, runs, jacobian="forward", restart_plateaus=False)
        monkeypatch.setattr(_adjoint, "LOCAL_INFORMATION_ABOVE", 5)
        monkeypatch.setattr(_adjoint, "_JACOBIAN_BYTES", 0.0)
        local = tj.fit(start, runs, jacobian="adjoint", restart_plateaus=False)
    assert "links" in local.method and local.converged
    assert local.nll == pytest.approx(forward.nll, abs=1e-2)
    for name in forward.free_names:
        f, a = forward.parameters[name], local.parameters[name]
        assert abs(f["value"] - a["value"]) < 0.05 * f["std"], name
        # radius 40 spans the 16-node chain: the exact information, roundoff apart
        assert a["std"] == pytest.approx(f["std"], rel=0.01), name
