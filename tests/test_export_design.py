"""`observer.json` determines the gains and states the bound it guarantees: the Kalman
gain recomputed by SciPy from the recorded q and R alone, the recorded poles found in
the exported gain, and the fixed build's playback inside the recorded error bound."""

from __future__ import annotations

import json

import numpy as np
import scipy.linalg

import thermojax.reference as ref
from thermojax.cli import main

from helpers import CONFIGS, model_matrices, np_van_loan

MODEL = str(CONFIGS / "rtd2.toml")


def _export(tmp_path, *flags):
    out = tmp_path / "obs"
    assert main(["export", "--model", MODEL, "--rate", "2", "--out", str(out), *flags,
                 "--quiet"]) == 0
    return out, json.loads((out / "observer.json").read_text())


def test_recorded_q_and_r_give_the_exported_kalman_gain(tmp_path, capsys):
    out, meta = _export(tmp_path, "--fixed", "q16.16")
    said = capsys.readouterr().out
    d = meta["design"]
    q = np.array([d["process_noise_C_per_sqrt_s"][s["name"]] for s in meta["states"]])
    r = np.array([d["sensor_noise_C"][o["name"]] for o in meta["outputs"]])
    m = model_matrices(CONFIGS / "rtd2.toml")
    dt = meta["dt_s"]
    Phi = scipy.linalg.expm(m["A"] * dt)
    Qd = np_van_loan(m["A"], np.diag(q ** 2), dt)
    C, R = m["Cy"], np.diag(r ** 2)
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, R)
    L = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    art = ref.load_observer(out)
    np.testing.assert_allclose(art.system.L, L, rtol=1e-8)
    # the printed guarantee is the recorded one
    bound = meta["fixed"]["error_bound"]
    assert f"guaranteed within {bound['max_K']:.3g} K" in said


def test_recorded_poles_are_the_exported_gains(tmp_path):
    out, meta = _export(tmp_path, "--method", "poles")
    poles = meta["design"]["poles"]
    art = ref.load_observer(out)
    s = art.system
    got = np.sort(np.linalg.eigvals(s.Phi - s.L @ s.C @ s.Phi).real)
    np.testing.assert_allclose(got, np.sort(poles["discrete"]), rtol=1e-6)
    np.testing.assert_allclose(np.sort(poles["discrete"]),
                               np.sort(np.exp(np.array(poles["continuous_per_s"]) *
                                              meta["dt_s"])), rtol=1e-12)


def test_fixed_playback_stays_inside_the_recorded_bound(tmp_path):
    out, meta = _export(tmp_path, "--fixed", "q16.16")
    art = ref.load_observer(out)
    rng = np.random.default_rng(0)
    T = 4000
    u = np.cumsum(rng.normal(0.0, 0.5, (T, 1)), 0) + 30.0        # a wandering fluid
    y = np.clip(u + rng.normal(0.0, 0.05, (T, 1)), -50.0, 120.0)
    x0 = np.array([30.0, 30.0])
    exact = art.float_observer().run(x0, u, y).states
    fx = art.fixed_observer()
    got = fx.run_physical(x0, u, y).states
    bound = np.array([meta["fixed"]["error_bound"]["bound_K"][s["name"]]
                      for s in meta["states"]])
    err = np.abs(got - exact).max(axis=0)
    assert np.all(err <= bound), (err, bound)
    assert np.all(err > 0)        # the formats differ: the check is not vacuous
