"""Lag compensation by input reconstruction (the second seed's RTD).

Truths: `scipy.signal.step` for the raw sensor's step response, the eigen-decomposition
closed form for its 90 % time, `scipy.signal.cont2discrete` for the augmented model,
an analytic exponential for `rise_time`, and a Monte Carlo run for the noise
amplification computed from the Lyapunov equation.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.signal

import thermojax as tj
from thermojax import observer as ob
from thermojax.model import ThermalModel

from helpers import CONFIGS, model_matrices

DT = 0.1


def rtd():
    return ThermalModel.from_spec(tj.load_model(CONFIGS / "rtd2.toml"))


def step_data(steps, noise=None):
    """Core readings for a 20 -> 100 °C fluid step at t = 0 (scipy.signal.step, exact)."""
    m = model_matrices(CONFIGS / "rtd2.toml")
    ts = DT * np.arange(steps)
    _, y = scipy.signal.step((m["A"], m["B"], m["Cy"], np.zeros((1, 1))), T=ts)
    y = 20.0 + 80.0 * np.asarray(y).reshape(-1)
    return ts, y if noise is None else y + noise


def test_rise_time_on_an_exponential():
    ts = np.linspace(0, 20, 2001)
    tau = 3.0
    got = ob.rise_time(ts, 5 - 4 * np.exp(-ts / tau), 1.0, 5.0)
    assert math.isclose(got, tau * math.log(10), rel_tol=1e-5)  # linear interpolation
    assert ob.rise_time(ts, np.zeros_like(ts), 0.0, 1.0) == math.inf


def test_raw_sensor_is_much_slower_than_claimed():
    m = model_matrices(CONFIGS / "rtd2.toml")
    lam, V = np.linalg.eig(m["A"])
    x_inf = -np.linalg.solve(m["A"], m["B"][:, 0])
    coeff = np.linalg.solve(V, -x_inf)
    exact = scipy.optimize.brentq(
        lambda t: float(np.real(V @ (np.exp(lam * t) * coeff))[1] + x_inf[1]) - 0.9, 0, 100,
        xtol=1e-12)
    ts, y = step_data(400)
    raw = ob.rise_time(ts, y, 20.0, 100.0)
    assert abs(raw - exact) < 2e-3  # interpolation over 0.1 s samples of a smooth curve
    assert 11.8 < exact < 12.0  # about 11.92 s, not the source's 4.2 s


def test_augmented_model_against_cont2discrete():
    m = model_matrices(CONFIGS / "rtd2.toml")
    aug = ob.augment_unknown_input(rtd().linear_system(), 0)
    assert aug.A.shape == (3, 3) and aug.B.shape == (3, 0) and aug.holds == ()
    d = tj.discretize(aug, DT)
    Phi, Gam, *_ = scipy.signal.cont2discrete((m["A"], m["B"], m["Cy"], np.zeros((1, 1))), DT,
                                              method="zoh")
    # the input held as a state: its column is the ZOH input matrix
    np.testing.assert_allclose(np.asarray(d.Phi)[:2, :2], Phi, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(d.Phi)[:2, 2], Gam[:, 0], rtol=1e-12)
    np.testing.assert_allclose(np.asarray(d.Phi)[2], [0, 0, 1], atol=1e-15)
    with pytest.raises(ValueError, match="must index one of the system's 1 inputs"):
        ob.augment_unknown_input(rtd().linear_system(), 1)


def run_estimate(obs, y):
    run = ob.run_observer(obs, jnp.zeros((y.size, 0)), jnp.asarray(y[:, None]),
                          jnp.full(3, 20.0))
    return np.asarray(run.states)[:, 2]


def test_reconstruction_speed_and_noise_amplification():
    model = rtd()
    obs = ob.reconstruction_observer(model, DT, "T_fluid", input_noise=1.0)
    ts, y = step_data(300)
    u_hat = run_estimate(obs, y)
    t90 = ob.rise_time(ts, u_hat, 20.0, 100.0)
    assert 0.7 < t90 < 0.9  # measured 0.78 s (vs 11.9 s raw); the source claims 0.45 s
    assert abs(u_hat[-1] - 100.0) < 1e-3  # no bias once settled
    amp = ob.estimate_noise_std(obs, 0.01)[2] / 0.01
    # Monte Carlo: the estimate's deviation caused by noise alone (linear filter)
    rng = np.random.default_rng(0)
    noise = 0.01 * rng.standard_normal(20_000)
    _, y_long = step_data(20_000)
    dev = run_estimate(obs, y_long + noise) - run_estimate(obs, y_long)
    measured = np.std(dev[1000:]) / 0.01
    assert abs(measured / amp - 1) < 0.05  # 19 000 correlated samples: a few % sampling error
    assert 25 < amp < 32  # measured 28.7


def test_tradeoff_is_monotone():
    model = rtd()
    ts, y = step_data(300)
    t90s, amps = [], []
    for q in (0.01, 0.1, 1.0, 10.0):
        obs = ob.reconstruction_observer(model, DT, 0, input_noise=q)
        t90s.append(ob.rise_time(ts, run_estimate(obs, y), 20.0, 100.0))
        amps.append(ob.estimate_noise_std(obs, 0.01)[2] / 0.01)
    assert all(a > b for a, b in zip(t90s, t90s[1:]))  # faster with more input noise
    assert all(a < b for a, b in zip(amps, amps[1:]))  # and noisier


def test_reconstruction_errors():
    with pytest.raises(ValueError, match=r"the model's inputs are \['T_fluid'\]"):
        ob.reconstruction_observer(rtd(), DT, "T_air", 1.0)
    with pytest.raises(ValueError, match="input_noise"):
        ob.reconstruction_observer(rtd(), DT, "T_fluid", 0.0)
