"""Residual analysis: is what the model leaves behind white noise, and if not, what does
it follow? Pure NumPy/SciPy on residual sequences, one array per run.

Runs are pooled by summing per-run autocovariances (each run about its own mean):
a lag never straddles two runs.
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np


def _finite_segments(r: np.ndarray) -> np.ndarray:
    """A run's residual with dropped samples replaced by zero after centring (they then
    add nothing to any lagged product)."""
    r = np.asarray(r, float)
    ok = np.isfinite(r)
    out = np.zeros_like(r)
    if ok.any():
        out[ok] = r[ok] - r[ok].mean()
    return out


def pooled_autocorrelation(runs: list[np.ndarray], max_lag: int) -> tuple[np.ndarray, int]:
    """Autocorrelation at lags 1..max_lag pooled over runs, and the number of samples."""
    num = np.zeros(max_lag)
    den = 0.0
    n_total = 0
    for r in runs:
        ok = np.isfinite(np.asarray(r, float))
        x = _finite_segments(r)
        den += float(x @ x)
        n_total += int(ok.sum())
        for k in range(1, max_lag + 1):
            if k < len(x):
                num[k - 1] += float(x[k:] @ x[:-k])
    return (num / den if den > 0 else np.zeros(max_lag)), n_total


def newey_west_lags(n: int) -> int:
    """The Newey-West (1994) rule-of-thumb truncation lag `⌊4 (n/100)^(2/9)⌋` for a
    sequence of `n` samples."""
    return int(math.floor(4.0 * (max(n, 1) / 100.0) ** (2.0 / 9.0)))


def default_lags(n: int) -> int:
    """The usual portmanteau lag count, min(20, n/5) but at least 1."""
    return max(1, min(20, n // 5))


def ljung_box(runs: list[np.ndarray], max_lag: int | None = None) -> tuple[float, float, int]:
    """Ljung-Box statistic `Q = N(N+2) Σ ρ_k²/(N-k)` over pooled runs; returns
    `(Q, p_value, lags)`, p from chi-square with `lags` degrees of freedom."""
    from scipy import stats  # where used: SciPy's stats and signal cost 0.6 s to import

    n = sum(int(np.isfinite(np.asarray(r, float)).sum()) for r in runs)
    lags = default_lags(n) if max_lag is None else int(max_lag)
    rho, n = pooled_autocorrelation(runs, lags)
    k = np.arange(1, lags + 1)
    q = float(n * (n + 2) * np.sum(rho ** 2 / np.maximum(n - k, 1)))
    return q, float(stats.chi2.sf(q, lags)), lags


def cross_correlation(residuals: list[np.ndarray], signals: list[np.ndarray], max_lag: int
                      ) -> tuple[np.ndarray, np.ndarray, float]:
    """Correlation of residual with a signal at lags -max_lag..max_lag, pooled over runs.

    Lag `k > 0` pairs the residual at `t` with the signal at `t - k` (the signal
    leads). Returns `(lags, ccf, band)` with `band = 1.96/sqrt(N)`, the 95 % band
    for white residuals independent of the signal.
    """
    from scipy import signal

    lags = np.arange(-max_lag, max_lag + 1)
    num = np.zeros(len(lags))
    rr = ss = 0.0
    n = 0
    for r, s in zip(residuals, signals):
        r = _finite_segments(r)
        s = np.asarray(s, float)
        s = s - s[np.isfinite(s)].mean() if np.isfinite(s).any() else np.zeros_like(s)
        s = np.where(np.isfinite(s), s, 0.0)
        rr += float(r @ r)
        ss += float(s @ s)
        n += len(r)
        # full[j] = Σ_t r[t] s[t - k] at k = j - (len(s) - 1), by FFT
        full = signal.correlate(r, s, mode="full", method="fft")
        within = np.abs(lags) < len(r)
        num[within] += full[lags[within] + len(s) - 1]
    denom = np.sqrt(rr * ss)
    return lags, (num / denom if denom > 0 else np.zeros(len(lags))), 1.96 / np.sqrt(max(n, 1))


def cumulated_periodogram(runs: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, float]:
    """Normalized cumulated periodogram of the pooled residual (Box-Jenkins).

    Each run contributes its periodogram ordinates at its own Fourier frequencies, scaled
    by its length (so that every ordinate of a white residual has the same mean); the
    ordinates of all runs are pooled in order of frequency. Returns `(frequency as a
    fraction of Nyquist, C, band)`, one entry per pooled ordinate: for white noise `C`
    follows the diagonal within `±band` (95 % Kolmogorov-Smirnov band).
    """
    freqs, powers = [], []
    for r in runs:
        x = _finite_segments(r)
        if len(x) >= 4:
            p = np.abs(np.fft.rfft(x)) ** 2 / len(x)
            freqs.append(2.0 * np.arange(1, len(p)) / len(x))
            powers.append(p[1:])
    f = np.concatenate(freqs)
    order = np.argsort(f, kind="stable")
    f, p = f[order], np.concatenate(powers)[order]
    m = len(f)
    c = np.cumsum(p) / np.sum(p) if np.sum(p) > 0 else np.arange(1, m + 1) / m
    return f, c, 1.36 / np.sqrt(max(m - 1, 1))


# ---------------------------------------------------------------------------
# Chamber phases found in the data (no profile needed)

PHASES = ("heating_ramp", "cooling_ramp", "dwell", "power_step")


@dataclass(frozen=True)
class PhaseLabels:
    """One label per sample: an index into `PHASES`."""

    labels: np.ndarray

    def mask(self, kind: str) -> np.ndarray:
        return self.labels == PHASES.index(kind)


def label_phases(ts: np.ndarray, temperature: np.ndarray | None, power: np.ndarray | None = None,
                 rate_threshold_c_per_min: float = 0.2, power_window_s: float = 600.0
                 ) -> PhaseLabels:
    """Label each sample heating ramp, cooling ramp, dwell, or power step.

    A ramp is where the chamber temperature moves faster than the threshold
    (°C/min); a power step labels `power_window_s` after each jump in power;
    everything else is a dwell.
    """
    ts = np.asarray(ts, float)
    labels = np.full(len(ts), PHASES.index("dwell"))
    if temperature is not None and len(ts) > 1:
        rate = np.gradient(np.asarray(temperature, float), ts) * 60.0
        labels[rate > rate_threshold_c_per_min] = PHASES.index("heating_ramp")
        labels[rate < -rate_threshold_c_per_min] = PHASES.index("cooling_ramp")
    if power is not None and len(ts) > 1:
        p = np.asarray(power, float)
        jumps = np.flatnonzero(np.abs(np.diff(p)) > 1e-6 * max(np.ptp(p), 1e-30) + 1e-12)
        for j in jumps:
            window = (ts >= ts[j]) & (ts < ts[j] + power_window_s)
            labels[window & (labels == PHASES.index("dwell"))] = PHASES.index("power_step")
    return PhaseLabels(labels)


def residuals_by_phase(residuals: list[np.ndarray], phases: list[PhaseLabels]) -> dict:
    """Mean, RMS and sample count of the residual per phase, pooled over runs, plus the
    heating-versus-cooling asymmetry (mean on heating ramps minus mean on cooling)."""
    out = {}
    for kind in PHASES:
        vals = np.concatenate([np.asarray(r, float)[ph.mask(kind)]
                               for r, ph in zip(residuals, phases)])
        vals = vals[np.isfinite(vals)]
        out[kind] = {"n": int(vals.size),
                     "mean": float(vals.mean()) if vals.size else None,
                     "rms": float(np.sqrt(np.mean(vals ** 2))) if vals.size else None}
    h, c = out["heating_ramp"]["mean"], out["cooling_ramp"]["mean"]
    out["heating_minus_cooling"] = None if h is None or c is None else h - c
    return out


def long_run_variance_ratio(runs: list[np.ndarray], bandwidth: int | None = None) -> float:
    """Long-run variance over variance of a residual sequence (Newey-West, Bartlett kernel),
    runs pooled: `1 + 2 Σ_{k≤L} (1 − k/(L+1)) ρ_k`, at least 1.

    A χ² statistic built from autocorrelated residuals is too large by about this factor
    (the effective sample is smaller than the sample count); dividing by it deflates it.
    `bandwidth` L defaults to `newey_west_lags(N)`, at least 1."""
    n = sum(int(np.isfinite(np.asarray(r, float)).sum()) for r in runs)
    if n < 3:
        return 1.0
    lag = max(1, newey_west_lags(n)) if bandwidth is None else int(bandwidth)
    rho, _ = pooled_autocorrelation(runs, lag)
    k = np.arange(1, lag + 1)
    ratio = 1.0 + 2.0 * float(np.sum((1.0 - k / (lag + 1.0)) * rho))
    return float(max(ratio, 1.0)) if np.isfinite(ratio) else 1.0
