"""The factory calibration pipeline as named stages, each a function on
plain data, and `run_pipeline(config)` running those a config names, in order:

1. `condition`: two logs per run onto one time base (Hampel outliers, the same low-pass
   on both logs before decimation, optional rate-table orientation separation);
2. `static_polynomial`: dwell plateaus found automatically, a polynomial per channel
   in the measured temperature that indexes it;
3. `thermal_fit`: `thermojax.fit` of the model and its bias channels, jointly, on the
   calibration runs (output error);
4. `coupling`: the gradient, rate and strain coefficients of each channel (the
   regression of the bias left after the polynomial on those states, solved inside the
   joint fit) as a channels × regressors matrix with stds (scaled for the low-passed
   noise's correlation);
5. `verify`: the fitted model exported as the reference observer, played back (float)
   on every held-back run, its bias output against the measured bias, pass or fail
   against the config's bias-stability specification; and the overlapping Allan
   deviation of each gyro channel's raw, static-compensated and observer-compensated
   output there (`verification_allan`).
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._errors import InputError
from ._conditioning import (ORIENTATIONS, label_orientations, remove_outliers,
                            separate_orientation_bias, synchronize)
from ._config import CalibrationConfig, RunFiles, load_config
from ._plateaus import Plateau, StaticPolynomial, find_plateaus, fit_static_polynomial


# ---------------------------------------------------------------------------
# Loaded and conditioned runs


@dataclass(frozen=True)
class RawRun:
    """One run as read: the temperature log (`Telemetry`: the model's inputs and
    sensors) and the inertial log (`Telemetry`: the bias columns), each with its own
    times; the same object twice for a combined telemetry file."""

    files: RunFiles
    temperature: object
    inertial: object

    @property
    def name(self) -> str:
        return self.files.name


@dataclass(frozen=True)
class ConditionedRun:
    """One run on the common time base.

    - `ts`: `(times,)` s, uniform at the config's `dt_s`.
    - `inputs`: `(times, inputs)` in the model's input order (°C, W).
    - `sensors`: `(times, sensors)` °C in the model's sensor order.
    - `bias`: channel -> `(times,)` the conditioned bias (channel unit), with the
      g-dependent offsets removed when orientations were separated.
    - `outliers`: channel -> samples of the raw inertial log replaced by the Hampel rule.
    - `cutoff_hz`: the low-pass cutoff (None: no decimation was needed).
    - `orientation`: channel -> {orientation: (offset, std)} or None.
    - `raw_rates_hz`: (temperature log, inertial log) median rates.
    - `noise_factor`: `Synchronized.noise_factor` (≥ 1): how much a white-noise std
      understates the low-passed, decimated noise's effect on a slow regressor.
    """

    name: str
    use: str
    ts: np.ndarray
    inputs: np.ndarray
    sensors: np.ndarray
    bias: dict
    outliers: dict
    cutoff_hz: float | None
    orientation: dict | None
    raw_rates_hz: tuple[float, float]
    noise_factor: float = 1.0


def load_runs(config: CalibrationConfig, spec) -> list[RawRun]:
    """Read every run's logs and check them before any work: the model's input and
    sensor columns in the temperature log, each calibrated channel (not all NaN) in the
    inertial log, timestamps strictly increasing (read_telemetry), streams overlapping in
    time. Raises `InputError` naming the data file and field (or line)."""
    from ..measurements._plausibility import check_plausibility, describe_dropped
    from ..measurements._telemetry import read_telemetry

    runs = []
    for r in config.runs:
        if r.telemetry is not None:
            t = i = read_telemetry(r.telemetry, uniform=False)
            t_file = i_file = r.telemetry
        else:
            t = read_telemetry(r.temperature, uniform=False)
            i = read_telemetry(r.inertial, uniform=False)
            t_file, i_file = r.temperature, r.inertial
        for c in (*spec.input_columns, *spec.sensor_columns):
            if c not in t.names:
                raise InputError(f"the temperature log has no column {c!r} (the model "
                                 f"{config.model.name} needs its inputs "
                                 f"{', '.join(spec.input_columns)} and sensors "
                                 f"{', '.join(spec.sensor_columns)}).", file=str(t_file),
                                 field=c)
        for c in (*config.channels, *(config.orientation_columns or ())):
            if c not in i.names:
                raise InputError(f"the inertial log has no column {c!r}; record it, or drop "
                                 "it from the config's 'channels'.", file=str(i_file), field=c)
            if not np.isfinite(i.column(c)).any():
                raise InputError(f"the column {c!r} is all NaN (empty): there is nothing to "
                                 "calibrate in this run; record it or drop the run.",
                                 file=str(i_file), field=c)
        # the temperature log against the model's units (kelvin, milliseconds, cells no
        # temperature or power can take): stop, or drop them (config outliers.implausible);
        # the inertial log's spikes are the conditioning's (Hampel)
        t, dropped = check_plausibility(dataclasses.replace(spec, biases=()), t,
                                        config.implausible)
        if dropped:
            warnings.warn(describe_dropped(t, dropped), stacklevel=2)
        tt, ti = np.asarray(t.ts), np.asarray(i.ts)
        if max(tt[0], ti[0]) >= min(tt[-1], ti[-1]):
            raise InputError(
                f"the temperature log ({t_file.name}: {tt[0]:g}…{tt[-1]:g} s) and the inertial "
                f"log ({i_file.name}: {ti[0]:g}…{ti[-1]:g} s) do not overlap in time; check "
                "that both use the same clock and epoch.", file=str(i_file), field="time_s")
        runs.append(RawRun(r, t, i))
    return runs


def condition(run: RawRun, spec, config: CalibrationConfig) -> ConditionedRun:
    """Stage (a), data conditioning of one run.

    1. Outliers: each raw inertial channel through the Hampel-type rule
       (`remove_outliers`: `|x − med_window| > n_sigmas · σ̂`, σ̂ from successive
       differences per `scale_window` samples), outliers replaced by the rolling median.
    2. Synchronization: the common time base is the temperature log's times from the
       first one inside the overlap of both logs, every `dt_s`; both logs are low-passed
       alike (zero-phase Butterworth, cutoff `cutoff_fraction` × the new Nyquist) before
       being taken onto it: sensors and first-order-hold inputs at the sample times,
       zero-order-hold inputs (the model's `hold`) as each interval's mean
       (`synchronize`).
    3. Orientations (when the config names three accelerometer columns): each sample
       labelled by the rate-table position, each channel's g-dependent offsets and
       thermal drift fitted together (`separate_orientation_bias`, the drift polynomial of
       the channel's order in the indexing sensor), the offsets removed.

    **Returns:** a `ConditionedRun`.
    """
    t, i = run.temperature, run.inertial
    where = str(run.files.inertial or run.files.telemetry)
    outliers, filled = {}, {}
    for c in (*config.channels, *(config.orientation_columns or ())):
        raw = np.asarray(i.column(c), dtype=float)
        o = remove_outliers(raw, window=config.outlier_window, n_sigmas=config.outlier_n_sigmas,
                            scale_window=config.outlier_scale_window)
        v = o.filled
        bad = ~np.isfinite(v)
        if bad.any():  # whole windows missing: interpolate across the gap
            v = np.interp(np.asarray(i.ts), np.asarray(i.ts)[~bad], v[~bad])
        outliers[c], filled[c] = o.count, v
    tt = np.asarray(t.ts)
    start = max(tt[0], float(i.ts[0]))
    end = min(tt[-1], float(i.ts[-1]))
    t0 = tt[tt >= start][0]
    ts = t0 + config.dt_s * np.arange(int(math.floor((end - t0) / config.dt_s + 1e-9)) + 1)
    temp_cols = (*spec.input_columns, *spec.sensor_columns)
    try:
        sync = synchronize(tt, {c: t.column(c) for c in temp_cols}, i.ts, filled, ts,
                           cutoff_fraction=config.cutoff_fraction,
                           filter_order=config.filter_order,
                           holds={c: spec.hold_for(c) for c in spec.input_columns})
    except InputError as err:
        raise InputError(str(err), file=where) from None
    inputs = np.stack([sync.temperature[c] for c in spec.input_columns], 1)
    sensors = np.stack([sync.temperature[c] for c in spec.sensor_columns], 1)
    bias = {c: sync.inertial[c] for c in config.channels}
    orientation = None
    if config.orientation_columns:
        acc = np.stack([sync.inertial[c] for c in config.orientation_columns], 1)
        labels = label_orientations(acc, config.orientation_tolerance_deg)
        T = sync.temperature[config.temperature_sensor]
        orientation = {}
        for c in config.channels:
            try:
                sep = separate_orientation_bias(T, bias[c], labels, config.orders[c], name=c)
            except InputError as err:
                raise InputError(str(err), file=where) from None
            orientation[c] = {ORIENTATIONS[k]: (float(o), float(s)) for k, o, s in
                              zip(sep.orientations, sep.offsets, sep.offset_std)}
            bias[c] = sep.drift
    rate = lambda ts_: 1.0 / float(np.median(np.diff(np.asarray(ts_))))  # noqa: E731
    return ConditionedRun(run.name, run.files.use, sync.ts, inputs, sensors, bias, outliers,
                          sync.cutoff_hz, orientation, (rate(t.ts), rate(i.ts)),
                          sync.noise_factor)


# ---------------------------------------------------------------------------
# (b) static polynomial


@dataclass(frozen=True)
class ChannelPolynomial:
    """A channel's static polynomial (`StaticPolynomial`, in the indexing sensor's °C
    about 25 °C) with the plateaus it went through (`(run name, Plateau)`), each
    plateau's standard error of the mean bias (`standard_error`) and the Birge ratio
    `sqrt(χ²/dof)` by which the stds were scaled when above 1."""

    polynomial: StaticPolynomial
    plateaus: list
    standard_error: np.ndarray
    birge_ratio: float


def static_polynomial(runs: list[ConditionedRun], config: CalibrationConfig,
                      sensor_index: int) -> dict[str, ChannelPolynomial]:
    """Stage (b): the static bias polynomial of every channel from dwell plateaus.

    Plateaus are detected in each calibration run's indexing sensor (`find_plateaus`:
    `|dT/dt| < max_rate_k_per_min` for at least `min_duration_s`, the first `settle_s`
    skipped) and pooled. Each plateau gives (mean temperature, mean bias, standard error
    `std/√n`); the polynomial of the channel's order is fitted by weighted least squares
    through them, and its stds are multiplied by the Birge ratio `sqrt(χ²/dof)` when that
    exceeds 1 (plateau means scattered beyond their noise, e.g. by a drift that has not
    settled).

    **Arguments:** `runs` (the calibration runs, conditioned), `config`, `sensor_index`
    (the indexing sensor's column in `ConditionedRun.sensors`).

    **Returns:** channel -> `ChannelPolynomial`.
    """
    out = {}
    for c in config.channels:
        plateaus = []
        for r in runs:
            ps = find_plateaus(r.ts, r.sensors[:, sensor_index], r.bias[c],
                               max_rate_k_per_min=config.max_rate_k_per_min,
                               min_duration_s=config.min_duration_s, settle_s=config.settle_s,
                               rate_window_s=max(120.0, 4 * config.dt_s), name=c)
            plateaus += [(r.name, p) for p in ps]
        T = np.array([p.temperature for _, p in plateaus])
        b = np.array([p.bias for _, p in plateaus])
        se = np.array([p.bias_std / math.sqrt(max(p.n, 1)) for _, p in plateaus])
        order = config.orders[c]
        try:
            poly = fit_static_polynomial(T, b, order, se if se.size else None, name=c)
        except InputError as err:
            raise InputError(f"{err} (channel {c!r})", file=str(config.path),
                             field="static_polynomial.order") from None
        dof = len(plateaus) - order - 1
        birge = 1.0
        if dof > 0:
            chi2 = float(np.sum(((b - poly(T)) / se) ** 2))
            birge = max(1.0, math.sqrt(chi2 / dof))
        if birge > 1.0:
            poly = dataclasses.replace(poly, std=poly.std * birge,
                                       covariance=poly.covariance * birge ** 2)
        out[c] = ChannelPolynomial(poly, plateaus, se, birge)
    return out


def count_plateaus(runs: list[RawRun], config: CalibrationConfig) -> int:
    """Dwell plateaus in the raw temperature logs of the calibration runs (the check of
    the polynomial orders before any work)."""
    n = 0
    for r in runs:
        if r.files.use != "calibration":
            continue
        T = np.asarray(r.temperature.column(config.temperature_sensor), float)
        n += len(find_plateaus(r.temperature.ts, T, max_rate_k_per_min=config.max_rate_k_per_min,
                               min_duration_s=config.min_duration_s, settle_s=config.settle_s,
                               rate_window_s=max(120.0, 4 * config.dt_s)))
    return n


# ---------------------------------------------------------------------------
# (c) thermal fit


def calibration_spec(spec, channels):
    """`spec` with only the bias channels `channels` (and their viscoelastic effects)."""
    keep = set(channels)
    return dataclasses.replace(
        spec, biases=tuple(b for b in spec.biases if b.column in keep),
        effects=tuple(e for e in spec.effects if not (
            e.kind == "viscoelastic" and e.where[1] not in keep
            and e.where[1] in {b.column for b in spec.biases})))


def experiments(runs: list[ConditionedRun], spec) -> list:
    """The conditioned runs as `Experiment`s of `spec` (bias columns in its order)."""
    from ..measurements._data import Experiment

    return [Experiment(r.ts, r.inputs, r.sensors, r.name,
                       np.stack([r.bias[b.column] for b in spec.biases], 1)
                       if spec.biases else None) for r in runs]


# lag-1 autocorrelation of a column's weighted residuals above which the thermal fit says
# the model misses content between samples (filtered white noise stays near 0.3)
CORRELATED_RESIDUALS = 0.5


def thermal_fit(runs: list[ConditionedRun], spec, config: CalibrationConfig, progress=None):
    """Stage (c): `thermojax.fit` (output error) of the model's free thermal parameters
    and its bias channels jointly on the calibration runs (every run, plateaus and
    transients alike; the transients are what inform the conductances, the rate and
    strain terms).

    **Returns:** the `FitResult` (`result.spec` the calibrated model, `result.biases`
    each channel's `BiasFit`).
    """
    from ..fitting import fit

    return fit(spec, experiments(runs, spec), max_steps=config.fit_max_steps,
               progress=progress)


# ---------------------------------------------------------------------------
# (d) coupling matrix


@dataclass(frozen=True)
class Coupling:
    """`matrix[i, j]` (channel `channels[i]`'s unit per regressor unit: per K for a
    gradient or a strain state, per K/s for a rate) and `std` (NaN: not identifiable or
    fixed); NaN in `matrix` where the channel has no such term. `polynomial[c]` holds the
    joint fit's polynomial in the bias node's estimated temperature (names, values,
    stds) and `time_constants[c]` its relaxation times (τ s, std). Every std is the
    fit's times `noise_factor`."""

    channels: tuple[str, ...]
    regressors: tuple[str, ...]
    matrix: np.ndarray
    std: np.ndarray
    polynomial: dict
    time_constants: dict
    noise_factor: float = 1.0


def coupling(result, channels, noise_factor: float = 1.0) -> Coupling:
    """Stage (d): the coupling matrix from the joint fit's bias channels. Each channel's
    bias is `polynomial(T_node) + Σ d_g ΔT_g + Σ e_r dT_r/dt + Σ k_v (T_v − ε_v)`, and
    the gradient, rate and strain coefficients are the least-squares regression of what
    the polynomial leaves on those states (solved with the polynomial, by variable
    projection inside the fit, so the stds include the thermal parameters'
    uncertainty).

    The fit takes each sample's noise as independent. After the low-pass the decimated
    noise is correlated from sample to sample, which a slowly varying regressor sees as
    `noise_factor²` (`ConditionedRun.noise_factor`, ~1.15 at the default cutoff) times
    more variance: every std is multiplied by `noise_factor`.
    """
    regs, rows, poly, taus = [], {}, {}, {}
    q = float(noise_factor)
    for c in channels:
        b = result.biases[c]
        rows[c] = {}
        poly[c] = {n: (float(v), q * float(s)) for n, v, s
                   in zip(b.names, b.coefficients, b.std) if n.startswith("poly")}
        taus[c] = {n: (float(t), None if s is None else q * float(s))
                   for n, (t, s) in b.time_constants.items()}
        for n, v, s in zip(b.names, b.coefficients, b.std):
            if n.startswith("poly"):
                continue
            rows[c][n] = (float(v), q * float(s))
            if n not in regs:
                regs.append(n)
    M = np.full((len(channels), len(regs)), np.nan)
    S = np.full_like(M, np.nan)
    for i, c in enumerate(channels):
        for j, n in enumerate(regs):
            if n in rows[c]:
                M[i, j], S[i, j] = rows[c][n]
    return Coupling(tuple(channels), tuple(regs), M, S, poly, taus, q)


# ---------------------------------------------------------------------------
# (e) verification playback


@dataclass(frozen=True)
class ChannelCheck:
    """One channel of one held-back run: the residual `measured − observer` bias
    (`residual (times,)`, channel unit; NaN before `skip_s`), its `rms`, `peak` (max |·|)
    and `mean`, the static polynomial's residual RMS for comparison (None without that
    stage), the limits and `passed`; also the series the statistics came from, NaN before
    `skip_s` like `residual`: `measured (times,)` the conditioned bias itself and
    `static_residual (times,)` `measured − static polynomial` (None without that stage)."""

    run: str
    channel: str
    ts: np.ndarray
    residual: np.ndarray
    rms: float
    peak: float
    mean: float
    static_rms: float | None
    limits: dict
    passed: bool
    measured: np.ndarray | None = None
    static_residual: np.ndarray | None = None


def verify(spec, runs: list[ConditionedRun], config: CalibrationConfig, observer_dir,
           static: dict | None = None, sensor_index: int | None = None) -> list[ChannelCheck]:
    """Stage (e): the fitted model exported as the reference observer (at `1/dt_s`) into
    `observer_dir`, loaded back, and played (float64) through every held-back run: its
    inputs and sensor readings in, its bias channels out (evaluated from the state
    estimate). The observer starts at the steady state of the run's first input. Each
    channel's residual `measured − observer` after `skip_s` is compared with the
    specification: `rms ≤ spec.rms` and `peak ≤ spec.peak`.

    **Returns:** one `ChannelCheck` per run and channel.
    """
    from ..observer._export import export_observer
    from ..reference import load_observer

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        export_observer(spec, 1.0 / config.dt_s, observer_dir)
    art = load_observer(observer_dir)
    obs = art.float_observer()
    s = art.system
    columns = [b["column"] for b in art.metadata["biases"] if b["coefficients"] is not None]
    checks = []
    for r in runs:
        u = r.inputs[:, [spec.input_columns.index(n) for n in art.input_names]]
        y = r.sensors[:, [spec.sensor_columns.index(n) for n in art.output_names]]
        n = s.Phi.shape[0]
        x0 = np.linalg.solve(np.eye(n) - s.Phi, (s.B0 + s.B1) @ u[0])
        played = obs.run(x0, u, y)
        keep = r.ts >= r.ts[0] + config.skip_s
        for c in config.channels:
            res = np.where(keep, r.bias[c] - played.bias[:, columns.index(c)], np.nan)
            ok = np.isfinite(res)
            rms = float(np.sqrt(np.mean(res[ok] ** 2)))
            peak = float(np.max(np.abs(res[ok])))
            static_rms = sres = None
            if static is not None and c in static:
                sres = np.where(keep, r.bias[c] - static[c].polynomial(
                    r.sensors[:, sensor_index]), np.nan)
                static_rms = float(np.sqrt(np.nanmean(sres ** 2)))
            lim = config.limits[c]
            passed = rms <= lim.get("rms", math.inf) and peak <= lim.get("peak", math.inf)
            checks.append(ChannelCheck(r.name, c, r.ts, res, rms, peak,
                                       float(np.mean(res[ok])), static_rms, dict(lim), passed,
                                       np.where(keep, r.bias[c], np.nan), sres))
    return checks


#: The outputs whose Allan deviation the verification reads: label -> `ChannelCheck`
#: field (each NaN before `skip_s`).
ALLAN_OUTPUTS = {"raw": "measured", "static polynomial": "static_residual",
                 "observer": "residual"}


def is_gyro(channel: str) -> bool:
    """A gyro channel: its name ends in `_dph` (deg/h, docs/formats.md §1) or starts with
    `gyro`."""
    return channel.endswith("_dph") or channel.lower().startswith("gyro")


@dataclass(frozen=True)
class ChannelAllan:
    """The overlapping Allan deviation of one gyro channel on one held-back run, on the
    conditioned `dt_s` base after `skip_s`: `curves` output -> `AllanDeviation` and
    `noise` output -> `NoiseParameters` (angle random walk, bias instability, with
    intervals), for the outputs of `ALLAN_OUTPUTS` present; `rate_unit` e.g. "deg/h"."""

    run: str
    channel: str
    rate_unit: str
    curves: dict
    noise: dict


def verification_allan(checks: list[ChannelCheck], dt_s: float) -> list[ChannelAllan]:
    """The Allan deviation of raw, static-compensated and observer-compensated output of
    every gyro channel (`is_gyro`) and held-back run, from the series `verify` kept
    (`ChannelCheck.measured`, `.static_residual`, `.residual`, after `skip_s`), sampled
    at `1/dt_s`. The series were low-passed before decimation (cutoff `cutoff_fraction`
    × Nyquist), which lowers the shortest-τ points a little. Runs with fewer than 16
    samples after `skip_s` are left out.

    **Returns:** one `ChannelAllan` per gyro channel and run.
    """
    from .._plots import column_unit
    from ._allan import allan_deviation, noise_parameters

    out = []
    for ch in checks:
        keep = np.isfinite(ch.residual)
        if not is_gyro(ch.channel) or keep.sum() < 16:
            continue
        unit = column_unit(ch.channel, bias=True)
        curves, noise = {}, {}
        for label, name in ALLAN_OUTPUTS.items():
            y = getattr(ch, name)
            if y is None:
                continue
            curves[label] = allan_deviation(np.asarray(y)[keep], 1.0 / dt_s)
            noise[label] = noise_parameters(curves[label], unit)
        out.append(ChannelAllan(ch.run, ch.channel, unit, curves, noise))
    return out


def _estimate(e, tau=None) -> dict | None:
    """An `Estimate` (and the τ it was read at) as a report dict."""
    if e is None:
        return None
    return {"value": e.value, "lower": e.lower, "upper": e.upper,
            **({} if tau is None else {"tau_s": tau})}


def allan_entry(allan: list[ChannelAllan]) -> list[dict]:
    """The Allan results as report dicts: per run and channel, per output the curve
    (`taus_s`, `adev`, `lower`, `upper`) and the noise terms with their intervals."""
    rows = []
    for a in allan:
        outputs = {}
        for label, curve in a.curves.items():
            n = a.noise[label]
            outputs[label] = {
                "taus_s": curve.taus, "adev": curve.adev, "lower": curve.lower,
                "upper": curve.upper,
                "angle_random_walk": _estimate(n.angle_random_walk, n.angle_random_walk_tau),
                "angle_random_walk_deg_per_sqrt_h": _estimate(
                    n.angle_random_walk_deg_per_sqrt_h, n.angle_random_walk_tau),
                "bias_instability": _estimate(n.bias_instability, n.bias_instability_tau),
                "bias_instability_at_longest_tau": bool(
                    n.bias_instability_tau >= curve.taus[-1]),
                "rate_random_walk": _estimate(n.rate_random_walk, n.rate_random_walk_tau)}
        ci = next(iter(a.curves.values())).ci
        rows.append({"run": a.run, "channel": a.channel, "rate_unit": a.rate_unit,
                     "sample_rate_hz": next(iter(a.curves.values())).sample_rate_hz,
                     "ci": ci, "outputs": outputs})
    return rows


# ---------------------------------------------------------------------------
# The whole pipeline


@dataclass
class CalibrationResults:
    """What `run_pipeline` produced; a stage not run leaves its entry None.

    `stages` is the log: one dict per stage run with `stage`, `did` (a sentence) and its
    numbers."""

    config: CalibrationConfig
    spec: object  # the model as loaded, restricted to the calibrated channels
    runs: list[ConditionedRun]
    static: dict | None = None
    fit: object | None = None
    coupling: Coupling | None = None
    checks: list[ChannelCheck] | None = None
    allan: list[ChannelAllan] | None = None
    observer_dir: Path | None = None
    stages: list = field(default_factory=list)

    @property
    def calibrated_spec(self):
        """The calibrated model (the fit's), or the model as loaded without a fit."""
        return self.fit.spec if self.fit is not None else self.spec

    @property
    def passed(self) -> bool | None:
        return None if self.checks is None else all(c.passed for c in self.checks)


def prepare(config) -> tuple[CalibrationConfig, object, list[RawRun]]:
    """Load and check the config, the model and every data file (no work yet); also the
    polynomial orders against the plateaus the calibration runs' temperature logs show.
    Returns `(config, spec restricted to the channels, raw runs)`."""
    from ..model._model_file import load_model

    if not isinstance(config, CalibrationConfig):
        config = load_config(config)
    spec = calibration_spec(load_model(config.model), config.channels)
    raw = load_runs(config, spec)
    if "static_polynomial" in config.stages:
        n = count_plateaus(raw, config)
        worst = max(config.orders.values())
        if n < worst + 1:
            c = max(config.orders, key=config.orders.get)
            raise InputError(
                f"found {n} dwell plateau{'s' if n != 1 else ''} in the calibration runs' "
                f"'{config.temperature_sensor}' (|dT/dt| < {config.max_rate_k_per_min:g} K/min "
                f"for {config.min_duration_s:g} s or more); channel {c!r} asks for an order-"
                f"{worst} polynomial, which needs {worst + 1}: lower the order to "
                f"{max(n - 1, 0)}, add dwells at more temperatures, or loosen "
                "max_rate_k_per_min / min_duration_s.", file=str(config.path),
                field="static_polynomial.order")
    return config, spec, raw


def run_pipeline(config, *, observer_dir=None, progress=None) -> CalibrationResults:
    """Run the stages the config names, in the fixed order `STAGES`.

    **Arguments:**

    - `config`: a config path or a `CalibrationConfig`.
    - `observer_dir`: where `verify` writes the exported observer (default a temporary
      folder, removed afterwards).
    - `progress`: optional callable taking a one-line string (one or more per stage).

    **Returns:** a `CalibrationResults`. Raises `InputError` for bad input, before any
    work where it can be seen in the files.
    """
    say = progress or (lambda _msg: None)
    config, spec, raw = prepare(config)
    i_sensor = spec.sensor_columns.index(config.temperature_sensor)
    runs = [condition(r, spec, config) for r in raw]
    res = CalibrationResults(config, spec, runs)
    n_out = {c: sum(r.outliers[c] for r in runs) for c in config.channels}
    cut = {r.cutoff_hz for r in runs}
    res.stages.append({
        "stage": "condition",
        "did": (f"{len(runs)} runs onto a {config.dt_s:g} s time base: Hampel outliers "
                f"(|x − median of {config.outlier_window}| > {config.outlier_n_sigmas:g} σ̂, "
                f"σ̂ from successive differences per {config.outlier_scale_window} samples) "
                "replaced by the rolling median, both streams low-passed alike (zero-phase "
                f"Butterworth order {config.filter_order}, cutoff "
                f"{config.cutoff_fraction:g} × the new Nyquist) before decimation, "
                "zero-order-hold inputs averaged over each new sample period"
                + (", g-dependent bias separated per rate-table orientation"
                   if config.orientation_columns else "")),
        "outliers": n_out, "cutoff_hz": sorted(c for c in cut if c is not None),
        "runs": {r.name: {"use": r.use, "samples": int(r.ts.size),
                          "span_s": [float(r.ts[0]), float(r.ts[-1])],
                          "temperature_rate_hz": r.raw_rates_hz[0],
                          "inertial_rate_hz": r.raw_rates_hz[1], "outliers": r.outliers,
                          "noise_factor": r.noise_factor,
                          "orientation_offsets": r.orientation} for r in runs}})
    say(f"condition: {len(runs)} runs on a {config.dt_s:g} s base; outliers removed "
        + ", ".join(f"{c} {n}" for c, n in n_out.items()))
    cal = [r for r in runs if r.use == "calibration"]
    held = [r for r in runs if r.use == "verification"]
    if "static_polynomial" in config.stages:
        res.static = static_polynomial(cal, config, i_sensor)
        entry = {"stage": "static_polynomial",
                 "did": (f"dwell plateaus detected in {config.temperature_sensor} "
                         f"(|dT/dt| < {config.max_rate_k_per_min:g} K/min for ≥ "
                         f"{config.min_duration_s:g} s, first {config.settle_s:g} s skipped); "
                         "a polynomial in (T − 25 °C) per channel by weighted least squares "
                         "through the plateau means, stds scaled by the Birge ratio when "
                         "above 1"),
                 "channels": {}}
        for c, p in res.static.items():
            entry["channels"][c] = {
                "order": p.polynomial.order,
                "coefficients": p.polynomial.coefficients.tolist(),
                "std": p.polynomial.std.tolist(), "birge_ratio": p.birge_ratio,
                "residual_rms": p.polynomial.residual_rms,
                "plateaus": [{"run": name, "start_s": q.start_s, "end_s": q.end_s,
                              "temperature_c": q.temperature, "bias": q.bias,
                              "standard_error": float(se)}
                             for (name, q), se in zip(p.plateaus, p.standard_error)]}
            say(f"static_polynomial: {c}: {len(p.plateaus)} plateaus, order "
                f"{p.polynomial.order}, residual RMS {p.polynomial.residual_rms:.4g}")
        res.stages.append(entry)
    if "thermal_fit" in config.stages:
        say(f"thermal_fit: fitting {len(cal)} calibration runs (model and bias channels "
            "jointly, output error)")
        res.fit = thermal_fit(cal, spec, config, progress=say)
        f = res.fit
        from ..fitting._correlated_noise import correlated_noise_stds

        hac = correlated_noise_stds(f) if len(f.theta) else None
        res.stages.append({
            "stage": "thermal_fit",
            "did": (f"thermojax.fit (output error) of the model's free parameters and its "
                    f"{len(config.channels)} bias channels jointly on {len(cal)} runs; "
                    "std_hac: the stds with the residuals' correlation in time (Newey-West"
                    + (f", {hac.lags} lags)" if hac else ")")),
            "converged": bool(f.converged), "message": f.message, "n_steps": int(f.n_steps),
            "nll": float(f.nll), "n_params": int(f.n_params), "rmse": dict(f.rmse),
            "residual_autocorrelation": hac.autocorrelation if hac else None,
            "parameters": {k: {"value": v["value"], "std": v["std"], "free": v.get("free"),
                               **({"std_hac": hac.stds[k]} if hac and k in hac.stds else {})}
                           for k, v in f.parameters.items()}})
        for c, rho in (hac.autocorrelation.items() if hac else ()):
            if rho > CORRELATED_RESIDUALS:
                say(f"thermal_fit: the {c} residuals are correlated from sample to sample "
                    f"(lag-1 autocorrelation {rho:.2f}): the model misses content between "
                    f"samples at dt_s = {config.dt_s:g} s (fast input steps, a lag); quote "
                    "std_hac, and a smaller dt_s reduces the misfit")
    if "coupling" in config.stages:
        res.coupling = coupling(res.fit, config.channels,
                                max((r.noise_factor for r in cal), default=1.0))
        k = res.coupling
        res.stages.append({
            "stage": "coupling",
            "did": ("the residual bias after the polynomial regressed on the gradient, "
                    "rate and strain states of the fitted model (jointly with the "
                    "polynomial, inside the fit); stds are the fit's times "
                    f"{k.noise_factor:.3g}, for the low-passed noise's sample-to-sample "
                    "correlation"),
            "noise_factor": k.noise_factor,
            "channels": list(k.channels), "regressors": list(k.regressors),
            "matrix": k.matrix.tolist(), "std": k.std.tolist(),
            "polynomial": k.polynomial, "time_constants": k.time_constants})
        for i, c in enumerate(k.channels):
            terms = [f"{n} {k.matrix[i, j]:.4g} ± {k.std[i, j]:.2g}"
                     for j, n in enumerate(k.regressors) if np.isfinite(k.matrix[i, j])]
            say(f"coupling: {c}: " + ", ".join(terms))
    if "verify" in config.stages:
        tmp = None
        if observer_dir is None:
            tmp = tempfile.TemporaryDirectory()
            observer_dir = Path(tmp.name) / "observer"
        say(f"verify: exporting the calibrated observer at {1 / config.dt_s:g} Hz and "
            f"playing back {len(held)} held-back run(s)")
        try:
            res.checks = verify(res.calibrated_spec, held, config, observer_dir, res.static,
                                i_sensor)
        finally:
            if tmp is not None:
                tmp.cleanup()
        res.observer_dir = None if tmp is not None else Path(observer_dir)
        for ch in res.checks:
            say(f"verify: {ch.run} {ch.channel}: RMS {ch.rms:.4g}, peak {ch.peak:.4g} "
                f"(spec {ch.limits}) {'PASS' if ch.passed else 'FAIL'}")
        res.allan = verification_allan(res.checks, config.dt_s)
        for a in res.allan:
            arw = {k: n.angle_random_walk for k, n in a.noise.items()}
            say(f"verify: {a.run} {a.channel}: Allan deviation; ARW ({a.rate_unit}·√s) "
                + ", ".join(f"{k} " + ("—" if e is None else f"{e.value:.3g}")
                            for k, e in arw.items()))
        res.stages.append({
            "stage": "verify",
            "did": ("the calibrated model exported as the reference observer (float64), "
                    "played back on each held-back run from the steady state of its first "
                    "input; residual = measured − observer bias"
                    + (f" after the first {config.skip_s:g} s" if config.skip_s else "")
                    + "; overlapping Allan deviation (NIST SP 1065, one-sigma intervals from "
                    "Greenhall's EDF) of each gyro channel's raw, static-polynomial-"
                    "compensated and observer-compensated output on the same samples, "
                    "angle random walk and bias instability read off (IEEE Std 952)"),
            "passed": res.passed,
            "checks": [{"run": ch.run, "channel": ch.channel, "rms": ch.rms, "peak": ch.peak,
                        "mean": ch.mean, "static_polynomial_rms": ch.static_rms,
                        "spec": ch.limits, "passed": ch.passed} for ch in res.checks],
            "allan": allan_entry(res.allan)})
    return res
