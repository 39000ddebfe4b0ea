"""Export a model's observer as a versioned artifact a firmware engineer can run and trust.

`export_observer` samples the model at the observer rate, designs one gain per nonempty
sensor subset (the fault fallback of `thermojax.reference`), and writes into a folder:

- `observer.json`: metadata (`"schema": 1`, `"thermojax_version"`, the model, the rate,
  state/input/output names and units, the hold of each input, plausibility limits,
  fault settings, the fixed-point format and scales, bias coefficients, and for a model
  with nonlinear effects the operating point of its linearization);
- `observer.npz`: the arrays (`Phi`, `B0`, `B1`, `C`, `D`, `gain_table`, the offsets, and
  for bias channels with rate terms `bias_rate_nodes`, `bias_rate_A`, `bias_rate_B`: the
  rows of the continuous model `A_c`, `B_c` giving those nodes' exact `dT/dt`);
- `tj_observer.c`/`.h` (the float64 build) and, with `fixed`, `tj_observer_<fmt>.c`/`.h`
  (the fixed-point build), each with a playback harness `*_main.c`.

`thermojax.reference.load_observer` reads the artifact back (NumPy only) and checks it.

Coordinates: states, inputs and readings are physical (°C, W) in every artifact. A model
with nonlinear effects (radiation, temperature-dependent conductance or capacitance) is
linearized at a uniform temperature `T_op` with zero power. Its heat flows vanish at every
uniform temperature, so the linearization has no constant term and every uniform
temperature (35 °C, the fixed-point reference, included) stays an equilibrium.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import warnings
from fractions import Fraction
from pathlib import Path

import numpy as np

from .._errors import InputError
from ..reference._artifact_checks import HASH_FIELD, content_hash
from ._input_scale import representable_input_scale
from ._linearize import linearize as _linearize

SCHEMA = 1
LIMITS = (-55.0, 125.0)       # °C, plausibility limits (the seed)
ABSOLUTE_ZERO_C = -273.15      # °C, the lowest operating point accepted
T_REF = 35.0                  # °C, fixed-point reference: middle of −55…+125 °C
FLOAT_PREFIX = "tj_observer"


@dataclasses.dataclass(frozen=True)
class ExportResult:
    """What `export_observer` wrote and found.

    - `folder`: the artifact folder.
    - `files`: file name → size in bytes.
    - `metadata`: the contents of `observer.json`.
    - `arrays`: the contents of `observer.npz`.
    - `warnings`: the warnings raised (also issued with `warnings.warn`).
    """

    folder: Path
    files: dict
    metadata: dict
    arrays: dict
    warnings: tuple


def _load_spec(spec_or_model):
    from ..model._model import ThermalModel
    from ..model._model_file import load_model
    from ..model._spec import ModelSpec

    if isinstance(spec_or_model, (str, Path)):
        spec = load_model(spec_or_model)
        return spec, ThermalModel.from_spec(spec), str(spec_or_model)
    if isinstance(spec_or_model, ModelSpec):
        return spec_or_model, ThermalModel.from_spec(spec_or_model), \
            str(getattr(spec_or_model, "source", None) or spec_or_model.name)
    if isinstance(spec_or_model, ThermalModel):
        return None, spec_or_model, "model"
    raise TypeError("`export_observer(spec_or_model=...)` takes a model file path, a "
                    f"`ModelSpec` or a `ThermalModel`, got {type(spec_or_model).__name__}.")


def _gain(discrete_full, system_c, rows, dt, method, noise, q, names, speedup):
    """The filter-form gain for sensor rows `rows` (the same steps as `design_observer`)."""
    import equinox as eqx
    import jax.numpy as jnp

    from ..dynamics._discretize import discretize
    from ._kalman import discrete_process_covariance, steady_state_kalman
    from ._pole_placement import observer_poles, place_observer_gain

    idx = jnp.asarray(np.array(rows, dtype=int))
    sub = eqx.tree_at(lambda s: (s.C, s.D), system_c, (system_c.C[idx], system_c.D[idx]))
    discrete = discretize(sub, dt)
    if method == "kalman":
        Qd = discrete_process_covariance(sub.A, q, dt)
        return np.asarray(steady_state_kalman(discrete, Qd, noise[rows] ** 2).gain)
    poles = observer_poles(sub, dt, speedup)
    return np.asarray(place_observer_gain(discrete, poles, state_names=names))


def export_observer(spec_or_model, rate_hz: float, out_dir, fixed=None, method: str = "kalman",
                    sensors=None, operating_point: float = 25.0, speedup: float = 4.0,
                    faults=None, power_scale: float = 1.0, c_float: str = "float64",
                    c_layout: str = "rows", reconstruct: str | None = None,
                    input_noise: float | None = None,
                    inertial_rate_hz: float | None = None,
                    adaptive: dict | None = None,
                    schedule: dict | None = None,
                    trim: dict | None = None) -> ExportResult:
    """Write the reference-observer artifact of a model (see the module docstring).

    The full sensor set must observe every state (else `InputError` naming the lost
    states and the sensor that would restore them). Each nonempty subset gets its own
    gain by `method`; a subset whose poles cannot be placed falls back to the Kalman gain
    (recorded in `observer.json`). Every gain must give stable error dynamics
    `(I − L C) Phi` at this rate, also after quantization with `fixed`.

    **Arguments:**

    - `spec_or_model`: a model file path, a `ModelSpec` (bias channels exported) or a
      `ThermalModel`.
    - `rate_hz`: the observer rate (Hz); the sample period is `1 / rate_hz` (exactly,
      when `rate_hz` is a `fractions.Fraction`: `Fraction(1, 1800)` records 1800 s).
    - `out_dir`: the folder to write (created; existing files of the same names replaced).
    - `fixed`: `None`, `"q16.16"`, `"q8.24"`, `"q15"`, `"q31"` or a
      `thermojax.reference.FixedFormat`.
    - `method`: `"kalman"` (steady-state Kalman gains) or `"poles"` (4× the open-loop poles).
    - `sensors`: sensor column names to use (default all).
    - `operating_point`: `T_op` (°C) of the linearization of a nonlinear model.
    - `speedup`: observer poles × open-loop poles for `method="poles"`.
    - `faults`: a `thermojax.reference.FaultConfig` (default: limits −55…+125 °C).
    - `power_scale`: W per format unit of a power input in the fixed build.
    - `c_float`: `"float64"` (default) or `"float32"`, the word of the float C build.
    - `c_layout`: `"rows"` (default, straight-line, any core) or `"columns"`
      (column-at-a-time sums and lane-parallel supervision for SIMD cores), the float C
      build's layout (`thermojax.reference.generate_c`).
    - `reconstruct`, `input_noise`: lag compensation (`thermojax compensate` in firmware):
      the temperature input `reconstruct` (a column name) becomes the observer's last
      state, a random walk of diffusion `input_noise` °C/√s (Kalman gains only); the
      artifact's inputs are the others. A sensor subset that does not see it holds its
      estimate (zero gain on that state; recorded in `subsets`).
    - `inertial_rate_hz`: with bias channels, also write the multi-rate split
      (`tj_multirate.c`/`.h`: double buffer and interpolation at this rate, an integer
      multiple of `rate_hz`; `thermojax.reference.generate_multirate_c`).
    - `adaptive`: `{"tracked": [conductance names], "drift": per √s, "ceiling": relative
      std}`: also write the firmware adaptive filter (`tj_adaptive.c`/`.h`, docs/observer.md
      §11) at this rate, on the model's inputs and every sensor, its design in
      `observer.json` `"adaptive"`.
    - `schedule`: `{"points": [°C, ...], "by": sensor column}`: also write the
      gain-scheduled observer of a nonlinear model (`tj_scheduled.c`/`.h`, docs/observer.md
      §12), its matrices in `observer.npz` (`schedule_*`), `observer.json` `"schedule"`.
    - `trim`: `{"file": trim file path, "factors": a unit's factors (in the file's order,
      or by name) or None}`: also write
      the end-of-line trimmed observer (`tj_trimmed.c`/`.h`, docs/observer.md §13) over the
      trim file's grid, its matrices in `observer.npz` (`trim_*`), `observer.json`
      `"trim"`; with `factors`, the unit's factor table `tj_trimmed_unit.c`.

    **Returns:** an `ExportResult`. Warnings (a nonlinear effect linearized, a coefficient
    that rounds to zero in the fixed format) are issued with `warnings.warn` and listed.
    """
    import equinox as eqx
    import jax.numpy as jnp

    from .. import __version__
    from .. import reference as ref
    from ..dynamics._discretize import discretize
    from ..model.effects import KINDS
    from ._design import METHODS, _sensor_rows
    from ._observability import observability_rank
    from ._pole_placement import check_observable

    if method not in METHODS:
        raise InputError(f"unknown method {method!r}; expected one of {list(METHODS)}.",
                         field="--method")
    exact = rate_hz if isinstance(rate_hz, Fraction) else None
    try:
        rate_hz = float(rate_hz)
    except (TypeError, ValueError):
        raise InputError(f"expected a number of Hz, got {rate_hz!r}.", field="--rate") from None
    if not np.isfinite(rate_hz) or rate_hz <= 0:
        raise InputError(f"the observer rate must be a positive number of Hz, got {rate_hz}.",
                         field="--rate")
    # an exact rate (1/1800 Hz) records its exact period (1800 s, not 1799.9999999999998)
    dt = float(1 / exact) if exact is not None else 1.0 / rate_hz
    try:
        operating_point = float(operating_point)
    except (TypeError, ValueError):
        raise InputError(f"expected a temperature in °C, got {operating_point!r}.",
                         field="--operating-point") from None
    if not np.isfinite(operating_point) or operating_point < ABSOLUTE_ZERO_C:
        raise InputError(f"the operating point must be a finite temperature in °C at or above "
                         f"absolute zero ({ABSOLUTE_ZERO_C} °C), got {operating_point:g}.",
                         field="--operating-point")
    spec, model, where = _load_spec(spec_or_model)
    faults = ref.FaultConfig(limits=LIMITS) if faults is None else faults
    fmt = None if fixed is None else _format(fixed)
    caught: list[str] = []

    def warn(text):
        caught.append(text)
        warnings.warn(text, stacklevel=3)

    net = model.network
    t = net.topology
    names, inputs, all_sensors = t.node_names, t.input_names, t.sensor_names
    power_inputs = set(t.heat_inputs)
    rows = _sensor_rows(sensors, all_sensors)
    sensor_names = [all_sensors[i] for i in rows]
    p = len(rows)
    if p > 8:
        raise InputError(f"{p} sensors; the gain table of the reference (one gain per sensor "
                         "subset) is limited to 8. Choose sensors with --sensor.",
                         file=where, field="--sensor")

    system = model.linear_system()
    idx = jnp.asarray(np.array(rows, dtype=int))
    system = eqx.tree_at(lambda s: (s.C, s.D), system, (system.C[idx], system.D[idx]))
    linearization = None
    if model.is_nonlinear:
        A, B, x_op, u_op = _linearize(model, system, power_inputs, float(operating_point), where)
        system = eqx.tree_at(lambda s: (s.A, s.B), system, (A, B))
        effects = [e.key for e in (spec.effects if spec is not None else ())
                   if KINDS[e.kind].nonlinear] or \
            [f"{tm.kind}" for tm in model.effect_terms if KINDS[tm.kind].nonlinear]
        linearization = {"operating_point_C": float(operating_point),
                         "states_C": x_op.tolist(), "inputs": u_op.tolist(),
                         "effects": effects}
        warn(f"model '{where}' has nonlinear effect(s) {', '.join(effects)}: the exported "
             f"observer is its linearization at a uniform {operating_point:g} °C with no "
             "power, accurate near that temperature only.")
    q = np.asarray(model.process_noise, float)
    held = None   # the reconstructed input's state: no eigenvalue, held where unobserved
    if reconstruct is not None:
        system_plain = system
        system, names, inputs, power_inputs, q, held, holds = _augment(
            system, names, inputs, power_inputs, q, reconstruct, input_noise, method, where)
    else:
        holds = t.input_holds
    discrete = discretize(system, dt)
    Phi, B0, B1, C, D = (np.asarray(a, float) for a in
                         (discrete.Phi, discrete.B0, discrete.B1, discrete.C, discrete.D))
    call = f"export --sensor {' '.join(sensor_names)}"
    A_c = np.asarray(system.A, float)
    eig = np.linalg.eigvals(A_c if held is None else A_c[:held, :held])
    tau = np.sort(-1.0 / eig.real)
    if observability_rank(discrete) < len(names):
        fast = discretize(system, tau[0] / 10)   # a period that resolves every mode
        try:
            check_observable(fast, names, call)          # the sensors themselves
        except InputError as err:
            raise InputError(str(err), file=where, field="--sensor") from None
        if dt < tau[0] / 10:
            # observable at a moderate rate, not at this one: a sample moves the state so
            # little that the blocks C Phi^k of the observability test agree to roundoff
            raise InputError(f"the rate {rate_hz:g} Hz is implausibly high: one sample (dt "
                             f"{dt:g} s) is {dt / tau[0]:.2g} of the fastest time constant "
                             f"({tau[0]:.3g} s) and {dt / tau[-1]:.2g} of the slowest "
                             f"({tau[-1]:.3g} s), so the sampled state matrix is the "
                             "identity to within that and successive samples differ by less "
                             "than float64 arithmetic resolves: the states cannot be told "
                             "apart from the sensors. The same sensors observe every state "
                             f"at {10 / tau[0]:.3g} Hz; lower --rate.",
                             file=where, field="--rate")
        # observable at a fast rate: the sampling loses the modes
        raise InputError(f"at {rate_hz:g} Hz (dt {dt:g} s) the sampled observer cannot see "
                         f"every state: the fastest time constants ({', '.join(f'{v:.3g}' for v in tau[:3])} s) "
                         "decay to nothing within one sample, so its poles cannot be placed "
                         "and the estimate of those states is not corrected. Raise the rate.",
                         file=where, field="--rate")

    noise = np.asarray(model.noise, float)[rows]
    gains, subset_info = {}, []
    for r in range(1, p + 1):
        for s in itertools.combinations(range(p), r):
            s = list(s)
            used = method
            try:
                L = _gain(discrete, system, s, dt, method, noise, q, names, speedup)
            except InputError as err:
                if held is not None and r < p:   # these sensors do not see the input
                    L = np.vstack([_gain(None, system_plain, s, dt, "kalman", noise,
                                         q[:held], names[:held], speedup),
                                   np.zeros((1, len(s)))])
                    used = (f"kalman, {names[held]} held (these sensors do not observe it: "
                            f"{err})")
                    gains[tuple(s)] = L
                    rho = float(np.abs(np.linalg.eigvals(
                        ((np.eye(len(names)) - L @ C[s]) @ Phi)[:held, :held])).max())
                    subset_info.append({"sensors": [sensor_names[j] for j in s],
                                        "mask": int(sum(1 << j for j in s)), "method": used,
                                        "spectral_radius": rho,
                                        "observable_states": int(observability_rank(
                                            _Pair(Phi, C[s])))})
                    continue
                if r == p:
                    raise InputError(f"at {rate_hz:g} Hz (dt {dt:g} s) no observer gain: {err}",
                                     file=where, field="--rate") from None
                used = f"kalman (poles not placed: {err})"
                L = _gain(discrete, system, s, dt, "kalman", noise, q, names, speedup)
            gains[tuple(s)] = L
            Ae = (np.eye(len(names)) - L @ C[s]) @ Phi
            rho = float(np.abs(np.linalg.eigvals(Ae)).max())
            sub = _Pair(Phi, C[s])
            subset_info.append({"sensors": [sensor_names[j] for j in s],
                                "mask": int(sum(1 << j for j in s)), "method": used,
                                "spectral_radius": rho,
                                "observable_states": int(observability_rank(sub))})
            if not rho < 1.0:
                raise InputError(f"at {rate_hz:g} Hz (dt {dt:g} s) the observer with sensors "
                                 f"{[sensor_names[j] for j in s]} is unstable (error-dynamics "
                                 f"spectral radius {rho:.6g} >= 1); change the rate.",
                                 file=where, field="--rate")
    obs_system = ref.ObserverSystem.build(Phi, B0, B1, C, D, gains)
    if faults.input_limits is None:   # temperatures: the plausibility limits; powers: derived
        derived = faults.input_limits_array(obs_system)
        faults = dataclasses.replace(faults, input_limits=[
            derived[j].tolist() if j in power_inputs else list(faults.limits)
            for j in range(len(inputs))])

    # references of the fixed-point representation (also useful to a float build)
    m = len(inputs)
    x_ref = np.full(len(names), T_REF)
    u_ref = np.array([0.0 if j in power_inputs else T_REF for j in range(m)])
    y_ref = C @ x_ref + D @ u_ref
    u0 = np.array([0.0 if j in power_inputs else float(operating_point) for j in range(m)])
    if held is None:
        x_steady = np.asarray(system.steady_state(jnp.asarray(u0)))
    else:   # the steady state with the reconstructed input at the operating point too
        u_all = np.insert(u0, reconstructed_index(t.input_names, reconstruct),
                          float(operating_point))
        x_steady = np.append(np.asarray(system_plain.steady_state(jnp.asarray(u_all))),
                             float(operating_point))
    arrays = {"Phi": Phi, "B0": B0, "B1": B1, "C": C, "D": D,
              "gain_table": obs_system.gain_table, "x_ref": x_ref, "u_ref": u_ref,
              "y_ref": y_ref, "u_steady": u0, "x_steady": x_steady,
              "output_offset": np.asarray(model.output_offset(), float)[rows]}
    biases = _biases(spec)
    rate_nodes = sorted({names.index(r) for b in biases for r in b["rates"]})
    if rate_nodes:   # rows of the continuous model for the exact dT/dt of rate terms
        arrays["bias_rate_nodes"] = np.array(rate_nodes, dtype=np.int64)
        arrays["bias_rate_A"] = A_c[rate_nodes]
        arrays["bias_rate_B"] = np.asarray(system.B, float)[rate_nodes]
    bias_eval = None
    channels = ref.bias_channels_from_metadata(biases, list(names))
    if channels:  # evaluated by the reference observers and the generated C
        rows_ = arrays.get("bias_rate_nodes")
        bias_eval = ref.BiasEvaluator(channels, dt, arrays.get("bias_rate_A"),
                                      arrays.get("bias_rate_B"), rows_)
    fixed_meta = None
    fixed_obs = None
    if fmt is not None:
        u_scale = np.array([power_scale if j in power_inputs else fmt.state_scale
                            for j in range(m)])
        # the input limits inside the codes' range, or the format refused (_input_scale)
        u_scale, unrepresentable = representable_input_scale(
            u_scale, u_ref, faults.input_limits_array(obs_system), fmt, power_inputs, inputs,
            scale_given=power_scale != 1.0, where=where)
        scaling = ref.FixedScaling(x_ref, y_ref, u_ref, u_scale)
        try:
            fixed_obs = ref.FixedObserver(obs_system, fmt, scaling, faults, biases=bias_eval)
        except ValueError as err:
            raise InputError(str(err), file=where, field="--fixed") from None
        if unrepresentable is not None:
            raise unrepresentable
        arrays["u_scale"] = u_scale
        for name in fixed_obs.MATRICES:
            arrays[f"fixed_{name}"] = fixed_obs.coef[name]
        fixed_meta = {"format": fmt.name, "word_bits": fmt.word_bits,
                      "frac_bits": fmt.frac_bits, "state_scale_K": fmt.state_scale,
                      "lsb_K": fmt.lsb, "state_range_K": list(fmt.state_range),
                      "reference_C": T_REF, "input_scale": u_scale.tolist(),
                      "coefficient_frac_bits": {k: int(v) for k, v in fixed_obs.coef_frac.items()},
                      "representation": "value = reference + code * 2**-frac_bits * scale"}
        _check_fixed(fixed_obs, obs_system, np.asarray(system.A), np.asarray(system.B), names,
                     inputs, sensor_names, rate_hz, dt, where, warn, held)
        fixed_meta["error_bound"] = _error_bound(fixed_obs, faults, u_ref, power_inputs, names)

    meta = {
        "schema": SCHEMA, "thermojax_version": __version__,
        "model": model_name(spec, where), "model_file": where,
        "rate_hz": rate_hz, "dt_s": dt, "method": method,
        "states": [{"name": nm, "units": "°C"} for nm in names],
        "inputs": [{"name": nm, "units": "W" if j in power_inputs else "°C",
                    "hold": holds[j]} for j, nm in enumerate(inputs)],
        "outputs": [{"name": nm, "units": "°C"} for nm in sensor_names],
        "form": "filter: x⁻[k] = Phi x[k-1] + B0 u[k-1] + B1 u[k]; "
                "x[k] = x⁻[k] + L_S (y[k] - C x⁻[k] - D u[k]); readings minus output_offset",
        "gain_table": "gain_table[mask] is the gain when exactly the sensors whose bit is "
                      "set in mask are in use (bit j: outputs[j]); mask 0: prediction only",
        "subsets": subset_info,
        "design": _design_record(method, q, noise, sensor_names, names, dt, speedup,
                                 system, held),
        "plausibility_limits_C": list(faults.limits),
        "faults": {"limits_C": list(faults.limits),
                   "rails_C": _finite_or_none(faults.rails_array(p)),
                   "residual_threshold_K": _finite_or_none(faults.threshold_array(p)),
                   "wire_break_after": int(faults.wire_break_after),
                   "recover_after": int(faults.recover_after),
                   "gate": bool(faults.gate),
                   "input_limits": _finite_or_none(faults.input_limits_array(obs_system))},
        "fixed": fixed_meta,
        "biases": biases,
        "linearization": linearization,
        "warnings": caught,
        "c_build": {"float": c_float, "layout": c_layout},
        "reconstruct": None if held is None else {
            "input": names[held], "state_index": held, "input_noise_C_per_sqrt_s":
            float(input_noise),
            "model": "the input as a random walk (d u = input_noise dβ), held between "
                     "samples; its estimate is state x[state_index]"},
    }
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    meta["files"] = {}
    c_names = (list(names), list(inputs), list(sensor_names))
    sources = [ref.generate_c(ref.FloatObserver(obs_system, faults, dtype=np.dtype(c_float),
                                                biases=bias_eval),
                              FLOAT_PREFIX, c_names, layout=c_layout)]
    if fixed_obs is not None:
        sources.append(ref.generate_c(fixed_obs, fixed_prefix(fmt.name), c_names))
    meta["multirate"] = None
    if inertial_rate_hz is not None:
        ratio = _ratio(inertial_rate_hz, rate_hz, bias_eval, where)
        sources.append(ref.generate_multirate_c(MULTIRATE_PREFIX, bias_eval.n_channels, ratio))
        meta["multirate"] = {"inertial_rate_hz": float(inertial_rate_hz), "ratio": ratio,
                             "bias_channels": [ch["column"] for ch in biases
                                               if ch["coefficients"] is not None],
                             "use": f"after each {FLOAT_PREFIX}_step: {MULTIRATE_PREFIX}_publish("
                                    f"{FLOAT_PREFIX}_bias); every inertial tick: "
                                    f"{MULTIRATE_PREFIX}_tick()", "fixed": None}
        if fixed_obs is not None:   # the fixed build's int32 bias codes, ramped in integers
            mr_fixed, obs_fixed = multirate_prefix(fmt.name), fixed_prefix(fmt.name)
            sources.append(ref.generate_multirate_c(mr_fixed, bias_eval.n_channels, ratio,
                                                    word="int32_t"))
            meta["multirate"]["fixed"] = {
                "prefix": mr_fixed, "word": "int32_t",
                "bias_frac_bits": [int(g) for g in fixed_obs.biases.g],
                "use": f"after each {obs_fixed}_step: {mr_fixed}_publish({obs_fixed}_bias); "
                       f"every inertial tick: {mr_fixed}_tick() (int32 bias codes: value = "
                       "code * 2**-bias_frac_bits[channel])"}
    meta["schedule"] = None
    if schedule is not None:
        sources.append(_scheduled_source(spec, rate_hz, schedule, where, meta, arrays))
    meta["trim"] = None
    if trim is not None:
        sources.append(_trimmed_source(spec, rate_hz, trim, where, meta, arrays))
    meta["adaptive"] = None
    if adaptive is not None:
        sources.append(_adaptive_source(spec, model, adaptive, dt, where, meta))
    for src in sources:
        for key, path in src.write(out).items():
            meta["files"][path.name] = key
    meta["files"]["observer.npz"] = "arrays"
    np.savez(out / "observer.npz", **arrays)
    # verified by every load (reference._artifact_checks): a modified artifact is refused
    meta[HASH_FIELD] = content_hash(meta, dict(np.load(out / "observer.npz")))
    (out / "observer.json").write_text(json.dumps(meta, indent=2, ensure_ascii=False) + "\n",
                                       encoding="utf-8")
    files = {f: (out / f).stat().st_size for f in [*meta["files"], "observer.json"]}
    return ExportResult(out, files, meta, arrays, tuple(caught))


def reconstructed_index(input_names, column) -> int:
    return list(input_names).index(column)


def _augment(system, names, inputs, power_inputs, q, column, input_noise, method, where):
    """The system with input `column` as its last state (`augment_unknown_input`), and
    the names, inputs, power inputs, process noises and holds that go with it."""
    from ._input_reconstruction import augment_unknown_input

    field = "--reconstruct"
    if column not in inputs:
        raise InputError(f"'{column}' is not an input of the model; its inputs are "
                         f"{list(inputs)}.", file=where, field=field)
    j = reconstructed_index(inputs, column)
    if j in power_inputs:
        raise InputError(f"'{column}' is a heat input (W); the exported observer "
                         "reconstructs a temperature input only (its state is stored like "
                         "the others, as °C). `thermojax compensate` reconstructs powers.",
                         file=where, field=field)
    if method != "kalman":
        raise InputError("a reconstructed input is a random walk without a pole to move: "
                         "its gains are Kalman gains; drop --method poles.",
                         file=where, field="--method")
    if input_noise is None or not np.isfinite(input_noise) or input_noise <= 0:
        raise InputError("--reconstruct needs --input-noise Q (°C/√s, > 0): the input's "
                         "random-walk diffusion, the speed/noise trade-off. `thermojax "
                         "compensate` on a log chooses it by maximum likelihood and prints it.",
                         file=where, field="--input-noise")
    rest = [i for i in range(len(inputs)) if i != j]
    aug = augment_unknown_input(system, j)
    return (aug, (*names, column), tuple(inputs[i] for i in rest),
            {k for k, i in enumerate(rest) if i in power_inputs},
            np.append(q, float(input_noise)), len(names), aug.holds)


MULTIRATE_PREFIX = "tj_multirate"
ADAPTIVE_PREFIX = "tj_adaptive"
SCHEDULED_PREFIX = "tj_scheduled"
TRIMMED_PREFIX = "tj_trimmed"


def _scheduled_source(spec, rate_hz, schedule: dict, where, meta, arrays):
    """The gain-scheduled observer's C; its matrices into `arrays`, its facts into
    `meta["schedule"]`."""
    from .. import reference as ref
    from ._schedule import scheduled_design

    if spec is None:
        raise InputError("the gain schedule is designed from a model file; export a model "
                         "file, not a ThermalModel.", file=where, field="--schedule")
    design = scheduled_design(spec, rate_hz, schedule["points"], schedule["by"], where)
    for name in ("points", "Phi", "B0", "B1", "L", "C", "D"):
        arrays[f"schedule_{name}"] = np.asarray(getattr(design, name), float)
    meta["schedule"] = {
        "prefix": SCHEDULED_PREFIX, "by": schedule["by"], "by_index": int(design.by),
        "points_C": [float(v) for v in design.points],
        "inputs": list(spec.input_columns), "sensors": list(spec.sensor_columns),
        "use": f"every step: {SCHEDULED_PREFIX}_step(u, y); the matrices and gains are "
               f"interpolated linearly at the reading of {schedule['by']} (clamped to the "
               "points, held while it is not finite)"}
    return ref.generate_scheduled_c(design, SCHEDULED_PREFIX,  # the artifact's limits
                                    reading_limits=tuple(meta["faults"]["limits_C"]))


def _trimmed_source(spec, rate_hz, trim: dict, where, meta, arrays):
    """The end-of-line trimmed observer's C (and the unit's factor table when `trim`
    has factors); its matrices into `arrays`, its facts into `meta["trim"]`."""
    from .. import reference as ref
    from ._trim import load_trim_plan, trim_design, unit_design

    if spec is None:
        raise InputError("the trim is designed from a model file; export a model file, not a "
                         "ThermalModel.", file=where, field="--trim")
    plan = load_trim_plan(trim["file"], spec)
    design = trim_design(spec, rate_hz, plan, where)
    arrays["trim_grid"] = np.concatenate([np.asarray(g, float) for g in design.grids])
    arrays["trim_sizes"] = np.array([len(g) for g in design.grids], dtype=np.int64)
    for name in ("Phi", "B0", "B1", "L", "C", "D"):
        arrays[f"trim_{name}"] = np.asarray(getattr(design, name), float)
    unit = None
    src = ref.generate_trimmed_c(design, TRIMMED_PREFIX,  # the artifact's limits
                                 reading_limits=tuple(meta["faults"]["limits_C"]))
    if trim.get("factors") is not None:
        values = trim["factors"]
        if isinstance(values, dict):   # by name, as `thermojax trim` writes them
            missing = [n for n in plan.names if n not in values]
            if missing:
                raise InputError(f"has no factor {missing} of the trim file {trim['file']} "
                                 f"(it has {sorted(values)}): estimate them with this trim "
                                 "file.", file=str(trim.get("factors_file", where)),
                                 field="--trim-factors")
            values = [values[n] for n in plan.names]
        values = np.asarray(values, float)
        if values.shape != (len(plan.factors),) or not np.all(np.isfinite(values)):
            raise InputError(f"{values.size} trim factors for the trim file's "
                             f"{len(plan.factors)} ({', '.join(plan.names)}), or one not "
                             "finite.", file=str(trim.get("factors_file", where)),
                             field="--trim-factors")
        # the interpolation's error at this unit: against its exact design
        exact = unit_design(spec, rate_hz, plan, values)
        got = ref.trim_matrices(design, values)
        worst = {k: float(np.max(np.abs(np.asarray(got.matrices[k]) - exact[k])))
                 for k in ("Phi", "B0", "B1", "L")}
        outside = [n for n, v, g in zip(plan.names, values, design.grids)
                   if not g[0] <= v <= g[-1]]
        if outside:
            warnings.warn(f"the unit's factors {outside} lie outside the trim grid: the "
                          "firmware clamps them to its edge; widen the trim file's range.")
        unit = {"factors": values.tolist(), "file": f"{TRIMMED_PREFIX}_unit.c",
                "interpolation_error": worst}
    meta["trim"] = {
        "prefix": TRIMMED_PREFIX, "trim_file": str(trim["file"]),
        "factors": [{"name": f.name, "parameters": list(f.parameters), "grid": list(f.grid)}
                    for f in plan.factors],
        "inputs": list(spec.input_columns), "sensors": list(spec.sensor_columns),
        "unit": unit,
        "use": f"at start-up: {TRIMMED_PREFIX}_init({TRIMMED_PREFIX}_unit_factors) (the "
               "unit's table in flash; a factor that is not finite counts as 1), then "
               f"{TRIMMED_PREFIX}_reset(x0); every step: {TRIMMED_PREFIX}_step(u, y)"}
    if unit is not None:
        src = dataclasses.replace(src, unit=ref.unit_factor_table(
            design, unit["factors"], TRIMMED_PREFIX, note=f"From {trim.get('factors_file')}."))
    return src


def _adaptive_source(spec, model, adaptive: dict, dt: float, where, meta):
    """The adaptive filter's C source; its design recorded in `meta["adaptive"]`."""
    from .. import reference as ref
    from ._adaptive import adaptive_design

    if spec is None:
        raise InputError("the adaptive filter is designed from a model file (its named "
                         "conductances); export a model file, not a ThermalModel.",
                         file=where, field="--adaptive")
    if model.is_nonlinear:
        raise InputError("the adaptive filter tracks conductances of a linear network; this "
                         "model has nonlinear effects.", file=where, field="--adaptive")
    try:
        design = adaptive_design(spec, list(adaptive["tracked"]), dt, adaptive["drift"],
                                 ceiling=adaptive.get("ceiling", 0.5))
    except InputError as err:
        raise InputError(err.message, file=where, field="--adaptive") from None
    meta["adaptive"] = {"prefix": ADAPTIVE_PREFIX, "tracked": list(adaptive["tracked"]),
                        "inputs": list(spec.input_columns),
                        "sensors": list(spec.sensor_columns),
                        "design": dataclasses.asdict(design)}
    return ref.generate_adaptive_c(design, ADAPTIVE_PREFIX)


def multirate_prefix(fmt_name: str) -> str:
    """The C prefix of a fixed build's multi-rate split: `tj_multirate_q16_16`, ..."""
    return f"{MULTIRATE_PREFIX}_{fmt_name.replace('.', '_')}"


def _ratio(inertial_rate_hz, rate_hz, bias_eval, where) -> int:
    """Inertial ticks per observer step, an integer, for a model with bias channels."""
    if bias_eval is None:
        raise InputError("--inertial-rate interpolates bias corrections, and the model has no "
                         "bias channel with fitted coefficients ([[biases]], docs/formats.md "
                         "§4).", file=where, field="--inertial-rate")
    ratio = float(inertial_rate_hz) / rate_hz
    if not np.isfinite(ratio) or ratio < 1 or abs(ratio - round(ratio)) > 1e-9 * ratio:
        raise InputError(f"the inertial rate ({inertial_rate_hz:g} Hz) must be a whole multiple "
                         f"of the observer rate ({rate_hz:g} Hz).", file=where,
                         field="--inertial-rate")
    return int(round(ratio))


def fixed_prefix(fmt_name: str) -> str:
    """The C prefix of a fixed build: `tj_observer_q16_16`, `tj_observer_q8_24`, ..."""
    return f"{FLOAT_PREFIX}_{fmt_name.replace('.', '_')}"


def model_name(spec, where):
    return spec.name if spec is not None else where


def _format(fixed):
    from .. import reference as ref

    try:
        return ref.fixed_format(fixed)
    except ValueError:
        raise InputError(f"unknown fixed-point format {fixed!r}; expected one of "
                         f"{sorted(ref.FORMATS)}.", field="--fixed") from None


@dataclasses.dataclass(frozen=True)
class _Pair:
    Phi: np.ndarray
    C: np.ndarray


def _finite_or_none(a):
    return [[None if not np.isfinite(v) else float(v) for v in row] if np.ndim(row) else
            (None if not np.isfinite(row) else float(row)) for row in np.asarray(a, float)]


def _biases(spec) -> list:
    if spec is None or not spec.biases:
        return []
    out = []
    for b in spec.biases:
        visco = [{"time_constant_s": e.parameters["time_constant"].value,
                  "k": e.parameters["k"].value, "node": e.where[0]}
                 for e in spec.effects if e.kind == "viscoelastic" and e.where[1] == b.column]
        terms = [f"poly{i}" for i in range(b.order + 1)] + \
            [f"gradient {a}-{c}" for a, c in b.gradients] + [f"rate {r}" for r in b.rates]
        out.append({"column": b.column, "temperature": b.temperature, "order": b.order,
                    "polynomial_reference_C": 25.0,
                    "gradients": [list(g) for g in b.gradients], "rates": list(b.rates),
                    "terms": terms,
                    "coefficients": None if b.coefficients is None else list(b.coefficients),
                    "viscoelastic": visco,
                    "formula": "b = Σ c_p (T − 25)^p + Σ d_g (T_a − T_b) + Σ e_r dT_n/dt "
                               "+ Σ k_v (T_v − ε_v), dε_v/dt = (T_v − ε_v)/τ_v "
                               "(docs/formats.md §4)",
                    "evaluation": "thermojax.reference.BiasEvaluator, float64, from the "
                                  "corrected estimate x[k] and u[k]: dT_n/dt = "
                                  "bias_rate_A[i] x + bias_rate_B[i] u (i: the row of n in "
                                  "bias_rate_nodes); ε_v exact for T_v linear between "
                                  "samples, ε_v[0] = T_v[0]"})
    return out


def _design_record(method, q, noise, sensors, names, dt, speedup, system, held) -> dict:
    """The design's inputs as `observer.json` records them (docs/observer.md §4)."""
    out = {"method": method,
           "process_noise_C_per_sqrt_s": dict(zip(names, map(float, q))),
           "sensor_noise_C": dict(zip(sensors, map(float, noise))),
           "kalman": "Qc = diag(q²), Qd by Van Loan, P from the discrete Riccati equation, "
                     "L_S = P C_Sᵀ (C_S P C_Sᵀ + R)⁻¹ with R = diag(noise_S²)"}
    if method == "poles":
        from ._pole_placement import observer_poles

        poles = observer_poles(system, dt, speedup)
        out["poles"] = {"speedup": float(speedup), "min_time_constant_s": 5.0 * dt,
                        "rule": "s_i = speedup·λ_i; modes with −1/λ_i ≤ 5 dt kept; faster "
                                "than 1/(5 dt) capped there; repeats × 0.98",
                        "continuous_per_s": np.asarray(poles.continuous, float).tolist(),
                        "discrete": np.asarray(poles.discrete, float).tolist()}
    return out


def _error_bound(fx, faults, u_ref, power_inputs, names) -> dict:
    """The fixed build's guaranteed error against the exact float64 observer (all sensors
    in use, nothing saturated), with the envelopes it assumes: states and temperature
    inputs within the plausible range, powers within their input limits, residuals
    within the range's span."""
    from ..reference import quantization_error_bound

    lo, hi = faults.limits
    x_env = np.full(len(names), max(hi - T_REF, T_REF - lo))
    u_lim = np.asarray(faults.input_limits_array(fx.system), float) if hasattr(
        faults, "input_limits_array") else None
    u_env = np.array([max(abs(u_lim[j, 0] - u_ref[j]), abs(u_lim[j, 1] - u_ref[j]))
                      if u_lim is not None and j in power_inputs and np.all(np.isfinite(u_lim[j]))
                      else max(hi - T_REF, T_REF - lo) for j in range(len(u_ref))])
    r_env = np.full(fx.system.n_outputs, hi - lo)
    b = quantization_error_bound(fx, x_env, x_env, u_env, r_env)
    return {"bound_K": dict(zip(names, map(float, b.bound))), "max_K": float(b.bound.max()),
            "assumes": f"all sensors in use, no saturation, states within {lo:g}…{hi:g} °C "
                       f"(±{x_env[0]:g} K about {T_REF:g} °C), inputs within their limits, "
                       f"residuals within ±{hi - lo:g} K (docs/observer.md §7)"}


def _check_fixed(fx, system, A, B, names, inputs, sensors, rate_hz, dt, where, warn,
                 held=None) -> None:
    """Couplings the format rounds to zero (a warning) and stability after quantization.

    A coupling is an entry of `Phi`, `B0`, `B1` whose continuous counterpart (`A`, `B`) is
    nonzero (a link, a boundary, a heat input: not the tiny fill-in of the exponential),
    a nonzero entry of `C` or `D`, or a gain entry above 1e-3 of its column's largest."""
    labels = {"Phi": (names, names), "B0": (names, inputs), "B1": (names, inputs),
              "C": (sensors, names), "D": (sensors, inputs)}
    exact = {"Phi": system.Phi, "B0": system.B0, "B1": system.B1, "C": system.C,
             "D": system.D, "L": system.L}
    direct = {"Phi": (A != 0) & ~np.eye(len(names), dtype=bool), "B0": B != 0, "B1": B != 0,
              "C": system.C != 0, "D": system.D != 0}
    zeroed = []
    for name, (rows, cols) in labels.items():
        q = fx.coef[name]
        for i, j in zip(*np.nonzero(direct[name] & (exact[name] != 0) & (q == 0))):
            zeroed.append(f"{name}[{rows[i]}, {cols[j]}] = {exact[name][i, j]:.3g}")
    qL = fx.coef["L"][system.full_mask]
    big = np.abs(exact["L"]) >= 1e-3 * np.abs(exact["L"]).max(axis=0, keepdims=True)
    for i, j in zip(*np.nonzero(big & (exact["L"] != 0) & (qL == 0))):
        zeroed.append(f"L[{names[i]}, {sensors[j]}] = {exact['L'][i, j]:.3g}")
    if zeroed:
        shown = "; ".join(zeroed[:8]) + (f"; and {len(zeroed) - 8} more" if len(zeroed) > 8 else "")
        warn(f"fixed-point format {fx.fmt.name} (LSB {fx.fmt.lsb:.3g} K) rounds "
             f"{len(zeroed)} nonzero coefficient(s) to zero, losing those couplings: {shown}. "
             "Use a format with more fractional bits (q8.24) or a lower rate.")
    n = system.n_states
    for mask in range(1, system.full_mask + 1):
        Phi_q = fx.coef["Phi"] * 2.0 ** -fx.coef_frac["Phi"]
        C_q = fx.coef["C"] * 2.0 ** -fx.coef_frac["C"]
        L_q = fx.coef["L"][mask] * 2.0 ** -fx.coef_frac["L"]
        E = (np.eye(n) - L_q @ C_q) @ Phi_q
        if held is not None and not L_q[held].any():   # a subset that holds the input
            E = E[:held, :held]
        rho = float(np.abs(np.linalg.eigvals(E)).max())
        if not rho < 1.0:
            used = [sensors[j] for j in range(system.n_outputs) if mask >> j & 1]
            raise InputError(f"at {rate_hz:g} Hz (dt {dt:g} s) the {fx.fmt.name} observer with "
                             f"sensors {used} is unstable after quantizing its coefficients "
                             f"(spectral radius {rho:.6g} >= 1); use a lower rate or a format "
                             "with more fractional bits.", file=where, field="--fixed")
