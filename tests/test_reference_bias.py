"""Bias channels evaluated by the reference observer (docs/formats.md §4), against an
independent computation: polynomial, gradient and rate terms written out in NumPy from
the model file (read with `tomllib`), and the viscoelastic strain integrated by
`scipy.integrate.solve_ivp` through the node temperature held linear between samples."""

import numpy as np
import pytest
import scipy.integrate

from helpers import CONFIGS, model_matrices, np_discretize
from test_reference_setup import DT, chamber_profile, simulate_plant, steady_state

import thermojax.reference as ref
from thermojax.observer import export_observer

MODEL = CONFIGS / "imu6_bias.toml"


def plant(steps, seed=0):
    """Exact node temperatures and noiseless readings of imu6_bias under a chamber profile."""
    net = model_matrices(MODEL)
    A, B = net["A"], net["B"]
    Phi, B0, B1 = np_discretize(A, B, DT, net["holds"])
    C = net["Cy"]
    u = chamber_profile(steps, DT, seed)
    x0 = steady_state(Phi, B0, B1, u[0])
    x, y = simulate_plant(Phi, B0, B1, C, np.zeros((C.shape[0], B.shape[1])), x0, u)
    return net, u, x, y, x0


def strain_ivp(ts, T, tau):
    """ε of dε/dt = (T(t) − ε)/τ, T linear between samples, ε(0) = T(0), by solve_ivp
    (`max_step` one sample: larger steps stride over the kinks of the interpolant)."""
    sol = scipy.integrate.solve_ivp(lambda t, e: (np.interp(t, ts, T) - e) / tau,
                                    (ts[0], ts[-1]), [T[0]], t_eval=ts, method="DOP853",
                                    rtol=1e-12, atol=1e-12, max_step=ts[1] - ts[0])
    assert sol.success
    return sol.y[0]


def independent_bias(net, x, u):
    """The two channels of imu6_bias.toml, written out from the file's numbers."""
    i = {n: k for k, n in enumerate(net["names"])}
    ts = np.arange(x.shape[0]) * DT
    d = x[:, i["proof_mass"]] - 25.0
    dT_mems = x @ net["A"][i["mems"]] + u @ net["B"][i["mems"]]     # exact model derivative
    gyro = (np.polynomial.polynomial.polyval(d, [0.5, 0.03, 5e-4, -2e-6])
            + 0.8 * (x[:, i["mems"]] - x[:, i["asic"]]) + 4.0 * dT_mems)
    T = x[:, i["mems"]]
    eps = strain_ivp(ts, T, 1500.0)
    accel = (np.polynomial.polynomial.polyval(T - 25.0, [120.0, -1.5, 0.02])
             + 3.0 * (x[:, i["pcb"]] - T) + 0.6 * (T - eps))
    return np.stack([gyro, accel], 1), T - eps


def test_artifact_observer_evaluates_bias_channels(tmp_path):
    """Exported imu6_bias, played back on exact readings: the estimate is the plant state,
    and the bias output equals the independent formula (strain by solve_ivp)."""
    export_observer(MODEL, 1 / DT, tmp_path)
    art = ref.load_observer(tmp_path)
    net, u, x, y, x0 = plant(24_000)          # 20 min at 20 Hz
    run = art.float_observer().run(x0, u, y)
    np.testing.assert_allclose(run.states, x, rtol=0, atol=1e-9)   # exact readings: roundoff
    want, strain = independent_bias(net, x, u)
    assert run.bias.shape == (24_000, 2)
    assert np.abs(strain).max() > 0.5         # the strain term matters in this profile (K)
    # the rate term: the continuous A_c, B_c rows in the artifact are the model's
    i = net["names"].index("mems")
    assert art.arrays["bias_rate_nodes"].tolist() == [i]
    np.testing.assert_allclose(art.arrays["bias_rate_A"][0], net["A"][i], rtol=1e-12, atol=0)
    np.testing.assert_allclose(art.arrays["bias_rate_B"][0], net["B"][i], rtol=1e-12, atol=1e-15)
    # gyro: deg/h, accel: ug; the states carry ~1e-10 K of roundoff; solve_ivp rtol 1e-11
    np.testing.assert_allclose(run.bias[:, 0], want[:, 0], rtol=0, atol=1e-8)
    np.testing.assert_allclose(run.bias[:, 1], want[:, 1], rtol=0, atol=1e-7)
    # evaluating the estimates afterwards gives the same numbers as during the run
    again = art.bias_evaluator().run(run.states, u)
    np.testing.assert_array_equal(again, run.bias)


def test_prony_series_and_rate_against_solve_ivp():
    """Two strain terms on one node (a Prony series) plus a rate and a gradient, fed the
    exact states directly."""
    net, u, x, _, _ = plant(12_000, seed=4)
    n = x.shape[1]
    ch = ref.BiasChannel("g", node=4, poly=(1.0, -0.2, 0.01), gradients=((2, 4, 0.5),),
                         rates=((3, 2.0), (4, -1.0)),
                         strains=((4, 300.0, 0.7), (4, 40.0, -0.3), (1, 2000.0, 0.1)))
    ev = ref.BiasEvaluator([ch], DT, net["A"], net["B"])
    got = ev.run(x, u)[:, 0]
    ts = np.arange(x.shape[0]) * DT
    rate = lambda k: x @ net["A"][k] + u @ net["B"][k]
    want = (1.0 - 0.2 * (x[:, 4] - 25) + 0.01 * (x[:, 4] - 25) ** 2
            + 0.5 * (x[:, 2] - x[:, 4]) + 2.0 * rate(3) - rate(4)
            + 0.7 * (x[:, 4] - strain_ivp(ts, x[:, 4], 300.0))
            - 0.3 * (x[:, 4] - strain_ivp(ts, x[:, 4], 40.0))
            + 0.1 * (x[:, 1] - strain_ivp(ts, x[:, 1], 2000.0)))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-8)   # solve_ivp: ~2e-9 K per strain
    assert n == 6


def test_strain_exact_on_a_ramp():
    """T = T0 + r t from rest: ε(t) = T(t) − r τ (1 − e^{−t/τ}), exactly (FOH is exact)."""
    tau, r, dt = 30.0, 0.2, 0.5
    t = np.arange(400) * dt
    x = np.zeros((400, 1))
    x[:, 0] = 20.0 + r * t
    ev = ref.BiasEvaluator([ref.BiasChannel("s", 0, strains=((0, tau, 1.0),))], dt)
    got = ev.run(x, np.zeros((400, 0)))[:, 0]          # k (T − ε) with k = 1
    np.testing.assert_allclose(got, r * tau * (1 - np.exp(-t / tau)), rtol=1e-12, atol=1e-12)


def test_no_bias_channels_and_bad_artifact(tmp_path):
    export_observer(CONFIGS / "imu6.toml", 1 / DT, tmp_path / "plain")
    art = ref.load_observer(tmp_path / "plain")
    assert art.bias_evaluator() is None
    _, u, x, y, x0 = plant(50)
    assert art.float_observer().run(x0, u, y).bias is None
    export_observer(MODEL, 1 / DT, tmp_path / "bias")
    art = ref.load_observer(tmp_path / "bias")
    del art.arrays["bias_rate_A"]
    with pytest.raises(ValueError, match="'bias_rate_A' is missing"):
        art.float_observer()
    with pytest.raises(ValueError, match="rate terms need"):
        ref.BiasEvaluator([ref.BiasChannel("g", 0, rates=((0, 1.0),))], DT)
    with pytest.raises(ValueError, match="must be positive"):
        ref.BiasEvaluator([ref.BiasChannel("g", 0, strains=((0, 0.0, 1.0),))], DT)
