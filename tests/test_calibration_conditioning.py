"""Data conditioning: synchronizing two streams, the Hampel filter, and orientation
offsets told apart from thermal drift, each against data with a known truth."""

import numpy as np
import pytest
from scipy import signal

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
    np.testing.assert_array_equal(sync.temperature["T"], 20 + 0.01 * sync.ts)
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


def hampel_loop(x, half, n):
    """The Hampel rule written out sample by sample."""
    out = np.zeros(x.size, bool)
    padded = np.concatenate([[x[0]] * half, x, [x[-1]] * half])
    for i in range(x.size):
        w = padded[i:i + 2 * half + 1]
        med = np.median(w)
        out[i] = abs(x[i] - med) > n * 1.4826 * np.median(np.abs(w - med))
    return out


def test_hampel_matches_a_loop_and_finds_spikes():
    rng = np.random.default_rng(1)
    t = np.arange(3000) / 10.0
    x = np.sin(t / 20.0) + 0.01 * rng.standard_normal(t.size)
    spikes = rng.choice(np.arange(5, t.size - 5), 30, replace=False)
    x[spikes] += rng.choice([-1, 1], 30) * rng.uniform(0.5, 2.0, 30)  # ≥ 50 σ
    out = remove_outliers(x, window=7, n_sigmas=3.0, chunk=1000)  # several chunks
    np.testing.assert_array_equal(out.mask, hampel_loop(x, 3, 3.0))
    assert set(spikes) <= set(np.flatnonzero(out.mask))
    # Gaussian noise beyond 3σ: ~0.3 % false alarms expected (the MAD is noisier in 7 samples)
    assert out.count - 30 < 0.03 * t.size
    assert np.all(np.isnan(out.cleaned[spikes]))
    np.testing.assert_allclose(out.filled[spikes], np.sin(t[spikes] / 20.0), atol=0.05)


def test_hampel_skips_nan():
    x = np.array([0.0, 0.1, np.nan, -0.1, 9.0, 0.05, 0.0, np.nan, np.nan, np.nan, 0.1])
    out = remove_outliers(x, window=5)
    assert np.flatnonzero(out.mask).tolist() == [4]
    assert np.isnan(out.cleaned[[2, 4, 7]]).all() and out.count == 1


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
