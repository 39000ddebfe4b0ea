"""Overlapping Allan deviation: against a separately written NumPy estimator, and the
textbook curves of white rate noise and rate random walk."""

import numpy as np
import pytest

from thermojax._errors import InputError
from thermojax.calibration import allan_deviation, noise_parameters, plot_allan


def direct_oadev(y, m):
    """Overlapping ADEV from moving averages of the rate: σ² = Σ (ȳ_{k+m} − ȳ_k)² / (2 (N−2m+1))."""
    avg = np.array([y[k:k + m].mean() for k in range(len(y) - m + 1)])
    d = avg[m:] - avg[:-m]
    return np.sqrt(np.sum(d ** 2) / (2 * d.size))


def test_matches_direct_formula():
    y = np.random.default_rng(1).standard_normal(101) * 3.0 + 7.0
    fs = 4.0
    a = allan_deviation(y, fs, taus=np.arange(1, 40) / fs)
    expected = [direct_oadev(y, int(m)) for m in np.round(a.taus * fs)]
    assert a.taus.size == 39
    # same estimator; float64 roundoff of a cumulative sum over 100 samples only
    np.testing.assert_allclose(a.adev, expected, rtol=1e-12, atol=0)
    assert np.all(a.lower < a.adev) and np.all(a.adev < a.upper)


def test_white_rate_noise_gives_angle_random_walk():
    fs, sigma = 100.0, 2.0  # deg/h white rate noise, per sample
    y = sigma * np.random.default_rng(2).standard_normal(2 ** 18)
    a = allan_deviation(y, fs, ci=0.95)
    truth = sigma / np.sqrt(fs * a.taus)
    # each point inside its 95 % band (bands are per point; a few may miss by chance)
    inside = (a.lower <= truth) & (truth <= a.upper)
    assert inside.mean() >= 0.8
    slope = np.polyfit(np.log(a.taus[:10]), np.log(a.adev[:10]), 1)[0]
    assert abs(slope + 0.5) < 0.02  # textbook −1/2; 10 well-averaged octaves
    assert np.all(a.alpha[:10] == 0)  # named white rate noise
    p = noise_parameters(a, rate_unit="deg/h")
    n_true = sigma / np.sqrt(fs)  # deg/h·√s
    arw = p.angle_random_walk
    assert arw.lower <= n_true <= arw.upper
    assert abs(p.angle_random_walk_tau - 1.0) < 0.5  # read near τ = 1 s
    assert p.angle_random_walk_deg_per_sqrt_h.value == pytest.approx(arw.value / 60.0, rel=1e-12)
    assert p.rate_random_walk is None


def test_rate_random_walk_slope_and_coefficient():
    fs, K = 10.0, 0.3  # deg/h/√s
    y = np.cumsum(K * np.sqrt(1.0 / fs) * np.random.default_rng(3).standard_normal(2 ** 17))
    a = allan_deviation(y, fs, ci=0.95)
    mid = (a.taus >= 1.0) & (a.taus <= 200.0)
    slope = np.polyfit(np.log(a.taus[mid]), np.log(a.adev[mid]), 1)[0]
    assert abs(slope - 0.5) < 0.05  # textbook +1/2
    assert np.all(a.alpha[mid] == -2)
    p = noise_parameters(a)
    rrw = p.rate_random_walk
    assert rrw is not None and rrw.lower <= K <= rrw.upper  # σ(τ) = K √(τ/3)


def test_sinusoid_and_bias_instability_floor():
    # a sinusoid Ω0 sin(2π f0 t): σ(τ) = Ω0 sin²(π f0 τ)/(π f0 τ) (IEEE 952, C.6)
    fs, A, T0 = 10.0, 1.0, 200.0
    t = np.arange(2 ** 16) / fs
    taus = np.array([10.0, 40.0, 0.371 * T0, 150.0])
    a = allan_deviation(A * np.sin(2 * np.pi * t / T0), fs, taus=taus)
    x = np.pi * taus / T0
    # the formula averages over the phase; a finite record (327 periods) differs by ~0.5 %
    np.testing.assert_allclose(a.adev, A * np.sin(x) ** 2 / x, rtol=1e-2)
    y = 0.5 * np.random.default_rng(4).standard_normal(t.size) + A * np.sin(2 * np.pi * t / T0)
    b = allan_deviation(y, fs)
    p = noise_parameters(b)
    k = int(np.argmin(b.adev))
    assert p.bias_instability.value == pytest.approx(b.adev[k] / 0.664, rel=1e-12)
    assert p.bias_instability_tau == b.taus[k]


def test_bad_input():
    with pytest.raises(InputError, match=r"not finite \(the first is sample 3\)"):
        allan_deviation(np.array([0, 1, 2, np.nan, 4, 5, 6, 7, 8.0]), 1.0)
    with pytest.raises(InputError, match="positive number of Hz"):
        allan_deviation(np.zeros(100), 0.0)
    with pytest.raises(InputError, match="at least 8 samples"):
        allan_deviation(np.zeros(5), 1.0)


def test_plot(tmp_path):
    y = np.random.default_rng(5).standard_normal(4096)
    path = plot_allan(tmp_path / "adev.png", {"raw": allan_deviation(y, 10.0),
                                              "halved": allan_deviation(0.5 * y, 10.0)})
    from matplotlib.image import imread
    assert imread(path).shape[1] >= 1000
