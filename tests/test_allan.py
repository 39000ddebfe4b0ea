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


# --- against allantools: an independent implementation (a dev dependency only) ---------

def _noise(alpha, n, rng):
    """Power-law rate noise S_y ∝ f^α: white phase (2), flicker phase (1), white rate (0),
    flicker rate (−1), random walk of rate (−2), by shaping white noise in frequency."""
    f = np.fft.rfftfreq(n)
    f[0] = f[1]
    spec = np.fft.rfft(rng.standard_normal(n)) * f ** (alpha / 2.0)
    return np.fft.irfft(spec, n) + 5.0  # an offset too: σ must not see it


@pytest.mark.parametrize("alpha", [2, 1, 0, -1, -2])
@pytest.mark.parametrize("n", [9, 57, 1000, 20_000])
def test_against_allantools(alpha, n):
    allantools = pytest.importorskip("allantools")
    fs, ci = 8.0, 0.9
    y = _noise(alpha, n, np.random.default_rng(100 + n))
    taus = np.unique(np.r_[np.arange(0.6, 40), np.geomspace(1, n, 30)]) / fs
    a = allan_deviation(y, fs, taus=taus, alpha=alpha, ci=ci)
    t, dev, _, n_terms = allantools.oadev(y, rate=fs, data_type="freq", taus=taus)
    assert np.array_equal(a.taus, t) and np.array_equal(a.n_terms, n_terms)
    # same estimator; float64 roundoff of the cumulative phase only
    np.testing.assert_allclose(a.adev, dev, rtol=1e-12, atol=0)
    ms, n_phase = np.round(t * fs).astype(int), n + 1
    edf = []
    for m in ms:
        try:
            edf.append(allantools.edf_greenhall(alpha=alpha, d=2, m=int(m), N=n_phase,
                                                overlapping=True, modified=False))
        except NotImplementedError:  # white phase, r ≤ d: SP 1065's simple fit
            edf.append(allantools.edf_simple(n_phase, int(m), alpha))
    # same algorithm, same printed table constants; only the order of float64 sums differs
    np.testing.assert_allclose(a.edf, edf, rtol=1e-10, atol=0)
    bounds = np.array([allantools.confidence_interval(d, e, ci=ci) for d, e in zip(dev, edf)])
    # chi-squared quantiles from scipy on both sides; roundoff only
    np.testing.assert_allclose(a.lower, bounds[:, 0], rtol=1e-10, atol=0)
    np.testing.assert_allclose(a.upper, bounds[:, 1], rtol=1e-10, atol=0)


def test_edf_all_branches_against_allantools():
    """Every branch of Greenhall's algorithm (exact sum with F = m and F = ∞, table 2,
    the rescaled J_max sum, table 3 for flicker phase, the white-phase simple fit)."""
    allantools = pytest.importorskip("allantools")
    from thermojax.calibration._allan import _edf
    for n in (9, 20, 101, 250, 1000, 5000, 100_000):
        for alpha in (2, 1, 0, -1, -2):
            for m in (1, 2, 3, 5, 8, 16, 33, 34, 40, 64, 100, 128, 500, 1000, 4000, 20_000):
                if 2 * m > n - 1:
                    continue
                try:
                    ref = allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n + 1,
                                                   overlapping=True, modified=False)
                except NotImplementedError:
                    ref = allantools.edf_simple(n + 1, m, alpha)
                # same algorithm; float64 summation order only (measured ≤ 3e-14)
                assert _edf(alpha, m, n + 1) == pytest.approx(ref, rel=1e-10), (n, alpha, m)


def test_greenhall_tables_from_their_integrals():
    """The printed table constants are the three-digit roundings of integrals of sz."""
    from scipy import integrate

    from thermojax.calibration._allan import _GREENHALL_TABLE2, _GREENHALL_TABLE3, _sz
    knots = np.arange(-3.0, 4.0)
    for alpha in (0, -1, -2):
        def g(t, p=0):
            return np.abs(t) ** p * (_sz(t, np.inf, alpha) / _sz(0.0, np.inf, alpha)) ** 2
        a0 = sum(integrate.quad(g, lo, hi)[0] for lo, hi in zip(knots[:-1], knots[1:]))
        a1 = sum(integrate.quad(g, lo, hi, args=(1,))[0] for lo, hi in zip(knots[:-1], knots[1:]))
        # table printed to three significant digits
        np.testing.assert_allclose(_GREENHALL_TABLE2[alpha], (a0, a1), rtol=1.5e-3)
    # flicker phase: sz(0; m) = b0 + b1 ln m up to O(1/m²); b0 = 18 − 4 ln 2 printed 15.23
    b0, b1 = _GREENHALL_TABLE3
    for m in (100, 1000):
        assert float(_sz(0.0, m, 1)) == pytest.approx(b0 + b1 * np.log(m), rel=1e-4)


def test_bad_alpha_and_ci():
    y = np.random.default_rng(6).standard_normal(100)
    with pytest.raises(InputError, match="noise type alpha"):
        allan_deviation(y, 1.0, alpha=-3)
    with pytest.raises(InputError, match="confidence level"):
        allan_deviation(y, 1.0, ci=1.0)


def test_runtime_requirements_free_of_test_and_doc_tools():
    """`pip install thermojax` brings no allantools, test or documentation tools (issue 32):
    they may appear only behind an extra."""
    import re
    from importlib.metadata import PackageNotFoundError, requires

    try:
        reqs = requires("thermojax") or []
    except PackageNotFoundError:
        pytest.skip("thermojax is not installed (pip install -e .)")
    runtime = {re.split(r"[\s<>=!~\[;(]", r, maxsplit=1)[0].lower()
               for r in reqs if "extra ==" not in r}
    assert runtime and not runtime & {"allantools", "pytest", "sphinx", "numpydoc"}
