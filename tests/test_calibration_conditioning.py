"""Data conditioning: synchronizing two streams, the Hampel filter, and orientation
offsets told apart from thermal drift, each against data with a known truth."""

import numpy as np
import pytest
from scipy import signal, stats

from thermojax._errors import InputError
from thermojax.calibration import (ORIENTATIONS, label_orientations, remove_outliers,
                                   separate_orientation_bias, synchronize)


def test_synchronize_low_passes_before_decimating():
    # inertial at 100 Hz from 3 s to 603 s; temperature at 1 Hz from 0 s to 500 s
    t_in = 3.0 + np.arange(60000) / 100.0
    slow = 2.0 * np.sin(2 * np.pi * 0.01 * t_in)        # kept: 0.01 Hz
    fast = 1.0 * np.cos(2 * np.pi * 1.0 * t_in)         # 1 Hz: aliases to DC at 1 Hz sampling
    t_T = np.arange(501.0)
    sync = synchronize(t_T, {"T": 20 + 0.01 * t_T}, t_in, {"gyro": slow + fast})
    assert sync.ts[0] == 3.0 and sync.ts[-1] == 500.0  # overlap only, temperature times
    assert sync.cutoff_hz == pytest.approx(0.8 * 0.5)
    assert sync.matched  # the temperature stream went through the same low-pass
    # a ramp passes a zero-phase low-pass unchanged, but for the edge transients (1e-4)
    np.testing.assert_allclose(sync.temperature["T"], 20 + 0.01 * sync.ts, rtol=0, atol=1e-4)
    inner = (sync.ts > 20) & (sync.ts < 480)  # away from the filter's edge transients
    truth = 2.0 * np.sin(2 * np.pi * 0.01 * sync.ts)
    # a 4th-order Butterworth twice at 0.4 Hz: |H(0.01 Hz)|² − 1 ~ 1e-12, |H(1 Hz)|² ~ 6e-4
    np.testing.assert_allclose(sync.inertial["gyro"][inner], truth[inner], atol=2e-3)
    naive = np.interp(sync.ts, t_in, slow + fast)  # decimating without the filter aliases
    assert np.max(np.abs(naive[inner] - truth[inner])) > 0.5


def test_synchronize_matches_scipy_filter_on_a_given_grid():
    rng = np.random.default_rng(0)
    t_in = np.arange(2000) / 50.0
    x = rng.standard_normal(t_in.size)
    ts = np.arange(0.0, 40.0, 0.5)
    sync = synchronize(t_in[::10], {"T": np.zeros(200)}, t_in, {"a": x}, ts=ts)
    sos = signal.butter(4, 0.8, fs=50.0, output="sos")
    np.testing.assert_allclose(sync.inertial["a"],
                               np.interp(sync.ts, t_in, signal.sosfiltfilt(sos, x)),
                               rtol=0, atol=1e-12)  # same filter; roundoff only


def test_synchronize_bad_input():
    t = np.arange(10.0)
    with pytest.raises(InputError, match=r"temperature stream \(0…9 s\) and the inertial stream \(100…109 s\) do not overlap"):
        synchronize(t, {"T": t}, t + 100, {"g": t})
    back = t.copy()
    back[6] = 4.5
    with pytest.raises(InputError, match=r"inertial stream's timestamps go backwards .* row 6"):
        synchronize(t, {"T": t}, back, {"g": t})
    with pytest.raises(InputError, match=r"temperature stream needs at least two samples, got 0"):
        synchronize([], {"T": []}, t, {"g": t})
    with pytest.raises(InputError, match=r"field 'g'.*non-finite sample at row 2"):
        synchronize(t, {"T": t}, t, {"g": np.where(t == 2, np.nan, t)})


def _foh_lag(u, h, tau):
    """x' = (u − x)/τ, exact for u linear between samples h apart (from x = u_0)."""
    a = np.exp(-h / tau)
    b1 = 1 - tau * (1 - a) / h
    x = np.empty_like(u)
    x[0] = u[0]
    for k in range(u.size - 1):
        x[k + 1] = a * x[k] + (1 - a - b1) * u[k] + b1 * u[k + 1]
    return x


def test_matched_filtering_keeps_a_gradient_coefficient():
    # a chamber input with steps (1 Hz log, each step a 1 s ramp: its FOH is exact), a
    # lagged node x (τ = 30 s), and a bias 0.8·(u − x) logged at 20 Hz. Decimated to
    # 10 s and regressed on u − x simulated from the decimated input, the gain must come
    # back 0.8: only if the input went through the same low-pass as the bias.
    tau, gain, dt = 30.0, 0.8, 10.0
    t_T = np.arange(4001.0)
    u_T = np.zeros(t_T.size)
    for t_step, level in ((203, 10.0), (617, -5.0), (1234, 20.0), (1999, 0.0), (2571, 15.0),
                          (3303, -10.0)):
        u_T[t_T >= t_step] = level  # steps off the 10 s grid
    t_in = np.arange(80001) / 20.0
    u_in = np.interp(t_in, t_T, u_T)
    bias = gain * (u_in - _foh_lag(u_in, 0.05, tau))
    ts = np.arange(0.0, 4000.0 + 1e-9, dt)
    got = {}
    for matched in (True, False):
        s = synchronize(t_T, {"u": u_T}, t_in, {"b": bias}, ts, matched=matched)
        assert s.matched == matched
        r = s.temperature["u"] - _foh_lag(s.temperature["u"], dt, tau)
        got[matched] = float(s.inertial["b"] @ r / (r @ r))
    # matched: only FOH interpolation of the band-limited input at 10 s is left (~0.1 %)
    assert got[True] == pytest.approx(gain, rel=2e-3)
    assert abs(got[False] - gain) > 0.03 * gain  # the defect: ~8 % low unmatched


def test_synchronize_low_passes_both_streams_alike():
    # a sinusoid at the cutoff in both streams: both come out at the filter's gain there,
    # |H(f_c)|² = 1/2 for a Butterworth run forward and backward (bilinear prewarping puts
    # the cutoff at f_c at any rate)
    f = 0.8 * 0.5 / 10.0
    t_T = np.arange(0.0, 3000.0, 2.0)
    t_in = np.arange(0.0, 3000.0, 0.2)
    ts = np.arange(0.0, 2990.0, 10.0)
    s = synchronize(t_T, {"T": np.sin(2 * np.pi * f * t_T)}, t_in,
                    {"g": np.sin(2 * np.pi * f * t_in)}, ts)
    inner = (ts > 600) & (ts < 2400)  # away from the edge transients
    half = 0.5 * np.sin(2 * np.pi * f * ts)
    # |H|² at the cutoff is 1/2 exactly; 2e-3 for the edges' and interpolation's residue
    np.testing.assert_allclose(s.temperature["T"][inner], half[inner], atol=2e-3)
    np.testing.assert_allclose(s.inertial["g"][inner], half[inner], atol=2e-3)


def test_zero_order_hold_inputs_are_averaged_per_interval():
    # power switched at 23 s and off at 61 s (1 s ZOH log); on a 10 s base a ZOH input
    # must carry each interval's mean: 2 W for 7 s of [20, 30), for 1 s of [60, 70)
    t_T = np.arange(100.0)
    p = np.where((t_T >= 23) & (t_T < 61), 2.0, 0.0)
    ts = np.arange(0.0, 91.0, 10.0)
    s = synchronize(t_T, {"P": p, "Q": p}, t_T, {"g": np.zeros(100)}, ts,
                    holds={"P": "zoh"}, matched=False)
    expected = np.array([0, 0, 1.4, 2, 2, 2, 0.2, 0, 0, 0])
    np.testing.assert_allclose(s.temperature["P"], expected, rtol=0, atol=1e-12)  # exact
    np.testing.assert_array_equal(s.temperature["Q"], np.interp(ts, t_T, p))  # FOH: samples
    with pytest.raises(InputError, match="hold of 'P' must be 'zoh' or 'foh'"):
        synchronize(t_T, {"P": p}, t_T, {"g": p}, ts, holds={"P": "linear"})


def test_noise_factor_is_the_decimated_noise_variance_ratio():
    # Monte Carlo: the mean of N decimated samples of low-passed white noise has
    # noise_factor² times the variance σ_f²/N that independent samples would give
    rng = np.random.default_rng(5)
    t_in = np.arange(10000) / 5.0
    channels = {str(k): rng.standard_normal(t_in.size) for k in range(1000)}
    ts = np.arange(100.0, 1900.0, 10.0)
    s = synchronize(t_in, {"T": np.zeros(t_in.size)}, t_in, channels, ts)
    x = np.stack(list(s.inertial.values()))
    ratio = x.mean(axis=1).var() / (x.var() / ts.size)
    assert 1.1 < s.noise_factor < 1.3
    # 1000 realizations: the variance ratio is known to ~5 %; 15 % bounds
    assert ratio == pytest.approx(s.noise_factor ** 2, rel=0.15)


def hampel_loop(x, half, n, block):
    """The rule written out: median of the window, σ̂ from successive differences per
    block (len/block nearly equal blocks)."""
    out = np.zeros(x.size, bool)
    padded = np.concatenate([[x[0]] * half, x, [x[-1]] * half])
    nb = max(1, round(x.size / block))
    edges = [int(v) for v in np.linspace(0, x.size, nb + 1)]
    sigma = np.empty(x.size)
    for a, b in zip(edges[:-1], edges[1:]):
        d = [abs(x[j + 1] - x[j]) for j in range(a, min(b, x.size - 1))]
        sigma[a:b] = np.median(d) / (np.sqrt(2) * 0.6744897501960817)
    for i in range(x.size):
        w = padded[i:i + 2 * half + 1]
        out[i] = abs(x[i] - np.median(w)) > n * sigma[i]
    return out


def test_hampel_matches_a_loop_and_finds_spikes():
    rng = np.random.default_rng(1)
    t = np.arange(3000) / 10.0
    x = np.sin(t / 100.0) + 0.01 * rng.standard_normal(t.size)
    spikes = rng.choice(np.arange(5, t.size - 5), 30, replace=False)
    x[spikes] += rng.choice([-1, 1], 30) * rng.uniform(0.5, 2.0, 30)  # ≥ 50 σ
    out = remove_outliers(x, window=7, n_sigmas=3.0, scale_window=700, chunk=1000)
    np.testing.assert_array_equal(out.mask, hampel_loop(x, 3, 3.0, 700))
    assert set(spikes) <= set(np.flatnonzero(out.mask))
    assert np.all(np.isnan(out.cleaned[spikes]))
    # the noise std is seen through the sinusoid and the spikes (σ̂ from ~750 samples
    # has a ~4.5 % std: ±15 %)
    np.testing.assert_allclose(out.scale, 0.01, rtol=0.15)
    np.testing.assert_allclose(out.filled[spikes], np.sin(t[spikes] / 100.0), atol=0.05)


def _false_alarm_rate(window, n):
    """P(|x_i − median of the window| > n σ) for white Gaussian noise, σ known: the
    window's median is the other samples' upper (lower) median when x_i lies above
    (below) it, so the rate is 2 ∫ f(y) Φ̄(y + n) dy, f the density of order statistic
    h + 1 of 2h standard normals (h = window // 2)."""
    from scipy import integrate, special

    h = window // 2
    c = special.factorial(2 * h) / (special.factorial(h) * special.factorial(h - 1))
    dens = lambda y: (c * stats.norm.cdf(y) ** h * stats.norm.sf(y) ** (h - 1)  # noqa: E731
                      * stats.norm.pdf(y) * stats.norm.sf(y + n))
    return 2 * integrate.quad(dens, -np.inf, np.inf)[0]


@pytest.mark.parametrize("window, n", [(7, 3.0), (7, 3.5), (15, 3.0)])
def test_hampel_false_alarms_on_gaussian_noise(window, n):
    rng = np.random.default_rng(3)
    x = 2.5 * rng.standard_normal(400_000)
    out = remove_outliers(x, window=window, n_sigmas=n)
    expected = _false_alarm_rate(window, n)  # 0.41 %, 0.090 %, 0.34 %
    # ≥ 360 expected alarms (±5 % Poisson); σ̂ from 1000-sample blocks adds a few %: ±20 %
    assert out.count / x.size == pytest.approx(expected, rel=0.2)
    # and the threshold means about what it says: within 2.5× of 2Φ̄(n) (the distance to
    # a 7-sample median is a little wider than to a known mean); the classical rule with
    # σ from the same 7 samples' MAD flagged ~4.7 % at 3σ, 17×
    assert out.count / x.size < 2.5 * 2 * stats.norm.sf(n)


def test_hampel_skips_nan():
    rng = np.random.default_rng(4)
    x = 0.1 * rng.standard_normal(300)
    x[[2, 7, 8, 9, 150]] = np.nan
    x[4] = 9.0  # 90 σ, next to a NaN
    out = remove_outliers(x, window=5, n_sigmas=5.0)  # 5σ: no false alarm expected
    assert np.flatnonzero(out.mask).tolist() == [4]
    assert np.isnan(out.cleaned[[2, 4, 7, 150]]).all() and out.count == 1
    assert out.filled[4] == pytest.approx(np.nanmedian(x[2:7]))  # NaN skipped in the median
    # σ̂ from the finite differences only (one block; ±15 % for ~290 differences)
    np.testing.assert_allclose(out.scale, 0.1, rtol=0.15)
    assert remove_outliers(np.full(20, np.nan)).count == 0


def test_label_orientations():
    g = np.array([[0, 0, 1.0], [0, 0, -9.81], [0.1, 0.99, 0], [-1, 0.05, 0.0],
                  [0.7, 0.7, 0.0], [0, 0, 0]])
    labels = label_orientations(g, tolerance_deg=10.0)
    names = [ORIENTATIONS[k] if k >= 0 else None for k in labels]
    assert names == ["+z", "-z", "+y", "-x", None, None]


def test_orientation_offsets_and_drift_recovered():
    rng = np.random.default_rng(2)
    n = 6000
    T = np.linspace(-40, 85, n)
    orient = np.tile(np.repeat(np.arange(6), 50), n // 300)  # table cycles all six
    offsets = np.array([3.0, -3.0, 1.5, -1.5, 0.4, -0.4])    # deg/h, mean zero
    coefficients = np.array([0.7, 0.02, -3e-4, 2e-6])         # drift in (T − 25)
    noise = 0.05
    bias = (offsets[orient] + np.polynomial.polynomial.polyval(T - 25, coefficients)
            + noise * rng.standard_normal(n))
    labels = orient.copy()
    labels[::97] = -1  # some samples while the table moves
    bias[5] = np.nan
    sep = separate_orientation_bias(T, bias, labels, order=3)
    assert sep.orientations == (0, 1, 2, 3, 4, 5)
    # within 4 reported standard deviations (the truth is known exactly)
    assert np.all(np.abs(sep.offsets - offsets) < 4 * sep.offset_std)
    assert np.all(np.abs(sep.coefficients - coefficients) < 4 * sep.coefficient_std)
    assert sep.residual_rms == pytest.approx(noise, rel=0.05)
    drift_truth = np.polynomial.polynomial.polyval(T - 25, coefficients)
    ok = np.isfinite(sep.drift)
    assert np.isnan(sep.drift[::97]).all() and np.isnan(sep.drift[5])
    assert np.sqrt(np.mean((sep.drift[ok] - drift_truth[ok]) ** 2)) == pytest.approx(noise, rel=0.05)


def test_orientation_bad_input():
    T = np.linspace(0, 50, 100)
    with pytest.raises(InputError, match=r"field 'gyro_x_dph'.*all NaN"):
        separate_orientation_bias(T, np.full(100, np.nan), np.zeros(100), name="gyro_x_dph")
    # each orientation at one temperature of its own: offset and drift are the same column
    labels = (T > 25).astype(int)
    with pytest.raises(InputError, match="cannot be told apart.*2 or more temperatures"):
        separate_orientation_bias(np.where(labels, 40.0, 10.0), T.copy(), labels, order=1)
