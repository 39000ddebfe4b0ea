"""Residual analysis against independent formulas and known-answer signals."""

import numpy as np
import pytest
from scipy import stats

from thermojax.fitting._residual_analysis import (PHASES, cross_correlation, cumulated_periodogram,
                                          label_phases, ljung_box, residuals_by_phase)


def _ljung_box_reference(x, lags):
    """Textbook Ljung-Box for one series, written out with explicit loops."""
    x = np.asarray(x, float) - np.mean(x)
    n = len(x)
    c0 = sum(v * v for v in x)
    q = 0.0
    for k in range(1, lags + 1):
        ck = sum(x[t] * x[t - k] for t in range(k, n))
        q += (ck / c0) ** 2 / (n - k)
    q *= n * (n + 2)
    return q, stats.chi2.sf(q, lags)


def test_ljung_box_single_run_matches_textbook():
    x = np.random.default_rng(1).standard_normal(400)
    q, p, lags = ljung_box([x], 10)
    q_ref, p_ref = _ljung_box_reference(x, 10)
    assert lags == 10
    assert q == pytest.approx(q_ref, rel=1e-12)  # same formula, summation order only
    assert p == pytest.approx(p_ref, rel=1e-10)


def test_white_noise_is_white_and_ar1_is_not():
    rng = np.random.default_rng(2)
    white = [rng.standard_normal(3000) for _ in range(3)]
    _, p_white, _ = ljung_box(white)
    ar = []
    for _ in range(3):
        e = rng.standard_normal(3000)
        x = np.zeros_like(e)
        for k in range(1, len(e)):
            x[k] = 0.5 * x[k - 1] + e[k]
        ar.append(x)
    _, p_ar, _ = ljung_box(ar)
    assert p_white > 1e-3  # seeded white noise: a fixed, non-extreme draw
    assert p_ar < 1e-30  # AR(1) with phi = 0.5 over 9000 samples: rho_1 = 0.5


def test_ljung_box_ignores_dropped_samples_and_does_not_straddle_runs():
    rng = np.random.default_rng(3)
    a, b = rng.standard_normal(500), rng.standard_normal(500)
    # Two runs with very different levels: pooling must not see a jump between them.
    q_sep, _, _ = ljung_box([a + 100.0, b - 100.0], 5)
    q_ref, _, _ = ljung_box([a, b], 5)
    assert q_sep == pytest.approx(q_ref, rel=1e-12)  # each run centred on its own mean
    a_nan = a.copy()
    a_nan[10] = np.nan
    q_nan, p_nan, _ = ljung_box([a_nan], 5)
    assert np.isfinite(q_nan) and np.isfinite(p_nan)


def test_cross_correlation_finds_the_lag_of_a_leading_signal():
    rng = np.random.default_rng(4)
    s = rng.standard_normal(2000)
    r = np.roll(s, 7) + 0.1 * rng.standard_normal(2000)  # residual follows the signal 7 later
    r[:7] = 0.0
    lags, ccf, band = cross_correlation([r], [s], 20)
    assert lags[np.argmax(ccf)] == 7
    assert ccf.max() > 0.9 and band == pytest.approx(1.96 / np.sqrt(2000))
    # Independent noise stays (mostly) inside the band.
    _, ccf0, band0 = cross_correlation([rng.standard_normal(2000)], [s], 20)
    assert np.mean(np.abs(ccf0) < band0) > 0.85


def test_cross_correlation_equals_the_direct_lagged_sums():
    """Pooled over runs of different lengths, with dropped samples and lags longer than
    a run: the definition written out, sample by sample."""
    rng = np.random.default_rng(8)
    runs = [(rng.standard_normal(n), rng.standard_normal(n) + 3.0) for n in (50, 9, 31)]
    runs[0][0][[3, 17]] = np.nan
    runs[2][1][5] = np.nan
    max_lag = 12
    num = np.zeros(2 * max_lag + 1)
    rr = ss = 0.0
    for r, s in runs:
        ok = np.isfinite(r)
        rc = np.where(ok, r - r[ok].mean(), 0.0)
        fin = np.isfinite(s)
        sc = np.where(fin, s - s[fin].mean(), 0.0)
        rr, ss = rr + np.sum(rc ** 2), ss + np.sum(sc ** 2)
        for i, k in enumerate(range(-max_lag, max_lag + 1)):
            num[i] += sum(rc[t] * sc[t - k] for t in range(len(r)) if 0 <= t - k < len(s))
    lags, ccf, band = cross_correlation([r for r, _ in runs], [s for _, s in runs], max_lag)
    np.testing.assert_array_equal(lags, np.arange(-max_lag, max_lag + 1))
    np.testing.assert_allclose(ccf, num / np.sqrt(rr * ss), rtol=1e-10, atol=1e-14)
    assert band == pytest.approx(1.96 / np.sqrt(50 + 9 + 31))


def test_cumulated_periodogram_white_vs_lowpass():
    rng = np.random.default_rng(5)
    inside = []
    for _ in range(200):
        f, c, band = cumulated_periodogram([rng.standard_normal(512)])
        inside.append(np.max(np.abs(c - f)) < band)
    assert 0.90 < np.mean(inside) <= 1.0  # a 95 % band: ~190 of 200 white series inside
    x = np.convolve(rng.standard_normal(4096), np.ones(20) / 20, mode="same")
    f, c, band = cumulated_periodogram([x])
    assert np.max(np.abs(c - f)) > 3 * band  # low-pass: power piles up at low frequency


def test_cumulated_periodogram_pools_runs_of_unequal_length_by_frequency():
    """A tone at 0.6 of Nyquist in the longer of two white runs shows as a jump at 0.6,
    wherever the shorter run's frequencies fall; two white runs stay inside the band."""
    rng = np.random.default_rng(6)
    short, long = rng.standard_normal(600), rng.standard_normal(2000)
    f, c, band = cumulated_periodogram([short, long])
    assert len(f) == 300 + 1000 and np.all(np.diff(f) >= 0) and f[-1] == 1.0
    assert np.max(np.abs(c - f)) < band
    k = np.arange(2000)
    f, c, band = cumulated_periodogram([short, long + 2.0 * np.sin(np.pi * 0.6 * k)])
    jump = np.argmax(np.diff(c))
    assert abs(f[jump + 1] - 0.6) < 2e-3 and c[jump + 1] - c[jump] > 0.3


def test_phases_from_data():
    ts = np.arange(0, 3600.0, 1.0)
    temp = np.interp(ts, [0, 600, 1200, 1800, 2400, 3600], [25, 25, 75, 75, 25, 25])
    power = np.where((ts >= 3000), 1.0, 0.0)
    ph = label_phases(ts, temp, power)
    assert np.all(ph.mask("heating_ramp")[700:1100])
    assert np.all(ph.mask("cooling_ramp")[1900:2300])
    assert np.all(ph.mask("dwell")[100:500])
    assert np.all(ph.mask("power_step")[3000:3590])
    res = np.where(ph.mask("heating_ramp"), 0.2, 0.0) + np.where(ph.mask("cooling_ramp"), -0.1, 0)
    out = residuals_by_phase([res], [ph])
    assert out["heating_ramp"]["mean"] == pytest.approx(0.2)
    assert out["cooling_ramp"]["mean"] == pytest.approx(-0.1)
    assert out["heating_minus_cooling"] == pytest.approx(0.3)
    assert set(PHASES) <= set(out)
