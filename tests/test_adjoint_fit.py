"""Large networks: the exponential times a vector against SciPy, the adjoint path's fit
against the forward sensitivities' and against the generated truth, and the path choice
(thermojax.fitting._adjoint, thermojax.dynamics._taylor_hold, thermojax.fitting._size)."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import thermojax as tj
from helpers import chain_data, random_network
from thermojax.dynamics._taylor_hold import (gathered, model_outputs_taylor, sparse_matvec,
                                             sparse_plan, taylor_plan, taylor_states)
from thermojax.fitting import _size
from thermojax.measurements._data import Experiment
from thermojax.model._model import ThermalModel

CHAIN = chain_data()


def _scipy_outputs(A, B, C, x0, U, dt, foh):
    """Exact-hold outputs by `scipy.linalg.expm` of the augmented matrix, step by step."""
    n, m = B.shape
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n], M[:n, n:n + m], M[n:n + m, n + m:] = A * dt, B * dt, np.eye(m)
    E = scipy.linalg.expm(M)
    Phi, G0, G1 = E[:n, :n], E[:n, n:n + m], E[:n, n + m:] * foh[None, :]
    x = np.empty((U.shape[0], n))
    x[0] = x0
    for k in range(U.shape[0] - 1):
        x[k + 1] = Phi @ x[k] + (G0 - G1) @ U[k] + G1 @ U[k + 1]
    return x @ C.T


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_chain_by_diagonal_products_matches_scipy(hold):
    C, G, Gb = CHAIN.chain_truth(30, seed=3)
    text = CHAIN.chain_text(30, C, G, Gb, boundary_hold=hold)
    model = ThermalModel.from_spec(tj.parse_model(text))
    system = jax.tree.map(np.asarray, model.linear_system())
    rng = np.random.default_rng(0)
    U = np.stack([20 + np.cumsum(rng.normal(0, 0.5, 200)), 2.0 * (rng.random(200) < 0.5)], 1)
    x0 = 20 + rng.normal(0, 2, 30)
    plan = sparse_plan([system], 3.0)
    assert plan.offsets is not None and list(plan.offsets) == [-1, 0, 1]   # a chain: 3 diagonals
    y = model_outputs_taylor(model, model.linear_system(), plan, jnp.asarray(x0),
                             jnp.asarray(U), 3.0)
    foh = np.array([h == "foh" for h in system.holds], float)
    want = _scipy_outputs(system.A, system.B, system.C, x0, U, 3.0, foh)
    # both exact; float64 roundoff of a ~25-term series on ~20 °C values
    np.testing.assert_allclose(np.asarray(y), want, rtol=0, atol=1e-11)


def test_random_network_by_gathered_products_matches_scipy():
    rng = np.random.default_rng(4)
    net = random_network(rng, 12)
    system = jax.tree.map(np.asarray, net.linear_system())
    plan = sparse_plan([system], 0.5)
    n, m = system.B.shape
    U = rng.normal(0, 1, (100, m))
    x0 = rng.normal(0, 1, n)
    # gathered entries (the general sparse product) whatever the offsets
    vals = gathered(jnp.asarray(system.A), plan.a_cols, plan.a_real)
    foh = np.array([h == "foh" for h in system.holds], bool)
    xs = taylor_states(lambda x: sparse_matvec(vals, plan.a_cols, x), jnp.asarray(system.B),
                       jnp.asarray(x0), jnp.asarray(U), 0.5, foh, plan.substeps, plan.degree)
    want = _scipy_outputs(system.A, system.B, np.eye(n), x0, U, 0.5, foh.astype(float))
    np.testing.assert_allclose(np.asarray(xs), want, rtol=0, atol=1e-11)   # roundoff


def test_taylor_plan_is_exact_to_roundoff_for_stiff_periods():
    # ‖A dt‖ = 40: more substeps, and the series of exp(-40) still exact
    s, d = taylor_plan(40.0)
    assert s > 1
    h = -40.0 / s
    term, total = 1.0, 1.0
    for k in range(1, d + 1):
        term *= h / k
        total += term
    assert abs(total ** s - np.exp(-40.0)) < 1e-15


def _chain_fit_data(n, seed=0):
    C, G, Gb = CHAIN.chain_truth(n, seed)
    ts, U, Y, x0 = CHAIN.chain_run(n, n_times=300, dt=2.0, seed=seed)
    rng = np.random.default_rng(seed + 7)
    start = tj.parse_model(CHAIN.chain_text(n, C * np.exp(0.2 * rng.standard_normal(n)),
                                            G * np.exp(0.2 * rng.standard_normal(n - 1)),
                                            Gb * 1.2))
    truth = {**{f"nodes.n{i}.capacitance": c for i, c in enumerate(C)},
             **{f"links.n{i}-n{i + 1}.conductance": g for i, g in enumerate(G)}}
    return start, [Experiment(ts, U, Y, "chain")], truth


@pytest.fixture(scope="module")
def both_fits():
    start, runs, truth = _chain_fit_data(16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # a run shorter than the slowest mode: on purpose
        forward = tj.fit(start, runs, jacobian="forward", restart_plateaus=False)
        adjoint = tj.fit(start, runs, jacobian="adjoint", restart_plateaus=False)
    return forward, adjoint, truth


def test_adjoint_and_forward_reach_the_same_optimum(both_fits):
    forward, adjoint, _ = both_fits
    assert forward.converged and adjoint.converged
    assert adjoint.method.startswith("adjoint") and forward.method.startswith("forward")
    # one optimum: -log L within the solvers' stopping tolerance (1e-4 each, plus roundoff)
    assert adjoint.nll == pytest.approx(forward.nll, abs=1e-2)
    for name in forward.free_names:
        f, a = forward.parameters[name], adjoint.parameters[name]
        # the same point well inside its std, and the same curvature (stds) to 1 %
        assert abs(f["value"] - a["value"]) < 0.05 * f["std"], name
        assert a["std"] == pytest.approx(f["std"], rel=0.01), name


def test_adjoint_fit_recovers_the_generated_chain(both_fits):
    _, adjoint, truth = both_fits
    z = [(adjoint.parameters[k]["value"] - v) / adjoint.parameters[k]["std"]
         for k, v in truth.items()]
    assert np.max(np.abs(z)) < 4.0   # 31 parameters: the largest of 31 |N(0,1)| under 4
    assert np.mean(np.abs(z) < 3.0) > 0.9


def test_large_networks_take_the_adjoint_path_and_are_not_refused():
    assert _size.choose_path(200, 601, True, available=24e9) == "adjoint"
    assert _size.choose_path(200, 601, False, available=24e9) == "forward"
    assert _size.choose_path(6, 13, True, available=24e9) == "forward"
    with pytest.raises(tj.InputError, match="P·"):
        _size.check_fit_size(200, 601, available=12e9)                     # forward: refused
    cost = _size.check_fit_size(200, 601, available=12e9, path="adjoint", n_samples=400,
                                n_readings=400 * 200)
    assert cost.bytes < 2e9


def test_large_conductance_matrix_by_entries_equals_the_incidence_product():
    from helpers import random_topology
    from thermojax.model._network import _SCATTER_NODES, conductance_matrix

    rng = np.random.default_rng(8)
    topo = random_topology(rng, _SCATTER_NODES + 6)
    g = rng.uniform(0.1, 2.0, len(topo.links))
    gb = rng.uniform(0.1, 2.0, len(topo.boundary_nodes))
    K = conductance_matrix(topo, jnp.asarray(g), jnp.asarray(gb))      # traced: by entries
    # the NumPy branch is the incidence product; a sum of the same terms, roundoff only
    np.testing.assert_allclose(np.asarray(K), conductance_matrix(topo, g, gb), rtol=0,
                               atol=1e-14)


def test_adjoint_path_is_refused_where_it_does_not_apply():
    start, runs, _ = _chain_fit_data(4)
    with pytest.raises(tj.InputError, match="jacobian='adjoint'"):
        tj.fit(start, runs, likelihood="kalman", jacobian="adjoint")


def test_too_many_parameters_for_the_information_report_conditional_stds(monkeypatch):
    from thermojax.fitting import _adjoint

    start, runs, _ = _chain_fit_data(6)
    forward = tj.fit(start, runs, jacobian="forward", restart_plateaus=False)
    monkeypatch.setattr(_adjoint, "MAX_INFORMATION_PARAMS", 5)   # 19 free: only a diagonal
    adjoint = tj.fit(start, runs, jacobian="adjoint", restart_plateaus=False)
    assert "conditional" in adjoint.method
    assert adjoint.nll == pytest.approx(forward.nll, abs=1e-2)   # the same optimum
    for name in forward.free_names:
        f, a = forward.parameters[name], adjoint.parameters[name]
        # a conditional std (the others held) never exceeds the marginal one; 1 % for the
        # two information matrices' roundoff and the solvers' stopping points
        assert a["std"] <= 1.01 * f["std"], name


@pytest.mark.parametrize("jacobian_bytes", [1e9, 0.0])
def test_information_by_columns_or_by_pairs_is_the_gram_of_the_jacobian(monkeypatch,
                                                                         jacobian_bytes):
    # the information by forward products and one matrix product (a Jacobian that fits)
    # and by forward and reverse pairs (one that does not): both JᵀJ of the Jacobian that
    # jax.jacfwd forms whole from the residuals
    from thermojax.fitting import _adjoint
    from thermojax.fitting._problem import make_problem, prepare
    from thermojax.model._parameters import free_parameters

    monkeypatch.setattr(_adjoint, "_JACOBIAN_BYTES", jacobian_bytes)
    monkeypatch.setattr(_adjoint, "_BATCH", 8)   # 19 free parameters: three batches
    start, runs, _ = _chain_fit_data(6)
    prep = prepare(start, runs, "output_error")
    theta = free_parameters(prep.template, prep.index)
    ap = _adjoint.adjoint_problem(make_problem(prep.template, prep.index, prep.data,
                                               prep.sigma, theta), theta)
    J = jax.jacfwd(lambda t: _adjoint.adjoint_residuals(t, ap)[:-theta.shape[0]])(theta)
    want = np.asarray(J).T @ np.asarray(J)
    got = _adjoint.information(theta, ap)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10 * np.abs(want).max())
