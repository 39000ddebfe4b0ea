"""Checks of the synthetic building generator (`buildings.py`) against independent truths:
a Radau integration of the ODE written here from the truth dict, a brute-force quadrature of the
process-noise covariance, tomllib/CSV parsing of the written files, and byte-for-byte reproducibility.
"""

from __future__ import annotations

import tomllib

import numpy as np
import pytest
import scipy.integrate
import scipy.linalg

from . import buildings as b

CASES = b.building_case_names()


def _rhs(truth: dict, names: list[str]):
    """dT/dt written from the truth dict by hand (no matrices), inputs frozen per interval."""
    idx = {k: i for i, k in enumerate(names)}

    def f(t, x, u):
        q = np.zeros(len(names))
        for a, c, g in truth["links"]:
            q[idx[a]] += g * (x[idx[c]] - x[idx[a]])
            q[idx[c]] += g * (x[idx[a]] - x[idx[c]])
        for a, col, g in truth["boundaries"]:
            q[idx[a]] += g * (u[col] - x[idx[a]])
        for a, col, gain in truth["heats"]:
            q[idx[a]] += gain * u[col]
        cap = np.array([truth["nodes"][k][0] for k in names])
        beta = np.array([truth.get("capacitance_temperature", {}).get(k, 0.0) for k in names])
        return q / (cap * (1.0 + beta * (x - 25.0)))

    return f


@pytest.mark.parametrize("name", CASES)
def test_noise_free_matches_radau(name):
    truth = b.truth_of(name)
    ts = np.arange(2 * 96) * b.DT  # two days
    inputs = b.building_inputs(ts, np.random.default_rng(3))
    sim = b.simulate_building(truth, ts, inputs, np.random.default_rng(4), noise=False)
    names = list(truth["nodes"])
    f = _rhs(truth, names)
    x = np.array([sim[k][0] for k in names])
    # the start is the steady state of the first sample
    u0 = {c: inputs[c][0] for c in b.COLUMNS}
    assert np.max(np.abs(f(0.0, x, u0))) < 1e-12
    ref = [x]
    for k in range(len(ts) - 1):
        u = {c: inputs[c][k] for c in b.COLUMNS}
        r = scipy.integrate.solve_ivp(f, (ts[k], ts[k + 1]), ref[-1], method="Radau", args=(u,),
                                      rtol=1e-10, atol=1e-10)
        ref.append(r.y[:, -1])
    ref = np.array(ref)
    got = np.column_stack([sim[k] for k in names])
    # exact for a linear network; second order in its substeps for a nonlinear one (°C)
    assert np.max(np.abs(got - ref)) < (1e-4 if truth.get("capacitance_temperature") else 1e-6)
    assert np.array_equal(sim["yTi"], sim[truth["sensor"]["node"]])


def test_process_noise_covariance():
    truth = b.truth_of("building_4state")
    names, A, B, Q, _ = b.matrices(truth)
    Ad, Bd, Qd = b.discretize(A, B, Q, b.DT)
    # brute force: ∫0^dt e^{As} Q e^{Aᵀs} ds
    brute, _ = scipy.integrate.quad_vec(
        lambda s: scipy.linalg.expm(A * s) @ Q @ scipy.linalg.expm(A.T * s), 0.0, b.DT,
        epsabs=0.0, epsrel=1e-11)
    assert np.allclose(Qd, brute, rtol=1e-8, atol=1e-14 * np.max(Qd))
    # sample covariance of 20,000 one-step transitions drawn by simulate_building in one run
    # (inputs constant): the residuals x_{k+1} − e^{A dt} x_k − A⁻¹(e^{A dt} − I) B u are iid
    # N(0, Qd), with the noise-free step computed here, not by the generator
    n_draw = 20000
    ts = np.arange(n_draw + 1) * b.DT
    u = np.array([1.0, 200.0, 5000.0])
    inputs = {c: np.full(n_draw + 1, v) for c, v in zip(b.COLUMNS, u)}
    sim = b.simulate_building(truth, ts, inputs, np.random.default_rng(11))
    x = np.column_stack([sim[k] for k in names])
    E = scipy.linalg.expm(A * b.DT)
    step = np.linalg.solve(A, (E - np.eye(len(names))) @ B @ u)
    assert np.allclose(E, Ad, rtol=1e-12, atol=1e-14) and np.allclose(step, Bd @ u, rtol=1e-10)
    res = x[1:] - x[:-1] @ E.T - step
    S = res.T @ res / n_draw  # the mean is known (zero)
    se = np.sqrt((np.outer(np.diag(brute), np.diag(brute)) + brute ** 2) / n_draw)
    assert np.all(np.abs(S - brute) < 5 * se)
    assert np.all(np.abs(res.mean(0)) < 5 * np.sqrt(np.diag(brute) / n_draw))
    # and the sensor column is the sensor node plus white noise of the stated std
    v = sim["yTi"] - sim[truth["sensor"]["node"]]
    assert abs(v.std() / truth["sensor"]["noise"] - 1) < 5 / np.sqrt(2 * len(v))

@pytest.mark.parametrize("name", CASES)
def test_written_files(tmp_path, name):
    out = b.write_building_case(name, tmp_path, seed=2, days=3)
    assert out["model"] == tmp_path / f"{name}_model.toml"
    assert out["data"] == [tmp_path / f"{name}.csv"]
    assert out["expected_states"] == len(out["truth"]["nodes"])
    lines = out["data"][0].read_text().splitlines()
    assert lines[0] == "time_s,Ta,Ps,Ph,yTi"
    table = np.loadtxt(out["data"][0], delimiter=",", skiprows=1)
    assert table.shape == (3 * 96, 5)
    assert np.allclose(np.diff(table[:, 0]), b.DT) and table[0, 0] == 0.0
    assert np.all(np.isfinite(table))
    assert set(np.unique(table[:, 3])) == {0.0, 5000.0}
    assert table[:, 2].min() == 0.0 and table[:, 2].max() < 600.0
    doc = tomllib.loads(out["model"].read_text())
    assert [n["name"] for n in doc["nodes"]] == ["Ti"]
    assert {"process_noise", "initial", "initial_std"} <= set(doc["nodes"][0])
    assert [(x["node"], x["input"], x["hold"]) for x in doc["boundaries"]] == [("Ti", "Ta", "zoh")]
    assert [(x["input"], x["hold"]) for x in doc["heat_inputs"]] == [("Ph", "zoh"), ("Ps", "zoh")]
    assert doc["heat_inputs"][0]["gain"] == {"value": 1.0, "fixed": True}
    assert doc["sensors"] == [{"node": "Ti", "column": "yTi", "noise": 0.01}]
    # thermojax must read the written model: imported here so that the generator's other
    # checks need no thermojax, but a failed import fails this test (it is not skipped)
    from thermojax.model._model_file import load_model

    spec = load_model(out["model"])
    assert len(spec.nodes) == 1


def test_reproducible(tmp_path):
    a = b.write_building_case("building_4state", tmp_path / "a", seed=5, days=2)
    c = b.write_building_case("building_4state", tmp_path / "c", seed=5, days=2)
    d = b.write_building_case("building_4state", tmp_path / "d", seed=6, days=2)
    for key in ("model",):
        assert a[key].read_bytes() == c[key].read_bytes()
    assert a["data"][0].read_bytes() == c["data"][0].read_bytes()
    assert a["data"][0].read_bytes() != d["data"][0].read_bytes()
