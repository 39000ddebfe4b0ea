"""Overlapping Allan deviation of a rate signal, and the noise terms read off it.

Everything is computed here with NumPy and SciPy: the deviation (NIST SP 1065 eq. 11),
its equivalent degrees of freedom (Greenhall & Riley 2003, "Uncertainty of stability
variances based on finite differences", for the overlapping Allan variance; the simple
SP 1065 table 5 fit where that algorithm has no closed case) and the chi-squared interval
(SP 1065 §5.3). The tests check all three against `allantools`, an independent
implementation that is a development dependency only. This file also chooses the
averaging times, names the noise type at each of them and reads angle random walk, bias
instability and rate random walk off the curve (IEEE Std 952, annex C).
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np
from scipy import stats

from .._errors import InputError

#: Confidence level of the default intervals: one sigma, as Stable32 draws them.
ONE_SIGMA = 0.6826894921370859

#: `rate unit·√s` times this is `deg/√h` (the usual unit of angle random walk).
_TO_DEG_PER_SQRT_H = {"deg/h": 1.0 / 60.0, "deg/s": 60.0}


@dataclass(frozen=True)
class Estimate:
    """A value with its confidence interval `[lower, upper]` at the level `ci`."""

    value: float
    lower: float
    upper: float
    ci: float


@dataclass(frozen=True)
class AllanDeviation:
    """An overlapping Allan deviation curve with a confidence interval at every point.

    `taus` (s), `adev`, `lower`, `upper` (the rate unit), `edf` (equivalent degrees of
    freedom), `alpha` (the power-law noise type used for the EDF: 2 white phase
    (quantization), 0 white rate (angle random walk), −1 flicker (bias instability),
    −2 random walk of rate), `n_terms` (second differences averaged); all `(taus,)`.
    """

    taus: np.ndarray
    adev: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    edf: np.ndarray
    alpha: np.ndarray
    n_terms: np.ndarray
    sample_rate_hz: float
    ci: float


def allan_deviation(rate_samples, sample_rate_hz: float, taus=None, *, alpha: int | None = None,
                    ci: float = ONE_SIGMA) -> AllanDeviation:
    """Overlapping Allan deviation of uniformly sampled rate data.

    `σ²(τ) = 1/(2(N−2m+1)) Σ_k (ȳ_{k+m} − ȳ_k)²` with `τ = m/fs` and `ȳ_k` the mean of
    `m` samples starting at `k`. The interval at each `τ` is chi-squared with Greenhall's
    equivalent degrees of freedom for the noise type there.

    **Arguments:**

    - `rate_samples`: `(samples,)` rate in any unit (e.g. deg/h), finite, uniformly sampled.
    - `sample_rate_hz`: samples per second.
    - `taus`: averaging times, s (rounded to whole samples); default octaves `2^k/fs`
      up to a quarter of the record (Stable32's stop ratio for the overlapping ADEV).
    - `alpha`: the noise type for every EDF; default read from the local slope μ of
      `log σ² / log τ` at each point: `α = −μ − 1` rounded to −2…0, and 2 where the
      ADEV falls as `1/τ` (μ ≤ −1.5: quantization); points averaging fewer than 30
      independent stretches (`N/m < 30`) keep the type of the last point before them.
      Given, it must be one of 2, 1, 0, −1, −2.
    - `ci`: confidence level of the interval, between 0 and 1; default one sigma (0.683).

    **Returns:** an `AllanDeviation`.
    """
    y = np.asarray(rate_samples, dtype=float)
    fs = float(sample_rate_hz)
    if y.ndim != 1:
        raise InputError(f"the rate samples must be one column, got shape {y.shape}.",
                         field="rate_samples")
    if not np.isfinite(fs) or fs <= 0:
        raise InputError(f"the sample rate must be a positive number of Hz, got {sample_rate_hz!r}.",
                         field="sample_rate_hz")
    bad = np.flatnonzero(~np.isfinite(y))
    if bad.size:
        raise InputError(f"{bad.size} of {y.size} rate samples are not finite (the first is "
                         f"sample {bad[0]}); fill them before the Allan deviation, e.g. with "
                         "`remove_outliers(...).filled`.", field="rate_samples")
    if y.size < 8:
        raise InputError(f"the Allan deviation needs at least 8 samples, got {y.size}.",
                         field="rate_samples")
    if taus is None:
        m = 2 ** np.arange(int(np.log2(y.size / 4)) + 1)
        taus = m / fs
    if not 0.0 < ci < 1.0:
        raise InputError(f"the confidence level must lie between 0 and 1, got {ci!r}.",
                         field="ci")
    if alpha is not None and int(alpha) not in _GREENHALL_TABLE2:
        raise InputError(f"the noise type alpha must be one of 2, 1, 0, -1, -2 (the power-law "
                         f"types the overlapping Allan variance separates), got {alpha!r}.",
                         field="alpha")
    ms = _averaging_factors(np.asarray(taus, dtype=float), fs, y.size)
    taus_used = ms / fs
    adev, n_terms = _oadev(y, ms)
    if taus_used.size == 0:
        raise InputError(f"no averaging time fits in {y.size} samples at {fs:g} Hz.",
                         field="taus")
    if alpha is None:
        alphas = _noise_types(taus_used, adev, y.size // ms)
    else:
        alphas = np.full(taus_used.shape, int(alpha))
    edf = np.array([_edf(int(a), int(m), y.size + 1) for a, m in zip(alphas, ms)])
    lower, upper = _chi2_interval(adev, edf, ci)
    return AllanDeviation(taus=taus_used, adev=adev, lower=lower, upper=upper, edf=edf,
                          alpha=alphas, n_terms=n_terms, sample_rate_hz=fs, ci=ci)


def _averaging_factors(taus, fs: float, n_freq: int) -> np.ndarray:
    """The averaging factors `m = round(τ·fs)` that fit the record, sorted and unique: at
    least one sample, and at least two second differences (`N − 2m ≥ 2` over the
    `N = n_freq + 1` phase points)."""
    m = np.unique(np.round(np.atleast_1d(taus) * fs))
    m = m[(m >= 1) & (2 * m <= n_freq - 1)]
    return m.astype(int)


def _oadev(y, ms) -> tuple[np.ndarray, np.ndarray]:
    """Overlapping Allan deviation at the factors `ms` (NIST SP 1065 eq. 11), and the
    number of second differences averaged at each.

    With the phase `x_0 = 0, x_k = Σ_{j<k} (y_j − ȳ)` in sample periods (the mean removed
    first: it does not change σ, and it keeps the cumulative sum small),
    `σ²(m) = Σ_i (x_{i+2m} − 2x_{i+m} + x_i)² / (2 m² (N − 2m))` over the `N` phase points.
    """
    x = np.concatenate([[0.0], np.cumsum(y - y.mean())])
    adev = np.empty(ms.shape)
    for k, m in enumerate(ms):
        d2 = x[2 * m:] - 2.0 * x[m:x.size - m] + x[:x.size - 2 * m]
        adev[k] = np.sqrt(np.dot(d2, d2) / (2.0 * d2.size)) / m
    return adev, x.size - 2 * ms


def _chi2_interval(dev, edf, ci: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided interval at level `ci` for a deviation with `edf` degrees of freedom:
    `edf·σ̂²/σ²` is chi-squared, so `σ ∈ σ̂·√(edf / χ²_{edf}(1 − p, p))`, `p = (1 − ci)/2`
    (NIST SP 1065 eq. 33)."""
    p = 0.5 * (1.0 - ci)
    lower = dev * np.sqrt(edf / stats.chi2.isf(p, edf))
    upper = dev * np.sqrt(edf / stats.chi2.ppf(p, edf))
    return lower, upper


def _local_slopes(taus, adev) -> np.ndarray:
    """d log σ / d log τ at each point (central differences; one-sided at the ends)."""
    if taus.size < 2:
        return np.full(taus.shape, -0.5)
    return np.gradient(np.log(adev), np.log(taus))


def _noise_types(taus, adev, n_averages) -> np.ndarray:
    """The power-law noise type α at each point from the local slope of the curve, read
    where at least 30 averages enter the point (longer τ keep the last type so read: the
    curve is too noisy there to name a type)."""
    ok = n_averages >= 30
    if ok.sum() < 2:
        return np.zeros(taus.shape, dtype=int)
    mu = 2.0 * _local_slopes(taus[ok], adev[ok])
    alpha = np.where(mu <= -1.5, 2, np.clip(np.round(-mu - 1.0), -2, 0)).astype(int)
    return np.concatenate([alpha, np.full(int((~ok).sum()), alpha[-1])])


def _edf(alpha: int, m: int, n_phase: int) -> float:
    """Greenhall's EDF of the overlapping ADEV; the simple (SP 1065 table 5) one where
    Greenhall's has no closed case (white phase at the longest averaging times)."""
    edf = _edf_greenhall(alpha, m, n_phase)
    return _edf_simple_white_phase(m, n_phase) if edf is None else edf


#: Greenhall & Riley (2003), table 2, column d = 2 (unmodified variances): `(a0, a1)` of
#: `1/edf ≈ (a0 − a1/r)/r` for long records, `r = M/S`. For α ≤ 0 these are, to the three
#: digits printed, `∫ sz²(t) dt / sz(0)²` and `∫ |t| sz²(t) dt / sz(0)²` over
#: `|t| ≤ d + 1` with `F = ∞` (the tests check that); for α = 1 the same integrals of the
#: `m → ∞` shape of `sz` without the `sz(0)²` (table 3 gives that); α = 2 is
#: `C(4d, 2d)/C(2d, d)²`, `d/2`.
_GREENHALL_TABLE2 = {2: (35.0 / 18.0, 1.0), 1: (790.0, 410.0), 0: (2.0 / 3.0, 1.0 / 3.0),
                     -1: (0.852, 0.375), -2: (1.079, 0.368)}

#: Greenhall & Riley (2003), table 3, d = 2: `sz(0; m, α = 1) ≈ b0 + b1 ln m` for flicker
#: phase noise. With our `sw` this is `12 ln m + 18 − 4 ln 2` (= 15.227…; printed 15.23).
_GREENHALL_TABLE3 = (15.23, 12.0)

#: The algorithm's cutoff: sums longer than this many terms use the asymptotic forms.
_J_MAX = 100


def _sw(t: np.ndarray, alpha: int) -> np.ndarray:
    """Greenhall's `sw(t)` for the power law `α`, up to a factor that cancels in the EDF:
    `|t|^(3−α)` for even `α`, `t^(3−α) ln|t|` (0 at `t = 0`) for odd `α`."""
    t = np.abs(np.asarray(t, dtype=float))
    if alpha % 2 == 0:
        return t ** (3 - alpha)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(t == 0.0, 0.0, t ** (3 - alpha) * np.log(t))


def _sz(t, f: float, alpha: int, d: int = 2) -> np.ndarray:
    """Greenhall's `sz(t; F, α, d)`: the `d`-th order difference filter (binomial weights,
    unit steps in `t`) applied to `sx`, where `sx` is `F²` times minus the second difference
    of `sw` at step `1/F` (finite `F`, the unmodified variances have `F = m`), or `sw` of
    `α + 2` when `F = ∞`."""
    t = np.asarray(t, dtype=float)

    def sx(u):
        if np.isinf(f):
            return _sw(u, alpha + 2)
        return f * f * (2.0 * _sw(u, alpha) - _sw(u - 1.0 / f, alpha) - _sw(u + 1.0 / f, alpha))

    return sum((-1) ** abs(k) * comb(2 * d, d + k) * sx(t + k) for k in range(-d, d + 1))


def _basic_sum(j: int, big_m: float, s: float, f: float, alpha: int, d: int = 2) -> float:
    """Greenhall's `BasicSum(J, M, S, F, α, d) = sz²(0) + (1 − J/M) sz²(J/S)
    + 2 Σ_{j=1}^{J−1} (1 − j/M) sz²(j/S)`."""
    lags = np.arange(1, int(j))
    total = _sz(0.0, f, alpha, d) ** 2 + (1.0 - j / big_m) * _sz(j / s, f, alpha, d) ** 2
    return float(total + 2.0 * np.sum((1.0 - lags / big_m) * _sz(lags / s, f, alpha, d) ** 2))


def _edf_greenhall(alpha: int, m: int, n_phase: int) -> float | None:
    """EDF of the overlapping Allan variance (`d = 2`, unmodified: `F = m`, stride
    `S = m`) by Greenhall & Riley (2003), from `n_phase` phase points; None for white
    phase noise when `r = M/S` is at most `d` (the case the simple fit covers here).

    The filter spans `L = m/F + m d` phase points, so `M = 1 + ⌊S (N − L)/m⌋` terms are
    averaged; their correlations reach `J = min(M, (d + 1) S)` lags. Short sums are done
    exactly (`BasicSum`); long ones use table 2 when `r > d + 1`, else `J_max` terms at
    the stride `J_max/r` with `F = ∞`. For α ≤ 0 a short sum with `m (d + 1) > J_max` also
    uses `F = ∞`. Flicker phase (α = 1) keeps a finite `F` (`m`, or `J_max/r` for the
    rescaled sum) and, in the long cases, normalizes by table 3's `sz(0) ≈ b0 + b1 ln m`.
    """
    d = 2
    f = s = float(m)
    big_l = m / f + m * d
    big_m = 1.0 + np.floor(s * (n_phase - big_l) / m)
    j = min(big_m, (d + 1) * s)
    r = big_m / s
    if alpha == 2:
        if np.ceil(r) <= d:
            return None
        a0, a1 = _GREENHALL_TABLE2[2]
        return 1.0 / ((a0 - a1 / r) / big_m)
    if j <= _J_MAX:
        f_used = f if (alpha == 1 or m * (d + 1) <= _J_MAX) else np.inf
        inv = _basic_sum(int(j), big_m, s, f_used, alpha, d) / (big_m * _sz(0.0, f_used, alpha, d) ** 2)
    elif alpha == 1:  # Greenhall's case 3: sz(0) grows as ln m, table 3 gives it
        sz0 = _GREENHALL_TABLE3[0] + _GREENHALL_TABLE3[1] * np.log(m)
        if r > d + 1:
            a0, a1 = _GREENHALL_TABLE2[1]
            inv = (a0 - a1 / r) / (sz0 ** 2 * r)
        else:
            m_prime = _J_MAX / r
            inv = _basic_sum(_J_MAX, _J_MAX, m_prime, m_prime, alpha, d) / (sz0 ** 2 * _J_MAX)
    elif r > d + 1:
        a0, a1 = _GREENHALL_TABLE2[alpha]
        inv = (a0 - a1 / r) / r
    else:
        inv = (_basic_sum(_J_MAX, _J_MAX, _J_MAX / r, np.inf, alpha, d)
               / (_J_MAX * _sz(0.0, np.inf, alpha, d) ** 2))
    return float(1.0 / inv)


def _edf_simple_white_phase(m: int, n_phase: int) -> float:
    """NIST SP 1065 table 5, overlapping ADEV, white phase noise (α = 2):
    `edf = (N + 1)(N − 2m) / (2 (N − m))` from `N` phase points."""
    n = float(n_phase)
    return (n + 1.0) * (n - 2.0 * m) / (2.0 * (n - m))


@dataclass(frozen=True)
class NoiseParameters:
    """Noise terms read off an Allan deviation curve, each with its interval.

    - `angle_random_walk`: `N`, rate unit·√s (the slope −1/2 line at τ = 1 s), read at
      `angle_random_walk_tau`; `angle_random_walk_deg_per_sqrt_h`: the same in deg/√h
      when the rate unit is deg/h or deg/s, else None.
    - `bias_instability`: `B = min σ / 0.664`, rate unit, at `bias_instability_tau`
      (if that is the longest τ the curve has not turned up: `B` is an upper bound).
    - `rate_random_walk`: `K`, rate unit/√s (the slope +1/2 line at τ = 3 s), or None
      where no part of the curve rises as √τ.
    """

    rate_unit: str
    angle_random_walk: Estimate | None
    angle_random_walk_tau: float | None
    angle_random_walk_deg_per_sqrt_h: Estimate | None
    bias_instability: Estimate
    bias_instability_tau: float
    rate_random_walk: Estimate | None
    rate_random_walk_tau: float | None


def noise_parameters(allan: AllanDeviation, rate_unit: str = "deg/h",
                     slope_tolerance: float = 0.1) -> NoiseParameters:
    """Angle random walk, bias instability and rate random walk read off `allan`.

    Each term is read at one point of the curve, so that its interval is that point's:
    `N = σ(τ)·√τ` at the point closest to τ = 1 s among those where the local slope is
    −1/2 (within `slope_tolerance`); `B = σ_min / 0.664` (flicker floor, IEEE 952);
    `K = σ(τ)·√(3/τ)` at the point closest to τ = 3 s among those with slope +1/2.

    **Arguments:**

    - `allan`: the curve from `allan_deviation`.
    - `rate_unit`: the unit of the rate samples, e.g. "deg/h" (converts ARW to deg/√h).
    - `slope_tolerance`: how far a local slope may be from ∓1/2 to count.

    A term read where another noise still contributes is biased high; its interval
    covers the statistical scatter of that one point only.

    **Returns:** a `NoiseParameters`.
    """
    taus, slopes = allan.taus, _local_slopes(allan.taus, allan.adev)

    def read(target_slope, target_tau, scale):
        idx = np.flatnonzero(np.abs(slopes - target_slope) <= slope_tolerance)
        if idx.size == 0:
            return None, None
        k = idx[np.argmin(np.abs(np.log(taus[idx] / target_tau)))]
        s = scale(taus[k])
        return Estimate(allan.adev[k] * s, allan.lower[k] * s, allan.upper[k] * s,
                        allan.ci), float(taus[k])

    arw, arw_tau = read(-0.5, 1.0, np.sqrt)
    rrw, rrw_tau = read(0.5, 3.0, lambda t: np.sqrt(3.0 / t))
    k = int(np.argmin(allan.adev))
    bi = Estimate(allan.adev[k] / 0.664, allan.lower[k] / 0.664, allan.upper[k] / 0.664,
                  allan.ci)
    factor = _TO_DEG_PER_SQRT_H.get(rate_unit)
    arw_deg = (None if arw is None or factor is None else
               Estimate(arw.value * factor, arw.lower * factor, arw.upper * factor, arw.ci))
    return NoiseParameters(rate_unit=rate_unit, angle_random_walk=arw,
                           angle_random_walk_tau=arw_tau,
                           angle_random_walk_deg_per_sqrt_h=arw_deg, bias_instability=bi,
                           bias_instability_tau=float(taus[k]), rate_random_walk=rrw,
                           rate_random_walk_tau=rrw_tau)
