"""Overlapping Allan deviation of a rate signal, and the noise terms read off it.

The deviation itself and its equivalent degrees of freedom come from `allantools`
(NIST SP 1065 eq. 11; Greenhall's EDF); this file chooses the averaging times, names the
noise type at each of them and reads angle random walk, bias instability and rate random
walk off the curve (IEEE Std 952, annex C).
"""

from __future__ import annotations

from dataclasses import dataclass

import allantools
import numpy as np

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
    - `ci`: confidence level of the interval, default one sigma (0.683).

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
    taus_used, adev, _, n_terms = allantools.oadev(y, rate=fs, data_type="freq",
                                                   taus=np.asarray(taus, dtype=float))
    if taus_used.size == 0:
        raise InputError(f"no averaging time fits in {y.size} samples at {fs:g} Hz.",
                         field="taus")
    ms = np.round(taus_used * fs).astype(int)
    if alpha is None:
        alphas = _noise_types(taus_used, adev, y.size // ms)
    else:
        alphas = np.full(taus_used.shape, int(alpha))
    edf = np.array([_edf(int(a), int(m), y.size + 1) for a, m in zip(alphas, ms)])
    bounds = [allantools.confidence_interval(d, e, ci=ci) for d, e in zip(adev, edf)]
    lower, upper = (np.array(b, dtype=float) for b in zip(*bounds))
    return AllanDeviation(taus=taus_used, adev=adev, lower=lower, upper=upper, edf=edf,
                          alpha=alphas, n_terms=n_terms.astype(int), sample_rate_hz=fs, ci=ci)


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
    try:
        return float(allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n_phase,
                                              overlapping=True, modified=False))
    except NotImplementedError:
        return float(allantools.edf_simple(n_phase, m, alpha))


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
