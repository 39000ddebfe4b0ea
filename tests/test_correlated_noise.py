"""Newey-West stds for output-error fits with correlated residuals
(thermojax/fitting/_correlated_noise.py).

Truths: the exact covariance of least squares under AR(1) noise, written out from the
noise's covariance matrix; and for a thermal fit the long-run variance factor
`(1 + ρ)/(1 − ρ)` that AR(1) noise puts on a slowly varying regressor's estimate.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

from thermojax.fitting import fit
from thermojax.fitting._correlated_noise import (correlated_noise_stds, hac_covariance,
                                                 newey_west_lags)
from thermojax.measurements._data import Experiment
from thermojax.model._model_file import parse_model


def ar1(rng, rho, sigma, shape):
    """AR(1) noise `x_k = ρ x_(k−1) + e_k` with marginal std `sigma` along the last axis,
    started stationary."""
    e = rng.normal(0.0, sigma * np.sqrt(1 - rho ** 2), shape)
    e[..., 0] = rng.normal(0.0, sigma, shape[:-1])
    return scipy.signal.lfilter([1.0], [1.0, -rho], e, axis=-1)


def test_newey_west_matches_the_exact_ar1_covariance_of_least_squares():
    rng = np.random.default_rng(1)
    runs, T, rho, sigma = 8, 2000, 0.6, 0.3
    t = np.linspace(0.0, 1.0, T)
    X = np.stack([np.ones(T), t, np.sin(6 * t)], 1)  # slowly varying regressors
    noise = ar1(rng, rho, sigma, (runs, T))
    y = X @ np.array([1.0, -2.0, 0.5]) + noise
    F = runs * X.T @ X
    beta = np.linalg.solve(F, X.T @ y.sum(0))
    r = y - X @ beta
    scores = X[None, :, :] * r[:, :, None]
    bread = np.linalg.inv(F)
    hac = hac_covariance(scores, bread, lags=30)
    # exact: Cov = F⁻¹ (runs · Xᵀ Σ X) F⁻¹, Σ_ij = σ² ρ^|i−j|
    Sigma = sigma ** 2 * scipy.linalg.toeplitz(rho ** np.arange(T))
    exact = bread @ (runs * X.T @ Sigma @ X) @ bread
    np.testing.assert_allclose(np.sqrt(np.diag(hac)), np.sqrt(np.diag(exact)), rtol=0.1)
    # the white-noise covariance is too small by about sqrt((1 + ρ)/(1 − ρ)) = 2
    white = sigma ** 2 * bread
    assert np.all(np.sqrt(np.diag(exact) / np.diag(white)) > 1.7)
    # no lags: White's estimator, about the white covariance here (homoskedastic)
    np.testing.assert_allclose(np.sqrt(np.diag(hac_covariance(scores, bread, 0))),
                               np.sqrt(np.diag(white)), rtol=0.1)


def test_rule_of_thumb_lags():
    assert [newey_west_lags(n) for n in (100, 1000, 10000)] == [4, 6, 11]


MODEL = """
name = "one node"
[[nodes]]
name = "body"
capacitance = 50.0
[[boundaries]]
node = "body"
input = "T_chamber"
conductance = 0.5
[[heat_inputs]]
node = "body"
input = "P_heater"
gain = { value = 1.0, fixed = true }
[[sensors]]
node = "body"
column = "T_body"
"""


def one_node_runs(rho, seed=0):
    """Two 1 Hz runs of chamber and heater steps through C 40 J/K, G 0.4 W/K (τ 100 s),
    simulated exactly (SciPy `lsim`, inputs linear between samples as the model's default
    first-order hold has them), AR(1) sensor noise."""
    rng = np.random.default_rng(seed)
    C, G, T = 40.0, 0.4, 3000
    ts = np.arange(T, dtype=float)
    sys = scipy.signal.StateSpace([[-G / C]], [[G / C, 1 / C]], [[1.0]], [[0.0, 0.0]])
    runs = []
    for levels in ((20, 60, 30, 80, 40, 50), (70, 25, 55, 35, 85, 45)):
        chamber = np.repeat(np.asarray(levels, float), T // len(levels))
        heater = 2.0 * (np.arange(T) // 250 % 2)
        u = np.stack([chamber, heater], 1)
        _, y, _ = scipy.signal.lsim(sys, u, ts, X0=[chamber[0]])
        y = y + ar1(rng, rho, 0.02, (T,))
        runs.append(Experiment(ts, u, y[:, None], f"steps{len(runs)}"))
    return runs


@pytest.mark.parametrize("rho", [0.0, 0.5])
def test_fit_stds_under_ar1_sensor_noise(rho):
    spec = parse_model(MODEL, "one.toml")
    result = fit(spec, one_node_runs(rho))
    assert result.converged
    corr = correlated_noise_stds(result)
    assert corr.lags == newey_west_lags(3000)
    assert corr.autocorrelation["T_body"] == pytest.approx(rho, abs=0.06)
    expected = np.sqrt((1 + rho) / (1 - rho))  # 1 and 1.73
    for name in ("nodes.body.capacitance", "boundaries.body-T_chamber.conductance"):
        assert corr.ratio[name] == pytest.approx(expected, rel=0.15), (name, corr.ratio)
        assert corr.stds[name] == pytest.approx(corr.ratio[name] * result.parameters[name]["std"])
        # the truth (C 40, G 0.4) within 3 of the corrected stds
        truth = 40.0 if "capacitance" in name else 0.4
        assert abs(result.parameters[name]["value"] - truth) < 3 * corr.stds[name]


def test_refuses_kalman_fits():
    result = fit(parse_model(MODEL, "one.toml"), one_node_runs(0.0)[:1])
    with pytest.raises(ValueError, match="Kalman"):
        correlated_noise_stds(dataclasses.replace(result, likelihood="kalman"))
