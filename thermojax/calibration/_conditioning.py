"""Data conditioning, the first calibration stage: two logged streams onto one time base,
outliers removed by a stated rule, and g-dependent bias told apart from thermal drift.

The order on a raw run: `remove_outliers` on each inertial channel (fill with
`.filled`), then `synchronize`, then `separate_orientation_bias` where the rate table
moved the unit through orientations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy import signal

from .._errors import InputError


# ---------------------------------------------------------------------------
# Two streams, one time base


@dataclass(frozen=True)
class Synchronized:
    """Both streams on the common times `ts` (s, `(times,)`): `temperature` and
    `inertial` (name -> `(times,)`), and what was done: `cutoff_hz` of the zero-phase
    low-pass applied to the inertial stream (None where the new rate is not lower),
    `matched` (True where the temperature stream went through the same low-pass) and
    `noise_factor`: `1/sqrt(2·B·dt)`, `B` (Hz) the filtered noise's equivalent bandwidth,
    by which a std computed as if the decimated noise were white understates the true
    one for a slowly varying regressor (1 without a low-pass)."""

    ts: np.ndarray
    temperature: dict[str, np.ndarray]
    inertial: dict[str, np.ndarray]
    cutoff_hz: float | None
    matched: bool = False
    noise_factor: float = 1.0


def _check_stream(name: str, ts, channels) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    ts = np.asarray(ts, dtype=float)
    if ts.ndim != 1 or ts.size < 2:
        raise InputError(f"the {name} stream needs at least two samples, got {ts.size}.",
                         field="time_s")
    bad = np.flatnonzero(~np.isfinite(ts))
    if bad.size:
        raise InputError(f"the {name} stream has a non-finite time at row {bad[0]} (0-based).",
                         field="time_s")
    back = np.flatnonzero(np.diff(ts) <= 0)
    if back.size:
        k = int(back[0]) + 1
        raise InputError(f"the {name} stream's timestamps go backwards (or repeat) at row {k} "
                         f"(0-based): {ts[k]:.9g} s after {ts[k - 1]:.9g} s. Timestamps must "
                         "increase strictly; sort the log or split it where the clock was reset.",
                         field="time_s")
    out = {}
    for key, v in channels.items():
        v = np.asarray(v, dtype=float)
        if v.shape != ts.shape:
            raise InputError(f"the {name} channel has {v.size} samples but the stream has "
                             f"{ts.size} timestamps.", field=key)
        out[key] = v
    if not out:
        raise InputError(f"the {name} stream has no channels.")
    return ts, out


def _zoh_means(t, v, ts) -> np.ndarray:
    """Mean of the zero-order-hold interpolant of `(t, v)` over `[ts_k, ts_{k+1})` (the
    last interval as long as the one before; the last sample held beyond `t[-1]`)."""
    c = np.concatenate([[0.0], np.cumsum(v[:-1] * np.diff(t))])

    def integral(tau):
        k = np.clip(np.searchsorted(t, tau, side="right") - 1, 0, t.size - 1)
        return c[k] + v[k] * (tau - t[k])

    step = np.diff(ts)
    ends = ts + np.concatenate([step, step[-1:]])
    return (integral(ends) - integral(ts)) / (ends - ts)


def _lowpass(sos, t, v) -> np.ndarray:
    """`sosfiltfilt` of one channel; NaN gaps are bridged linearly for the filter and
    put back (NaN) afterwards."""
    bad = ~np.isfinite(v)
    if bad.all():
        return v
    filled = np.interp(t, t[~bad], v[~bad]) if bad.any() else v
    out = signal.sosfiltfilt(sos, filled, padlen=min(3 * (2 * len(sos) + 1), t.size - 1))
    return np.where(bad, np.nan, out)


def synchronize(temperature_ts, temperature: dict, inertial_ts, inertial: dict, ts=None, *,
                cutoff_fraction: float = 0.8, filter_order: int = 4, holds: dict | None = None,
                matched: bool = True) -> Synchronized:
    """Temperature and inertial streams, logged at their own rates and times, on one time base.

    The inertial channels (sampled at `fs_in`, taken as uniform at the median step) are
    low-passed with a zero-phase Butterworth (`scipy.signal.sosfiltfilt`, order
    `2·filter_order` in effect) whose cutoff is `cutoff_fraction` of the new Nyquist
    `1/(2·dt_new)`, then interpolated linearly onto the common times.

    With `matched` (default) the temperature channels go through the same low-pass (a
    Butterworth of that order and cutoff at their own rate, where that rate allows).
    A model fitted to the result then sees filtered inputs, filtered sensors and a
    filtered bias: for a linear model the filter commutes with the dynamics, so input,
    states and bias stay consistent. Filtering the bias alone, or decimating the inputs
    by picking samples, does not: fast input content (a chamber step, a power switch)
    is then misplaced by up to one new sample period, and a gradient or rate
    coefficient absorbs it.

    Each temperature channel is then taken onto `ts` according to its `holds` entry:
    `"foh"` (default) the value at `ts_k` (linear interpolation); `"zoh"` the mean over
    `[ts_k, ts_{k+1})` of the log's zero-order-hold signal, which is what a model
    holding `u_k` over that interval must be given to deliver the same energy with no
    half-sample lag. Only the span where both streams have samples is kept.

    **Arguments:**

    - `temperature_ts`, `inertial_ts`: `(n_T,)`, `(n_I,)` timestamps, s, strictly increasing.
    - `temperature`, `inertial`: name -> samples of the same length as the stream's times
      (°C, W; deg/h or µg). Inertial channels must be finite (fill outliers first);
      temperature channels may have NaN gaps (kept NaN).
    - `ts`: the common times, s; default the temperature times inside the overlap.
    - `cutoff_fraction`: low-pass cutoff as a fraction of the new Nyquist frequency.
    - `filter_order`: Butterworth order (applied forward and backward).
    - `holds`: temperature channel -> `"zoh"` or `"foh"` (the model's hold of that input).
    - `matched`: also low-pass the temperature stream.

    **Returns:** a `Synchronized`.
    """
    t_temp, temperature = _check_stream("temperature", temperature_ts, temperature)
    t_in, inertial = _check_stream("inertial", inertial_ts, inertial)
    holds = dict(holds or {})
    for key, h in holds.items():
        if h not in ("zoh", "foh"):
            raise InputError(f"the hold of {key!r} must be 'zoh' or 'foh', got {h!r}.",
                             field="holds")
    for key, v in inertial.items():
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise InputError(f"the inertial stream has a non-finite sample at row {bad[0]} "
                             f"(0-based); fill it before filtering, e.g. with "
                             "`remove_outliers(...).filled`.", field=key)
    start, end = max(t_temp[0], t_in[0]), min(t_temp[-1], t_in[-1])
    if start >= end:
        raise InputError(f"the temperature stream ({t_temp[0]:g}…{t_temp[-1]:g} s) and the "
                         f"inertial stream ({t_in[0]:g}…{t_in[-1]:g} s) do not overlap in time; "
                         "check that both use the same clock and epoch.", field="time_s")
    ts = t_temp if ts is None else np.asarray(ts, dtype=float)
    ts = ts[(ts >= start) & (ts <= end)]
    if ts.size < 2:
        raise InputError(f"fewer than two common times fall in the overlap {start:g}…{end:g} s.",
                         field="ts")
    dt_new = float(np.median(np.diff(ts)))
    fs_in = 1.0 / float(np.median(np.diff(t_in)))
    fs_temp = 1.0 / float(np.median(np.diff(t_temp)))
    cutoff = cutoff_fraction * 0.5 / dt_new
    factor, did_match = 1.0, False
    if cutoff < 0.5 * fs_in:
        sos = signal.butter(filter_order, cutoff, btype="low", fs=fs_in, output="sos")
        inertial = {k: _lowpass(sos, t_in, v) for k, v in inertial.items()}
        # equivalent noise bandwidth of the zero-phase filter, |H|⁴ integrated
        f, h = signal.sosfreqz(sos, worN=8192, fs=fs_in)
        bandwidth = float(np.trapezoid(np.abs(h) ** 4, f))
        factor = max(1.0, 1.0 / math.sqrt(2.0 * bandwidth * dt_new))
        if matched and cutoff < 0.5 * fs_temp:
            sos_t = signal.butter(filter_order, cutoff, btype="low", fs=fs_temp, output="sos")
            temperature = {k: _lowpass(sos_t, t_temp, v) for k, v in temperature.items()}
            did_match = True
    else:
        cutoff = None
    out_temp = {}
    for k, v in temperature.items():
        if holds.get(k, "foh") != "zoh":
            out_temp[k] = np.interp(ts, t_temp, v)
            continue
        bad = ~np.isfinite(v)
        if bad.all():
            out_temp[k] = np.full(ts.shape, np.nan)
            continue
        filled = np.interp(t_temp, t_temp[~bad], v[~bad]) if bad.any() else v
        out_temp[k] = _zoh_means(t_temp, filled, ts)
        if bad.any():  # an interval touching a gap has no mean
            touch = np.maximum(np.interp(ts, t_temp, bad.astype(float)),
                               np.interp(ts + np.gradient(ts), t_temp, bad.astype(float)))
            out_temp[k][touch > 0] = np.nan
    return Synchronized(
        ts=ts, cutoff_hz=cutoff, temperature=out_temp,
        inertial={k: np.interp(ts, t_in, v) for k, v in inertial.items()},
        matched=did_match, noise_factor=factor)


# ---------------------------------------------------------------------------
# Outliers: the Hampel filter


@dataclass(frozen=True)
class Outliers:
    """What `remove_outliers` found: `cleaned` (NaN at outliers), `mask` (True at
    outliers), `median` (the rolling median) and `scale` (the robust noise std the
    threshold is a multiple of, the channel's unit), all `(samples,)`."""

    cleaned: np.ndarray
    mask: np.ndarray
    median: np.ndarray
    scale: np.ndarray

    @property
    def count(self) -> int:
        """How many samples were outliers."""
        return int(self.mask.sum())

    @property
    def filled(self) -> np.ndarray:
        """The samples with each outlier replaced by its rolling median (the classical
        Hampel output; NaN only where the whole window was NaN)."""
        return np.where(self.mask, self.median, self.cleaned)


#: 1 / (Φ⁻¹(3/4) √2): `median |x_j − x_{j−1}|` times this is σ for white Gaussian noise.
_DIFF_MAD_TO_STD = 1.482602218505602 / math.sqrt(2.0)


def noise_std(x, block: int = 1000) -> np.ndarray:
    """Robust white-noise std of a channel, per block of `block` samples:
    `σ̂ = 1.4826 · median_j |x_j − x_{j−1}| / √2` (successive differences: a slow signal
    drops out, a spike moves only two differences). Blocks are `len(x)/block` nearly
    equal runs; one with fewer than 10 finite differences gets the whole channel's.

    **Arguments:** `x`: `(samples,)`; `block`: samples per block (≥ 10).

    **Returns:** `(samples,)` σ̂ (x's unit; NaN where the channel has no two finite
    neighbours).
    """
    x = np.asarray(x, dtype=float)
    d = np.abs(np.diff(x))
    out = np.full(x.shape, np.nan)
    ok = np.isfinite(d)
    if not ok.any():
        return out
    whole = _DIFF_MAD_TO_STD * float(np.median(d[ok]))
    edges = np.linspace(0, x.size, max(1, int(round(x.size / block))) + 1).astype(int)
    for a, b in zip(edges[:-1], edges[1:]):
        di = d[a:min(b, d.size)]
        di = di[np.isfinite(di)]
        out[a:b] = _DIFF_MAD_TO_STD * float(np.median(di)) if di.size >= 10 else whole
    return out


def remove_outliers(x, window: int = 7, n_sigmas: float = 3.0, scale_window: int = 1000,
                    chunk: int = 65536) -> Outliers:
    """Hampel-type filter: a sample is an outlier when it lies more than `n_sigmas`
    noise standard deviations from the median of the `window` samples centred on it,

    `|x_i − med_i| > n_sigmas · σ̂_i`, `σ̂` from `noise_std(x, scale_window)`.

    The noise std comes from successive differences over `scale_window` samples, not
    from the MAD of the same short window: seven samples give a MAD so noisy that the
    classical rule flags ~5 % of plain Gaussian noise at "3σ". With σ̂ from 1000
    samples, white Gaussian noise is flagged at the rate the threshold implies for a
    distance to a `window`-sample median: `2 ∫ f(y) Φ̄(y + n) dy`, `f` the density of
    the upper median of the other `window − 1` samples (0.41 % at window 7 and 3σ;
    `2Φ̄(3)` = 0.27 % for a known mean). The noise must be white from sample to sample
    (a raw inertial stream); NaN samples are ignored; windows are shortened at the ends
    (edge samples repeated). Zero σ̂ (quantized, constant data) flags any sample off its
    median.

    **Arguments:**

    - `x`: `(samples,)` one channel, any unit.
    - `window`: odd number of samples in the median's window (default 7, half-width 3).
    - `n_sigmas`: threshold in noise standard deviations (default 3).
    - `scale_window`: samples per block of the noise-std estimate (default 1000).
    - `chunk`: samples per block of the rolling median (bounds the memory,
      `chunk·window` floats).

    **Returns:** an `Outliers`.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 1:
        raise InputError(f"remove_outliers takes one channel, got shape {x.shape}.", field="x")
    if window < 3 or window % 2 == 0:
        raise InputError(f"the Hampel window must be an odd number of samples ≥ 3, got {window}.",
                         field="window")
    if scale_window < 10:
        raise InputError(f"the noise-std block must be at least 10 samples, got {scale_window}.",
                         field="scale_window")
    half = window // 2
    padded = np.pad(x, half, mode="edge")
    median = np.full(x.shape, np.nan)
    for a in range(0, x.size, chunk):
        w = sliding_window_view(padded[a:a + min(chunk, x.size - a) + 2 * half], window)
        has = np.isfinite(w).any(axis=1)
        if has.any():
            median[a:a + w.shape[0]][has] = np.nanmedian(w[has], axis=1)
    scale = noise_std(x, scale_window)
    with np.errstate(invalid="ignore"):
        mask = np.abs(x - median) > n_sigmas * scale
    return Outliers(cleaned=np.where(mask, np.nan, x), mask=mask, median=median, scale=scale)


# ---------------------------------------------------------------------------
# Rate-table orientations: g-dependent bias versus thermal drift

#: The six axis-aligned rate-table positions, named by the body axis that points up
#: (the accelerometer reads +1 g along it).
ORIENTATIONS = ("+x", "-x", "+y", "-y", "+z", "-z")


def label_orientations(accel, tolerance_deg: float = 10.0) -> np.ndarray:
    """Rate-table orientation of each sample from the accelerometer's g vector.

    Each sample is given the axis-aligned orientation (`ORIENTATIONS`) whose up axis is
    within `tolerance_deg` of the measured g direction, and −1 otherwise (the table
    moving, or a position that is not axis-aligned).

    **Arguments:**

    - `accel`: `(samples, 3)` specific force along x, y, z, any unit (g, m/s², µg).
    - `tolerance_deg`: largest angle between g and an axis, degrees.

    **Returns:** `(samples,)` int: an index into `ORIENTATIONS`, or −1.
    """
    a = np.asarray(accel, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"the accelerometer samples must have shape (samples, 3), got {a.shape}.",
                         field="accel")
    norm = np.linalg.norm(a, axis=1)
    axis = np.argmax(np.abs(a), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.abs(a[np.arange(len(a)), axis]) / norm
    labels = 2 * axis + (a[np.arange(len(a)), axis] < 0)
    ok = np.isfinite(cosine) & (cosine >= np.cos(np.radians(tolerance_deg)))
    return np.where(ok, labels, -1)


@dataclass(frozen=True)
class OrientationSeparation:
    """g-dependent bias and thermal drift told apart.

    - `orientations`: the labels, one per entry of `offsets`.
    - `offsets`, `offset_std`: the g-dependent bias per orientation (bias unit), their
      mean being zero (the mean is part of the drift).
    - `coefficients`, `coefficient_std`: the drift polynomial in `(T − reference_c)`,
      ascending powers (bias unit / K^k).
    - `drift`: `(samples,)` the bias with its orientation's offset removed (NaN where the
      sample has no orientation or no bias).
    - `residual_rms`: of the fit, bias unit.
    """

    orientations: tuple
    offsets: np.ndarray
    offset_std: np.ndarray
    coefficients: np.ndarray
    coefficient_std: np.ndarray
    reference_c: float
    drift: np.ndarray
    residual_rms: float


def separate_orientation_bias(temperature, bias, orientation, order: int = 3, *,
                              unlabelled=-1, reference_c: float = 25.0,
                              name: str = "bias") -> OrientationSeparation:
    """Per-orientation offsets (g-dependent bias) and one thermal drift, fitted together.

    Least squares on `bias_i = o_{orientation(i)} + Σ_{k=1..order} c_k (T_i − 25 °C)^k`
    (one indicator column per orientation, the polynomial shared); the offsets are then
    centred, `c_0 = mean(o)`, so that the drift carries the common level. Needs every
    orientation not to sit at a single temperature of its own (else offset and drift are
    the same column), which is checked.

    **Arguments:**

    - `temperature`: `(samples,)` °C.
    - `bias`: `(samples,)` the inertial output (deg/h, µg); NaN samples are skipped.
    - `orientation`: `(samples,)` labels (from `label_orientations` or the rate table's
      log); samples labelled `unlabelled` are skipped.
    - `order`: of the drift polynomial (≥ 1).
    - `name`: the bias column's name, for messages.

    **Returns:** an `OrientationSeparation`.
    """
    T = np.asarray(temperature, dtype=float)
    y = np.asarray(bias, dtype=float)
    lab = np.asarray(orientation)
    if not (T.shape == y.shape == lab.shape) or T.ndim != 1:
        raise InputError(f"temperature, bias and orientation must be equally long columns, got "
                         f"shapes {T.shape}, {y.shape}, {lab.shape}.", field=name)
    if not np.isfinite(y).any():
        raise InputError("the bias column is all NaN: there is nothing to calibrate.",
                         field=name)
    use = np.isfinite(y) & np.isfinite(T) & (lab != unlabelled)
    kinds = tuple(np.unique(lab[use]).tolist())
    if not kinds:
        raise InputError("no sample has both a bias and an orientation label.", field=name)
    dT = T[use] - reference_c
    indicators = (lab[use][:, None] == np.array(kinds)[None, :]).astype(float)
    powers = dT[:, None] ** np.arange(1, order + 1)[None, :]
    A = np.hstack([indicators, powers])
    scale = np.max(np.abs(A), axis=0)
    scale[scale == 0] = 1.0
    As = A / scale
    if np.linalg.matrix_rank(As) < A.shape[1]:
        raise InputError(f"the {len(kinds)} orientation offsets and an order-{order} drift "
                         "cannot be told apart from these samples: visit each orientation at "
                         f"{order + 1} or more temperatures (or lower the order).", field=name)
    beta_s, *_ = np.linalg.lstsq(As, y[use], rcond=None)
    beta = beta_s / scale
    resid = y[use] - A @ beta
    dof = max(use.sum() - A.shape[1], 1)
    cov = float(resid @ resid) / dof * np.linalg.inv(A.T @ A)
    # centre the offsets: o' = o − mean(o), c_0 = mean(o)
    n_o = len(kinds)
    M = np.zeros((n_o + order + 1, A.shape[1]))
    M[:n_o, :n_o] = np.eye(n_o) - 1.0 / n_o
    M[n_o, :n_o] = 1.0 / n_o
    M[n_o + 1:, n_o:] = np.eye(order)
    theta, cov = M @ beta, M @ cov @ M.T
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    offsets = np.full(T.shape, np.nan)
    for k, o in zip(kinds, theta[:n_o]):
        offsets[lab == k] = o
    return OrientationSeparation(
        orientations=kinds, offsets=theta[:n_o], offset_std=std[:n_o],
        coefficients=theta[n_o:], coefficient_std=std[n_o:], reference_c=reference_c,
        drift=np.where(lab != unlabelled, y - offsets, np.nan),
        residual_rms=float(np.sqrt(np.mean(resid ** 2))))
