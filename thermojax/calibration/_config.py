"""The config of `thermojax calibrate` (TOML), read and checked before any work.

```toml
model = "../imu6_bias.toml"             # relative to this file
channels = ["gyro_x_dph", "accel_x_ug"] # [[biases]] columns of the model to calibrate
stages = ["condition", "static_polynomial", "thermal_fit", "coupling", "verify"]
temperature_sensor = "T_asic"           # the measured temperature that indexes the static polynomial
dt_s = 10.0                             # common time base after low-pass and decimation, s

[[runs]]                                # one per chamber run
name = "plateaus"
temperature = "data/plateaus_temperature.csv"  # inputs and sensors, its own time_s
inertial = "data/plateaus_inertial.csv"        # bias columns, its own time_s
use = "calibration"                     # or "verification" (held back)
# telemetry = "run.csv"                 # instead of the two: one combined log

[outliers]        # Hampel: |x − median of `window` samples| > n_sigmas · σ̂ (raw inertial)
window = 7
n_sigmas = 3.0
scale_window = 1000  # samples per block of σ̂ = 1.4826 · median|Δx| / √2
[lowpass]         # zero-phase Butterworth before decimation to dt_s, on both streams
cutoff_fraction = 0.8
filter_order = 4
[orientation]     # optional: rate-table positions from three accelerometer columns
columns = ["acc_x_g", "acc_y_g", "acc_z_g"]
tolerance_deg = 10.0
[static_polynomial]
order = 3         # or a table: { gyro_x_dph = 3, accel_x_ug = 2 }
max_rate_k_per_min = 0.1
min_duration_s = 1200.0
settle_s = 600.0
[thermal_fit]
max_steps = 30
[verify]
skip_s = 0.0      # observer start-up left out of the statistics, s
rate_hz = 0.1     # default 1 / dt_s
[spec.gyro_x_dph] # bias-stability specification per channel, the channel's unit
rms = 0.05
peak = 0.2
```
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from .._errors import InputError

#: The pipeline's stages, in the order they run.
STAGES = ("condition", "static_polynomial", "thermal_fit", "coupling", "verify")
USES = ("calibration", "verification")
_TOP = {"model", "channels", "stages", "temperature_sensor", "dt_s", "runs", "outliers",
        "lowpass", "orientation", "static_polynomial", "thermal_fit", "verify", "spec"}


@dataclass(frozen=True)
class RunFiles:
    """One run of the config: its `name`, `use` ("calibration" or "verification") and
    either `temperature` and `inertial` log paths or one combined `telemetry` path."""

    name: str
    use: str
    temperature: Path | None = None
    inertial: Path | None = None
    telemetry: Path | None = None


@dataclass(frozen=True)
class CalibrationConfig:
    """A checked calibration config (see the module docstring for the file)."""

    path: Path
    model: Path
    channels: tuple[str, ...]
    stages: tuple[str, ...]
    temperature_sensor: str
    dt_s: float
    runs: tuple[RunFiles, ...]
    outlier_window: int = 7
    outlier_n_sigmas: float = 3.0
    outlier_scale_window: int = 1000
    implausible: str = "stop"   # the temperature log's implausible cells: stop or drop
    cutoff_fraction: float = 0.8
    filter_order: int = 4
    orientation_columns: tuple[str, ...] | None = None
    orientation_tolerance_deg: float = 10.0
    orders: dict = field(default_factory=dict)  # channel -> polynomial order
    max_rate_k_per_min: float = 0.1
    min_duration_s: float = 1200.0
    settle_s: float = 600.0
    fit_max_steps: int = 30
    skip_s: float = 0.0
    verify_rate_hz: float | None = None
    limits: dict = field(default_factory=dict)  # channel -> {"rms": x, "peak": y}

    def runs_for(self, use: str) -> list[RunFiles]:
        return [r for r in self.runs if r.use == use]


def _err(path, message, field_name):
    return InputError(message, file=str(path), field=field_name)


def _number(path, table, key, where, default, *, positive=True, integer=False):
    value = table.get(key, default)
    name = f"{where}.{key}" if where else key
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _err(path, f"expected a number, got {value!r}.", name)
    if integer and int(value) != value:
        raise _err(path, f"expected a whole number, got {value!r}.", name)
    if not math.isfinite(value) or (positive and value <= 0) or (not positive and value < 0):
        raise _err(path, f"expected a {'positive' if positive else 'non-negative'} number, got "
                   f"{value!r}.", name)
    return int(value) if integer else float(value)


# The fields each optional table may hold: any other is a typo, refused rather than dropped.
_TABLE_KEYS = {
    "outliers": {"window", "n_sigmas", "implausible", "scale_window"},
    "lowpass": {"cutoff_fraction", "filter_order"},
    "orientation": {"columns", "tolerance_deg"},
    "static_polynomial": {"order", "settle_s", "min_duration_s", "max_rate_k_per_min"},
    "thermal_fit": {"max_steps"},
    "verify": {"rate_hz", "skip_s"},
}


def _table(path, doc, key):
    value = doc.get(key, {})
    if not isinstance(value, dict):
        raise _err(path, f"expected a table [{key}], got {value!r}.", key)
    unknown = sorted(set(value) - _TABLE_KEYS.get(key, set(value)))
    if unknown:
        raise _err(path, f"unknown field; [{key}] may hold "
                   f"{', '.join(sorted(_TABLE_KEYS[key]))}.", f"{key}.{unknown[0]}")
    return value


def _names(path, doc, key):
    value = doc.get(key)
    if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
        raise _err(path, f"expected a non-empty list of names, got {value!r}.", key)
    return tuple(value)


def load_config(path) -> CalibrationConfig:
    """Read and check a calibration config: every field, every file's existence, the
    model's columns. Data files are read later (`check_data`).

    **Arguments:** `path`: the TOML file.

    **Returns:** a `CalibrationConfig` with paths resolved against the config's folder.

    **Raises:** `InputError` naming the config file and field.
    """
    from ..model._model_file import load_model

    path = Path(path)
    if not path.is_file():
        raise InputError("no such config file.", file=str(path))
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as err:
        raise InputError(f"not valid TOML ({err}).", file=str(path)) from None
    except UnicodeDecodeError:
        raise InputError("not a UTF-8 text file.", file=str(path)) from None
    unknown = sorted(set(doc) - _TOP)
    if unknown:
        raise _err(path, f"unknown field; expected one of {', '.join(sorted(_TOP))}.",
                   unknown[0])
    base = path.parent
    if not isinstance(doc.get("model"), str):
        raise _err(path, "name the model file (a [[biases]] model TOML), relative to this "
                   "config's folder.", "model")
    model = (base / doc["model"])
    if not model.is_file():
        raise _err(path, f"the model file '{model}' does not exist.", "model")
    spec = load_model(model)
    stages = _names(path, doc, "stages")
    for s in stages:
        if s not in STAGES:
            raise _err(path, f"unknown stage {s!r}; the stages are {', '.join(STAGES)}.",
                       "stages")
    if "coupling" in stages and "thermal_fit" not in stages:
        raise _err(path, "the 'coupling' stage reads the thermal fit's bias coefficients: add "
                   "'thermal_fit' to the stages.", "stages")
    stages = tuple(s for s in STAGES if s in stages or s == "condition")
    channels = _names(path, doc, "channels")
    known = [b.column for b in spec.biases]
    for c in channels:
        if c not in known:
            raise _err(path, f"unknown channel {c!r}: the model {model.name} has the bias "
                       f"channels {', '.join(known) or '(none)'}; add a [[biases]] entry for "
                       "it or remove it from 'channels'.", "channels")
    if "verify" in stages and "thermal_fit" not in stages:
        missing = [b.column for b in spec.biases if b.column in channels
                   and b.coefficients is None]
        if missing:
            raise _err(path, f"'verify' without 'thermal_fit' plays back the model file as "
                       f"it is, but channel {missing[0]!r} has no coefficients there.",
                       "stages")
    sensor = doc.get("temperature_sensor")
    if sensor not in spec.sensor_columns:
        raise _err(path, f"expected one of the model's sensor columns "
                   f"({', '.join(spec.sensor_columns)}), got {sensor!r}.",
                   "temperature_sensor")
    dt_s = _number(path, doc, "dt_s", None, None)
    raw_runs = doc.get("runs")
    if not isinstance(raw_runs, list) or not raw_runs:
        raise _err(path, "add at least one [[runs]] entry.", "runs")
    runs, names = [], set()
    for i, r in enumerate(raw_runs):
        where = f"runs[{i}]"
        if not isinstance(r, dict):
            raise _err(path, "expected a table.", where)
        extra = sorted(set(r) - {"name", "use", "temperature", "inertial", "telemetry"})
        if extra:
            raise _err(path, "unknown field; a run has name, use, and temperature + inertial "
                       "or telemetry.", f"{where}.{extra[0]}")
        name = r.get("name", f"run{i}")
        if not isinstance(name, str) or name in names:
            raise _err(path, f"run names must be distinct strings, got {name!r}.",
                       f"{where}.name")
        names.add(name)
        use = r.get("use", "calibration")
        if use not in USES:
            raise _err(path, f"expected 'calibration' or 'verification', got {use!r}.",
                       f"{where}.use")
        files = {}
        if "telemetry" in r:
            if "temperature" in r or "inertial" in r:
                raise _err(path, "give either 'telemetry' or 'temperature' and 'inertial', "
                           "not both.", f"{where}.telemetry")
            keys = ("telemetry",)
        else:
            keys = ("temperature", "inertial")
        for key in keys:
            if not isinstance(r.get(key), str):
                raise _err(path, f"name the {key} log (CSV with its own time_s), relative to "
                           "this config's folder.", f"{where}.{key}")
            p = base / r[key]
            if not p.is_file():
                raise _err(path, f"the data file '{p}' does not exist; write it (see the "
                           "comment at the top of the config) or fix the path.",
                           f"{where}.{key}")
            files[key] = p
        runs.append(RunFiles(name, use, **files))
    runs = tuple(runs)
    if not any(r.use == "calibration" for r in runs) and (
            {"static_polynomial", "thermal_fit"} & set(stages)):
        raise _err(path, "no run has use = \"calibration\".", "runs")
    if "verify" in stages and not any(r.use == "verification" for r in runs):
        raise _err(path, "the 'verify' stage needs a run with use = \"verification\" (held "
                   "back from the fit).", "runs")
    out = _table(path, doc, "outliers")
    window = _number(path, out, "window", "outliers", 7, integer=True)
    if window < 3 or window % 2 == 0:
        raise _err(path, f"the Hampel window must be an odd number ≥ 3, got {window}.",
                   "outliers.window")
    implausible = out.get("implausible", "stop")
    if implausible not in ("stop", "drop"):
        raise _err(path, f"'implausible' is \"stop\" or \"drop\", got {implausible!r}.",
                   "outliers.implausible")
    scale_window = _number(path, out, "scale_window", "outliers", 1000, integer=True)
    if scale_window < 10:
        raise _err(path, f"the noise-std block must be at least 10 samples, got "
                   f"{scale_window}.", "outliers.scale_window")
    lp = _table(path, doc, "lowpass")
    cutoff = _number(path, lp, "cutoff_fraction", "lowpass", 0.8)
    if cutoff >= 1.0:
        raise _err(path, f"must be below 1 (a fraction of the new Nyquist), got {cutoff}.",
                   "lowpass.cutoff_fraction")
    ori = _table(path, doc, "orientation")
    ori_cols = None
    if "columns" in ori:
        ori_cols = ori["columns"]
        if (not isinstance(ori_cols, list) or len(ori_cols) != 3
                or not all(isinstance(c, str) for c in ori_cols)):
            raise _err(path, f"expected three accelerometer column names (x, y, z), got "
                       f"{ori_cols!r}.", "orientation.columns")
        ori_cols = tuple(ori_cols)
    sp = _table(path, doc, "static_polynomial")
    order = sp.get("order", 3)
    orders = {}
    for c in channels:
        o = order.get(c, 3) if isinstance(order, dict) else order
        if isinstance(o, bool) or not isinstance(o, int) or not 0 <= o <= 5:
            raise _err(path, f"the static polynomial's order must be a whole number 0…5, got "
                       f"{o!r}.", "static_polynomial.order")
        orders[c] = o
    if isinstance(order, dict):
        for c in order:
            if c not in channels:
                raise _err(path, f"unknown channel {c!r} (not in 'channels').",
                           "static_polynomial.order")
    settle = _number(path, sp, "settle_s", "static_polynomial", 600.0, positive=False)
    min_dur = _number(path, sp, "min_duration_s", "static_polynomial", 1200.0)
    if settle >= min_dur:
        raise _err(path, f"settle_s ({settle:g} s) must be shorter than min_duration_s "
                   f"({min_dur:g} s).", "static_polynomial.settle_s")
    tf = _table(path, doc, "thermal_fit")
    ver = _table(path, doc, "verify")
    rate = None if "rate_hz" not in ver else _number(path, ver, "rate_hz", "verify", None)
    if rate is not None and abs(rate * dt_s - 1.0) > 1e-9:
        raise _err(path, f"the observer runs on the common time base: rate_hz must be 1/dt_s "
                   f"= {1 / dt_s:g}, got {rate:g}.", "verify.rate_hz")
    limits = {}
    spec_table = _table(path, doc, "spec")
    for c, lim in spec_table.items():
        if c not in channels:
            raise _err(path, f"unknown channel {c!r}; the calibrated channels are "
                       f"{', '.join(channels)}.", f"spec.{c}")
        if not isinstance(lim, dict) or not set(lim) <= {"rms", "peak"} or not lim:
            raise _err(path, "expected a table with rms and/or peak (the channel's unit).",
                       f"spec.{c}")
        limits[c] = {k: _number(path, lim, k, f"spec.{c}", None) for k in lim}
    if "verify" in stages:
        missing = [c for c in channels if c not in limits]
        if missing:
            raise _err(path, f"the 'verify' stage needs a bias-stability specification for "
                       f"every channel: add [spec.{missing[0]}] with rms and peak.",
                       f"spec.{missing[0]}")
    return CalibrationConfig(
        path=path, model=model, channels=channels, stages=stages, temperature_sensor=sensor,
        dt_s=dt_s, runs=runs, outlier_window=window,
        outlier_n_sigmas=_number(path, out, "n_sigmas", "outliers", 3.0),
        outlier_scale_window=scale_window, implausible=implausible,
        cutoff_fraction=cutoff,
        filter_order=_number(path, lp, "filter_order", "lowpass", 4, integer=True),
        orientation_columns=ori_cols,
        orientation_tolerance_deg=_number(path, ori, "tolerance_deg", "orientation", 10.0),
        orders=orders,
        max_rate_k_per_min=_number(path, sp, "max_rate_k_per_min", "static_polynomial", 0.1),
        min_duration_s=min_dur, settle_s=settle,
        fit_max_steps=_number(path, tf, "max_steps", "thermal_fit", 30, integer=True),
        skip_s=_number(path, ver, "skip_s", "verify", 0.0, positive=False),
        verify_rate_hz=rate, limits=limits)
