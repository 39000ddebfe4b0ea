"""Data conditioning, the first calibration stage: two logged streams onto one time base,
outliers removed by a stated rule, and g-dependent bias told apart from thermal drift.

The order on a raw run: `remove_outliers` on each inertial channel (fill with
`.filled`), then `synchronize`, then `separate_orientation_bias` where the rate table
moved the unit through orientations.
"""

from __future__ import annotations

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
    low-pass applied to the inertial stream (None where the new rate is not lower)."""

    ts: np.ndarray
    temperature: dict[str, np.ndarray]
    inertial: dict[str, np.ndarray]
    cutoff_hz: float | None


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


def synchronize(temperature_ts, temperature: dict, inertial_ts, inertial: dict, ts=None, *,
                cutoff_fraction: float = 0.8, filter_order: int = 4) -> Synchronized:
    """Temperature and inertial streams, logged at their own rates and times, on one time base.

    The inertial channels (sampled at `fs_in`, taken as uniform at the median step) are
    low-passed with a zero-phase Butterworth (`scipy.signal.sosfiltfilt`, order
    `2·filter_order` in effect) whose cutoff is `cutoff_fraction` of the new Nyquist
    `1/(2·dt_new)`, then interpolated linearly onto the common times; the temperature
    channels are interpolated linearly (they are already on `ts` by default). Only the
    span where both streams have samples is kept.

    **Arguments:**

    - `temperature_ts`, `inertial_ts`: `(n_T,)`, `(n_I,)` timestamps, s, strictly increasing.
    - `temperature`, `inertial`: name -> samples of the same length as the stream's times
      (°C; deg/h or µg). Inertial channels must be finite (fill outliers first).
    - `ts`: the common times, s; default the temperature times inside the overlap.
    - `cutoff_fraction`: low-pass cutoff as a fraction of the new Nyquist frequency.
    - `filter_order`: Butterworth order (applied forward and backward).

    **Returns:** a `Synchronized`.
    """
    t_temp, temperature = _check_stream("temperature", temperature_ts, temperature)
    t_in, inertial = _check_stream("inertial", inertial_ts, inertial)
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
    new_nyquist = 0.5 / float(np.median(np.diff(ts)))
    fs_in = 1.0 / float(np.median(np.diff(t_in)))
    cutoff = cutoff_fraction * new_nyquist
    if cutoff < 0.5 * fs_in:
        sos = signal.butter(filter_order, cutoff, btype="low", fs=fs_in, output="sos")
        pad = min(3 * (2 * len(sos) + 1), t_in.size - 1)
        inertial = {k: signal.sosfiltfilt(sos, v, padlen=pad) for k, v in inertial.items()}
    else:
        cutoff = None
    return Synchronized(
        ts=ts, cutoff_hz=cutoff,
        temperature={k: np.interp(ts, t_temp, v) for k, v in temperature.items()},
        inertial={k: np.interp(ts, t_in, v) for k, v in inertial.items()})


# ---------------------------------------------------------------------------
# Outliers: the Hampel filter


@dataclass(frozen=True)
class Outliers:
    """What `remove_outliers` found: `cleaned` (NaN at outliers), `mask` (True at
    outliers) and `median` (the rolling median), all `(samples,)`."""

    cleaned: np.ndarray
    mask: np.ndarray
    median: np.ndarray

    @property
    def count(self) -> int:
        """How many samples were outliers."""
        return int(self.mask.sum())

    @property
    def filled(self) -> np.ndarray:
        """The samples with each outlier replaced by its rolling median (the classical
        Hampel output; NaN only where the whole window was NaN)."""
        return np.where(self.mask, self.median, self.cleaned)


def remove_outliers(x, window: int = 7, n_sigmas: float = 3.0,
                    chunk: int = 65536) -> Outliers:
    """Hampel filter: a sample is an outlier when it lies more than `n_sigmas` robust
    standard deviations from the median of the `window` samples centred on it,

    `|x_i − med_i| > n_sigmas · 1.4826 · median_j |x_j − med_i|` (j in the window),

    1.4826 making the MAD a standard deviation for Gaussian noise. NaN samples are
    ignored; windows are shortened at the ends (edge samples repeated). A window with
    zero MAD (e.g. quantized, constant data) flags any sample off its median.

    **Arguments:**

    - `x`: `(samples,)` one channel, any unit.
    - `window`: odd number of samples in the window (default 7, half-width 3).
    - `n_sigmas`: threshold in robust standard deviations (default 3).
    - `chunk`: samples per block (bounds the memory, `chunk·window` floats).

    **Returns:** an `Outliers`.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 1:
        raise InputError(f"remove_outliers takes one channel, got shape {x.shape}.", field="x")
    if window < 3 or window % 2 == 0:
        raise InputError(f"the Hampel window must be an odd number of samples ≥ 3, got {window}.",
                         field="window")
    half = window // 2
    padded = np.pad(x, half, mode="edge")
    median = np.full(x.shape, np.nan)
    scale = np.full(x.shape, np.nan)
    for a in range(0, x.size, chunk):
        w = sliding_window_view(padded[a:a + min(chunk, x.size - a) + 2 * half], window)
        has = np.isfinite(w).any(axis=1)
        if not has.any():
            continue
        med = np.nanmedian(w[has], axis=1)
        median[a:a + w.shape[0]][has] = med
        scale[a:a + w.shape[0]][has] = 1.4826 * np.nanmedian(np.abs(w[has] - med[:, None]),
                                                             axis=1)
    with np.errstate(invalid="ignore"):
        mask = np.abs(x - median) > n_sigmas * scale
    return Outliers(cleaned=np.where(mask, np.nan, x), mask=mask, median=median)


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
