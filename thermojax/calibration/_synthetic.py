"""Synthetic chamber logs of an IMU whose truth is a model file: the example data of
`thermojax calibrate` (configs/calibration/imu6_bias.toml) and of its tests.

The truth model (default `configs/imu6_bias.toml`, its bias coefficients and
viscoelastic effects as written) is discretized exactly (the reference observer's
matrices: chamber temperature linear and power constant between samples) and driven
through chamber profiles built from `soak`, `ramp` and `step_shock`. Its bias channels
are evaluated by the reference `BiasEvaluator` (polynomial, gradients, exact-rate and
strain terms). Two logs are written per run, each with its own `time_s`:

- a **temperature log** at `temperature_dt_s` (default 1 s): the model's input columns
  and its sensors with their `noise` std;
- heat inputs switch on and off over `SOFT_START_S` (a linear ramp);
- an **inertial log** at `inertial_rate_hz` (default 20 Hz) on its own clock, starting
  `clock_offset_s` later: each bias column (the truth linearly interpolated between
  temperature samples) with white noise of std `inertial_noise` per sample and a few
  outliers (isolated spikes of `outlier_size` × that std).
"""

from __future__ import annotations

import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._errors import InputError

#: Chamber programmes of the example (°C, s, °C/min). `("soak", T, s)` holds, `("ramp",
#: T, rate)` ramps to T, `("step", T, s)` steps to T and holds, `("power", W, s)` switches
#: the heat inputs on for s seconds and off for 600 s more at the same chamber temperature. The first item sets the
#: start temperature.
CALIBRATION_PROGRAMME = (
    ("soak", 25.0, 3000.0), ("ramp", -40.0, 5.0), ("soak", -40.0, 3000.0),
    ("ramp", -10.0, 5.0), ("soak", -10.0, 3000.0), ("ramp", 55.0, 5.0),
    ("soak", 55.0, 3000.0), ("ramp", 85.0, 5.0), ("soak", 85.0, 3000.0),
)
TRANSIENT_PROGRAMME = (
    ("soak", 25.0, 600.0), ("power", 0.05, 1200.0), ("step", 85.0, 3600.0),
    ("ramp", -20.0, 10.0), ("soak", -20.0, 1200.0), ("power", 0.08, 1200.0),
    ("ramp", 60.0, 2.0), ("soak", 60.0, 1200.0),
)
VERIFICATION_PROGRAMME = (
    ("soak", 10.0, 600.0), ("ramp", 70.0, 3.0), ("soak", 70.0, 2400.0),
    ("step", 0.0, 3000.0), ("ramp", 40.0, 2.0), ("soak", 40.0, 1200.0),
)
#: The packaged example (`thermojax/data/calibration/`, copies of the repository's
#: `configs/imu6_bias.toml` and `configs/calibration/`): the truth the logs are
#: simulated from, the calibration config and its start model.
EXAMPLE_FOLDER = Path(__file__).resolve().parents[1] / "data" / "calibration"
EXAMPLE_TRUTH = EXAMPLE_FOLDER / "imu6_bias_truth.toml"
#: The example's runs: name -> (programme, use).
EXAMPLE_RUNS = {
    "plateaus": (CALIBRATION_PROGRAMME, "calibration"),
    "transients": (TRANSIENT_PROGRAMME, "calibration"),
    "holdout": (VERIFICATION_PROGRAMME, "verification"),
}


#: s, the ramp over which a heat input switches on or off.
SOFT_START_S = 120.0


@dataclass(frozen=True)
class SyntheticRun:
    """One written run: file paths, the truth on the temperature log's times (`ts`, s;
    `states (times, nodes)` °C; `bias` column -> truth), and the outlier rows of the
    inertial log per bias column."""

    name: str
    temperature_file: Path
    inertial_file: Path
    ts: np.ndarray
    states: np.ndarray
    bias: dict
    outlier_rows: dict


def chamber_programme(programme, dt: float):
    """A chamber `Profile` from a programme (see `CALIBRATION_PROGRAMME`), sample period
    `dt` s."""
    from ..measurements._profiles import concatenate, power_step, ramp, soak, step_shock

    if not programme or programme[0][0] not in ("soak", "ramp", "step", "power"):
        raise InputError("a chamber programme needs at least one item.", field="programme")
    parts, T = [], float(programme[0][1])
    for kind, target, value in programme:
        if kind == "soak":
            if target != T:
                raise InputError(f"a soak at {target:g} °C follows {T:g} °C; insert a ramp "
                                 "or a step.", field="programme")
            parts.append(soak(T, value, dt=dt))
        elif kind == "ramp":
            parts.append(ramp(T, target, value, dt=dt))
        elif kind == "step":
            parts.append(step_shock(T, target, 0.0, value, dt=dt))
        elif kind == "power":
            parts.append(power_step(target, 0.0, value, 600.0, temperature_c=T, dt=dt))
            continue
        else:
            raise InputError(f"unknown programme item {kind!r} (soak, ramp, step).",
                             field="programme")
        T = float(target)
    return concatenate(*parts)


def _artifact(spec, dt):
    """The exact discretization and bias evaluator of `spec` at period `dt` s (those of
    its exported reference observer), and its sensors: `(artifact, C, D, offset,
    names)`. The observer is exported with one sensor that observes every state (one
    gain to design instead of one per sensor subset: seconds instead of ~20 s); the
    sensors' output matrices come from the model itself."""
    from ..model import ThermalModel
    from ..observer._export import export_observer
    from ..reference import load_observer

    model = ThermalModel.from_spec(spec)
    system = model.linear_system()
    C, D = np.asarray(system.C, float), np.asarray(system.D, float)
    offset = np.asarray(model.output_offset(), float)
    names = tuple(model.network.topology.sensor_names)
    for sensors in [[n] for n in names] + [None]:
        try:
            with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
                warnings.simplefilter("ignore")
                export_observer(spec, 1.0 / dt, tmp, sensors=sensors)
                return load_observer(tmp), C, D, offset, names
        except InputError:
            if sensors is None:
                raise


def _truth(truth, programme, dt, power_w):
    """Node temperatures `(T, n)`, sensor readings `(T, p)` and bias channels `(T, q)`
    through a programme (`truth` from `_artifact`)."""
    art, C, D, offset, out_names = truth
    profile = chamber_programme(programme, dt)
    ts = np.asarray(profile.ts)
    s = art.system
    u = np.zeros((ts.size, len(art.input_names)))
    # power switched with a soft start: a moving average over SOFT_START_S makes each step
    # a linear ramp (a bias step would fall inside the anti-aliasing filter's window,
    # which a decimated record cannot represent; real ASICs also power up gradually)
    width = max(1, int(round(SOFT_START_S / dt)))
    power = np.convolve(np.concatenate([np.full(width - 1, profile.power[0]), profile.power]),
                        np.ones(width) / width, mode="valid")
    for j, name in enumerate(art.input_names):
        # chamber-temperature inputs follow the profile, power inputs its power + power_w
        u[:, j] = (power + power_w if name.startswith("P")
                   else np.asarray(profile.temperature))
    n = s.Phi.shape[0]
    x = np.empty((ts.size, n))
    # start at rest: the steady state of the first input
    x[0] = np.linalg.solve(np.eye(n) - s.Phi, (s.B0 + s.B1) @ u[0])
    for k in range(1, ts.size):
        x[k] = s.Phi @ x[k - 1] + s.B0 @ u[k - 1] + s.B1 @ u[k]
    y = x @ C.T + u @ D.T + offset
    bias = art.bias_evaluator().run(x, u)
    return ts, u, art.input_names, x, y, out_names, bias


def synthetic_imu_logs(out_dir, *, model=None, runs=None, temperature_dt_s: float = 1.0,
                       inertial_rate_hz: float = 20.0, clock_offset_s: float = 0.37,
                       inertial_noise=None, n_outliers: int = 5, outlier_size: float = 30.0,
                       power_w: float = 0.0, seed: int = 0) -> dict[str, SyntheticRun]:
    """Write a temperature log and an inertial log per run (see the module docstring).

    **Arguments:**

    - `out_dir`: folder to write into (created): `<run>_temperature.csv`,
      `<run>_inertial.csv`.
    - `model`: the truth, a model file path or `ModelSpec` with fitted bias coefficients
      (default `EXAMPLE_TRUTH`, the packaged copy of the repository's
      `configs/imu6_bias.toml`; the built-in `imu6` is not enough: it has no bias channel).
    - `runs`: name -> programme (see `CALIBRATION_PROGRAMME`) or (programme, use); default
      `EXAMPLE_RUNS`.
    - `temperature_dt_s`: temperature-log period, s.
    - `inertial_rate_hz`: inertial-log rate, Hz.
    - `clock_offset_s`: the inertial log's first sample is this much after the
      temperature log's, s.
    - `inertial_noise`: column -> white-noise std per inertial sample (column unit);
      default 10 × the model's `noise` of the channel (a 20 Hz raw stream is noisier than
      the filtered one the model's noise describes).
    - `n_outliers`, `outlier_size`: spikes per channel and their size in noise stds.
    - `power_w`: constant power on every heat input, W (0: the unit at rest; steady
      state is then uniform, so a plateau's sensor reading is the proof-mass
      temperature).
    - `seed`: random seed.

    **Returns:** run name -> `SyntheticRun`.
    """
    from ..measurements._telemetry import write_telemetry
    from ..model._model_file import load_model

    if model is None:
        model = EXAMPLE_TRUTH
    spec = load_model(model) if not hasattr(model, "biases") else model
    if not spec.biases or any(b.coefficients is None for b in spec.biases):
        raise InputError("the truth model needs bias channels with coefficients.",
                         file=str(model), field="biases")
    runs = EXAMPLE_RUNS if runs is None else runs
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    written = {}
    truth = _artifact(spec, temperature_dt_s)
    for name, item in runs.items():
        programme = item[0] if isinstance(item[0][0], tuple) else item
        ts, u, in_names, x, y, out_names, bias = _truth(truth, programme, temperature_dt_s,
                                                        power_w)
        noise = {sn.column: (sn.noise.value if sn.noise is not None else 0.01)
                 for sn in spec.sensors}
        channels = {c: u[:, j] for j, c in enumerate(in_names)}
        channels.update({c: y[:, j] + noise[c] * rng.standard_normal(ts.size)
                         for j, c in enumerate(out_names)})
        t_file = out / f"{name}_temperature.csv"
        write_telemetry(t_file, ts, channels, comments=[
            f"written by thermojax synthetic_imu_logs: run '{name}', truth '{spec.name}', "
            f"temperature log every {temperature_dt_s:g} s, seed {seed}"])
        t_in = np.arange(clock_offset_s, ts[-1], 1.0 / inertial_rate_hz)
        inertial, rows = {}, {}
        for j, b in enumerate(spec.biases):
            std = (inertial_noise or {}).get(
                b.column, 10.0 * (b.noise.value if b.noise is not None else 1.0))
            v = np.interp(t_in, ts, bias[:, j]) + std * rng.standard_normal(t_in.size)
            k = np.sort(rng.choice(np.arange(10, t_in.size - 10), n_outliers, replace=False))
            v[k] += outlier_size * std * rng.choice([-1.0, 1.0], k.size)
            inertial[b.column], rows[b.column] = v, k
        i_file = out / f"{name}_inertial.csv"
        write_telemetry(i_file, t_in, inertial, comments=[
            f"written by thermojax synthetic_imu_logs: run '{name}', inertial log at "
            f"{inertial_rate_hz:g} Hz, clock offset {clock_offset_s:g} s, {n_outliers} "
            "outliers per channel"])
        written[name] = SyntheticRun(name, t_file, i_file, ts, x,
                                     {b.column: bias[:, j] for j, b in enumerate(spec.biases)},
                                     rows)
    return written


def write_example_config(out_dir) -> Path:
    """Write the example calibration config and its start model into `out_dir`, beside
    the logs `synthetic_imu_logs(out_dir)` writes (the config's runs are read from the
    same folder). Returns the config's path."""
    out = Path(out_dir)
    text = (EXAMPLE_FOLDER / "imu6_bias.toml").read_text(encoding="utf-8")
    config = out / "imu6_bias.toml"
    config.write_text(text.replace('"data/', '"'), encoding="utf-8")
    start = "imu6_bias_start.toml"
    (out / start).write_text((EXAMPLE_FOLDER / start).read_text(encoding="utf-8"),
                             encoding="utf-8")
    return config
