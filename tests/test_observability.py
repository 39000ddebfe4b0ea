"""Observability: matrix and rank, the Gramian, weak states in words, sensor placement.

Truths: `control.obsv` and NumPy's rank; a plain NumPy sum of `(Phiᵀ)^k Cᵀ R⁻¹ C Phi^k`
over `scipy.linalg.expm`; brute-force enumeration of sensor sets.
"""

import itertools
import math

import control
import numpy as np
import pytest
import scipy.linalg

import thermojax as tj
from thermojax import observer as ob
from thermojax.model import ThermalModel

from helpers import CONFIGS, model_matrices


def imu_model():
    return ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))


def np_gramian(Phi, C, noise, steps):
    """Direct sum, the definition (independent of the doubling)."""
    Cw = C / noise[:, None]
    W = np.zeros_like(Phi)
    P = np.eye(Phi.shape[0])
    for _ in range(steps):
        W += P.T @ Cw.T @ Cw @ P
        P = Phi @ P
    return W


def test_observability_matrix_and_rank_match_control():
    m = model_matrices(CONFIGS / "imu6.toml")
    system = tj.discretize(tj.ThermalNetwork.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
                           .linear_system(), 0.05)
    Phi = scipy.linalg.expm(m["A"] * 0.05)
    O = ob.observability_matrix(system)
    # expm (Padé) in thermojax vs scipy: roundoff only
    np.testing.assert_allclose(O, control.obsv(Phi, m["Cy"]), rtol=1e-10, atol=1e-12)
    assert ob.observability_rank(system) == 6
    # the continuous pair too
    cont = tj.ThermalNetwork.from_spec(tj.load_model(CONFIGS / "imu6.toml")).linear_system()
    np.testing.assert_allclose(ob.observability_matrix(cont), control.obsv(m["A"], m["Cy"]),
                               rtol=1e-12)


def test_gramian_finite_and_infinite_against_direct_sum():
    m = model_matrices(CONFIGS / "imu6.toml")
    dt = 0.05
    Phi = scipy.linalg.expm(m["A"] * dt)
    system = tj.discretize(tj.ThermalNetwork.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
                           .linear_system(), dt)
    noise = np.array([0.01, 0.02, 0.03])
    for horizon in (0.05, 1.0, 3.7, 60.0):
        W = ob.observability_gramian(system, horizon, noise)
        ref = np_gramian(Phi, m["Cy"], noise, int(round(horizon / dt)))
        # doubling vs direct sum: roundoff relative to the largest entry
        np.testing.assert_allclose(W, ref, rtol=1e-9, atol=1e-9 * np.abs(ref).max())
    # infinite horizon on the RTD (slowest tau 4.7 s: 3000 samples converge to 1e-12)
    r = model_matrices(CONFIGS / "rtd2.toml")
    rsys = tj.discretize(tj.ThermalNetwork.from_spec(tj.load_model(CONFIGS / "rtd2.toml"))
                         .linear_system(), 0.1)
    ref = np_gramian(scipy.linalg.expm(r["A"] * 0.1), r["Cy"], np.ones(1), 3000)
    np.testing.assert_allclose(ob.observability_gramian(rsys, None), ref, rtol=1e-9)


def test_gramian_condition_not_raw_matrix_condition():
    model = imu_model()
    o = ob.observability(model, 0.05)
    # the Gramian's figures, recomputed independently from its eigenvalues
    mu = np.linalg.eigvalsh(o.gramian)
    assert math.isclose(o.condition_number, mu[-1] / mu[0], rel_tol=1e-8)
    assert math.isclose(o.worst_std, 1 / math.sqrt(mu[0]), rel_tol=1e-8)
    assert math.isclose(o.logdet, float(np.sum(np.log(mu))), rel_tol=1e-10)
    assert o.observable and o.rank == 6
    # the raw matrix's condition number depends on the unit of time (‖A‖ⁿ): the same
    # network with A in 1/ms instead of 1/s (control.obsv as truth)
    A, C = np.asarray(model.network.linear_system().A), np.eye(6)[[0, 2, 3]]
    per_s, per_ms = (np.linalg.cond(control.obsv(A * f, C)) for f in (1.0, 1e-3))
    assert per_ms / per_s > 1e4  # measured 1.9e4; the Gramian is unchanged by the unit


def test_weak_proof_mass_explained_in_words():
    o = ob.observability(imu_model(), 0.05, sensors=["pcb", "asic"])
    assert len(o.weak) == 1
    w = o.weak[0]
    assert w["nodes"] == ["proof_mass"] and not w["unobservable"]
    assert "local time constant of 0.1 s" in w["message"]
    assert "detectable" in w["message"]
    assert w["restore"] in ("proof_mass", "mems")
    # restricted to the modes slower than 5 dt, nothing is weak
    slow = ob.observability(imu_model(), 0.05, sensors=["pcb", "asic"], min_time_constant=0.25)
    assert slow.modes == 5 and slow.weak == []


def test_unobservable_node_named_with_restoring_sensor():
    topo = tj.Topology(node_names=("a", "b", "c"), links=((0, 1),), boundary_nodes=(0, 2),
                       boundary_inputs=(0, 0), heat_nodes=(), heat_inputs=(),
                       input_names=("T_amb",), input_holds=("foh",), sensor_nodes=(0,),
                       sensor_names=("Ta",))
    net = tj.ThermalNetwork.from_physical(topo, [1.0, 2.0, 3.0], [0.5], [0.1, 0.2])
    o = ob.observability(net, 0.5)
    assert o.rank == 2 and not o.observable and o.condition_number == math.inf
    (w,) = o.weak
    assert w["nodes"] == ["c"] and w["unobservable"] and w["restore"] == "c"
    assert "no conduction path to any sensor" in w["message"]


def test_unknown_sensor_name():
    with pytest.raises(ValueError, match=r"`observability\(sensors=...\)` names node 'lid'"):
        ob.observability(imu_model(), 0.05, sensors=["lid"])


def test_bulkhead_claim_measured():
    """The seed: a bulkhead sensor conditions the IMU better than electronics alone.
    Measured: it does not lower the Gramian's condition number (it raises μ_max more
    than μ_min); it only sharpens the bulkhead's own estimate."""
    model = imu_model()
    for kw in ({}, {"min_time_constant": 0.25}):
        e = ob.observability(model, 0.05, sensors=["pcb", "asic"], **kw)
        b = ob.observability(model, 0.05, sensors=["bulkhead", "pcb", "asic"], **kw)
        assert b.condition_number > e.condition_number
        assert b.min_eigenvalue >= e.min_eigenvalue  # a sensor never loses information


@pytest.mark.parametrize("criterion", ["condition", "min_eigenvalue", "logdet"])
def test_sensor_placement_exhaustive_matches_brute_force(criterion):
    model = imu_model()
    m = model_matrices(CONFIGS / "imu6.toml")
    dt, horizon = 0.1, 100.0
    Phi = scipy.linalg.expm(m["A"] * dt)
    ranked = ob.sensor_placement(model, 2, dt, horizon=horizon, criterion=criterion)
    assert len(ranked) == math.comb(6, 2)
    scores = {}
    for pair in itertools.combinations(range(6), 2):
        C = np.eye(6)[list(pair)]
        mu = np.linalg.eigvalsh(np_gramian(Phi, C, np.full(2, 0.01), 1000))
        scores[tuple(m["names"][i] for i in pair)] = {
            "condition": mu[-1] / mu[0], "min_eigenvalue": -mu[0],
            "logdet": -np.sum(np.log(mu))}[criterion]
    best = min(scores, key=scores.get)
    assert ranked[0].nodes == best
    s = ranked[0]
    figure = {"condition": s.condition_number, "min_eigenvalue": -s.min_eigenvalue,
              "logdet": -s.logdet}[criterion]
    # doubling vs direct sum: roundoff (condition numbers ~1e10 amplify it)
    assert math.isclose(figure, scores[best], rel_tol=1e-5)


def test_sensor_placement_greedy_and_required():
    model = imu_model()
    greedy = ob.sensor_placement(model, 3, 0.05, required=["asic"], max_exhaustive=0,
                                 criterion="min_eigenvalue", min_time_constant=0.25)
    assert "asic" in greedy[0].nodes and len(greedy[0].nodes) == 3
    full = ob.sensor_placement(model, 3, 0.05, required=["asic"], criterion="min_eigenvalue",
                               min_time_constant=0.25)
    # greedy on a monotone criterion: never better than the exhaustive optimum
    assert greedy[0].min_eigenvalue <= full[0].min_eigenvalue * (1 + 1e-12)
    with pytest.raises(ValueError, match=r"`sensor_placement\(k=9\)`"):
        ob.sensor_placement(model, 9, 0.05)
    with pytest.raises(ValueError, match="criterion"):
        ob.sensor_placement(model, 2, 0.05, criterion="trace")


@pytest.mark.slow
def test_observer_claims_study(tmp_path):
    import importlib.util

    from helpers import ROOT

    spec = importlib.util.spec_from_file_location(
        "observer_claims", ROOT / "experiments" / "observer_claims.py")
    study = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(study)
    folder = study.main(["--out", str(tmp_path)])
    assert folder.parent == tmp_path and folder.name.startswith("observer_claims-")
    for name in ("claims.md", "results.json", "imu6_sensor_sets.png", "rtd_tradeoff.png"):
        assert (folder / name).is_file(), name
