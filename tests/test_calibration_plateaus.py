"""Dwell plateaus found in a synthetic chamber run, and the static polynomial fitted through
them, against the known setpoints and polynomial, numpy.polyfit and scipy's curve_fit."""

import numpy as np
import pytest
from scipy import optimize

from thermojax._errors import InputError
from thermojax.calibration import find_plateaus, fit_static_polynomial

SETPOINTS = (-40.0, -15.0, 10.0, 35.0, 60.0, 85.0)
TRUTH = np.array([1.2, 0.05, -2e-3, 4e-5, 3e-7, -6e-9])  # deg/h per K^k, in (T − 25)


def chamber_run(setpoints, dwell_s=3600.0, rate_k_per_min=2.0, lag_s=120.0, seed=0):
    """1 Hz: ramps at `rate_k_per_min` between dwells; the sensor lags the chamber
    (first order, `lag_s`) and reads with 0.01 K noise; bias = TRUTH(T) + 0.02 deg/h noise."""
    knots_t, knots_T = [0.0], [setpoints[0]]
    for a, b in zip(setpoints, setpoints[1:] + (setpoints[-1],)):
        knots_t += [knots_t[-1] + dwell_s, knots_t[-1] + dwell_s + abs(b - a) / rate_k_per_min * 60]
        knots_T += [a, b]
    ts = np.arange(0.0, knots_t[-1], 1.0)
    chamber = np.interp(ts, knots_t, knots_T)
    T = np.empty_like(chamber)
    T[0] = chamber[0]
    k = np.exp(-1.0 / lag_s)
    for i in range(1, ts.size):
        T[i] = k * T[i - 1] + (1 - k) * chamber[i - 1]
    rng = np.random.default_rng(seed)
    bias = np.polynomial.polynomial.polyval(T - 25, TRUTH) + 0.02 * rng.standard_normal(ts.size)
    return ts, T + 0.01 * rng.standard_normal(ts.size), bias, np.array(knots_t)


def test_plateaus_found_at_the_setpoints():
    ts, T, bias, knots = chamber_run(SETPOINTS)
    plateaus = find_plateaus(ts, T, bias)
    assert len(plateaus) == len(SETPOINTS)
    for p, sp, start, end in zip(plateaus, SETPOINTS, knots[0::2], knots[1::2]):
        # after the settle margin (600 s = 5 lags) the sensor is within e⁻⁵·ramp·lag of setpoint
        assert p.temperature == pytest.approx(sp, abs=0.02)
        assert start + 600 <= p.start_s <= start + 600 + 5 * 120 and p.end_s <= end + 60
        truth = np.polynomial.polynomial.polyval(sp - 25, TRUTH)
        assert p.bias == pytest.approx(truth, abs=5 * 0.02 / np.sqrt(p.n) + 1e-3)


def test_polynomial_recovered_and_matches_polyfit():
    ts, T, bias, _ = chamber_run(SETPOINTS)
    plateaus = find_plateaus(ts, T, bias)
    temps = np.array([p.temperature for p in plateaus])
    biases = np.array([p.bias for p in plateaus])
    stds = np.array([p.bias_std / np.sqrt(p.n) for p in plateaus])
    fit = fit_static_polynomial(temps, biases, 4)
    expected = np.polynomial.polynomial.polyfit(temps - 25, biases, 4)
    np.testing.assert_allclose(fit.coefficients, expected, rtol=1e-8)  # same LSQ; conditioning
    fit5 = fit_static_polynomial(temps, biases, 5, bias_std=stds)
    assert np.all(np.abs(fit5.coefficients - TRUTH) < 4 * fit5.std)  # exactly determined
    np.testing.assert_allclose(fit5(temps), biases, atol=1e-9)  # interpolates the 6 means
    # covariance of the weighted fit against scipy's (absolute sigma)
    _, pcov = optimize.curve_fit(lambda x, *c: np.polynomial.polynomial.polyval(x, c),
                                 temps - 25, biases, p0=np.zeros(6), sigma=stds,
                                 absolute_sigma=True)
    np.testing.assert_allclose(fit5.std, np.sqrt(np.diag(pcov)), rtol=1e-5)  # LM vs direct


def test_unweighted_stds_match_monte_carlo():
    rng = np.random.default_rng(3)
    temps = np.linspace(-40, 85, 12)
    sigma = 0.1
    fits = [fit_static_polynomial(temps, np.polynomial.polynomial.polyval(temps - 25, TRUTH[:3])
                                  + sigma * rng.standard_normal(12), 2) for _ in range(400)]
    spread = np.std([f.coefficients for f in fits], axis=0)
    mean_std = np.mean([f.std for f in fits], axis=0)
    np.testing.assert_allclose(mean_std, spread, rtol=0.12)  # 400 draws: ~4 % scatter


def test_too_few_plateaus():
    ts, T, bias, _ = chamber_run((-40.0, 25.0, 85.0))
    plateaus = find_plateaus(ts, T, bias)
    assert len(plateaus) == 3
    with pytest.raises(InputError, match=r"found 3 dwell plateaus; a 5th-order polynomial needs "
                                         r"at least 6: lower the order to 2"):
        fit_static_polynomial([p.temperature for p in plateaus], [p.bias for p in plateaus], 5,
                              name="gyro_x_dph")
    with pytest.raises(InputError, match=r"only 2 distinct temperatures"):
        fit_static_polynomial([0, 0, 50, 50], [1, 1.1, 2, 2.1], 2)
    with pytest.raises(InputError, match=r"order must be 0…5"):
        fit_static_polynomial([0, 1], [0, 1], 6)


def test_all_nan_bias():
    ts, T, bias, _ = chamber_run((-40.0, 25.0))
    with pytest.raises(InputError, match=r"field 'gyro_x_dph'.*all NaN"):
        find_plateaus(ts, T, np.full(ts.size, np.nan), name="gyro_x_dph")
    with pytest.raises(InputError, match=r"NaN on every plateau"):
        fit_static_polynomial([0.0, 50.0], [np.nan, np.nan], 1)
