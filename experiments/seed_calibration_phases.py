"""Study: the seed's multi-phase calibration profile, phase by phase.

Issue 13, item 4. The seed (tactical-IMU thermal observer) tabulates, for each phase of
its calibration profile, the parameter it identifies and the residual RMS bias:

| phase | profile | target | residual RMS |
|---|---|---|---|
| Static Soak | −40, +25, +85 °C dwells, 2 h each | static polynomial coefficients | 0.04 °/h |
| Slow Dynamic Ramp | 1 °C/min, −40…+85 °C | bulkhead-to-housing conductance | 0.08 °/h |
| Fast Thermal Shock | 10 °C/min step transients | silicon die thermal capacitance | 0.12 °/h |
| Viscoelastic Dwell | +85 °C step, 3 h soak | polymer relaxation strain states | 0.06 °/h |

Synthetic truth (`TRUTH` below):

- Thermal model: `configs/imu6.toml` (the thermal part of configs/imu6_bias.toml),
  constant ASIC power 0.05 W, sensors housing, PCB, ASIC with 0.01 °C white noise, 1 Hz.
- Gyro bias (°/h): configs/imu6_bias.toml's `gyro_x_dph` channel plus one strain state:
  `b = 0.5 + 0.03 Δ + 5e-4 Δ² − 2e-6 Δ³ (Δ = T_pm − 25 °C) + 0.8 (T_mems − T_asic)
  + 4.0 dT_mems/dt + k (T_mems − ε)`, `dε/dt = (T_mems − ε)/τ`, τ = 1500 s,
  k = 0.05 °/h/K, with `dT_mems/dt` the model's exact derivative (K/s), plus white noise
  0.02 °/h per 1 Hz sample.

One continuous record (full run): 2 h soak at 25 °C; 1 °C/min to −40 °C; 2 h soak;
1 °C/min ramp −40 → +85 °C (the slow ramp phase); 2 h soak at +85 °C; 10 °C/min step
transients (+85 → −40, 30 min dwell, → +85, 30 min, → 25 °C, 30 min); a chamber step to
+85 °C (one sample) held 3 h (the viscoelastic dwell). 14 h at 1 Hz.

Calibration, in the seed's stages:

1. static polynomial: `find_plateaus` on the ASIC (on-die) sensor finds the three soaks;
   `fit_static_polynomial` fits the bias plateau means — three plateaus carry at most a
   quadratic (the seed's fifth order needs six);
2. conductance optimization: `thermojax.fit` on the slow ramp's temperature readings
   alone identifies the housing–bulkhead conductance, and on the fast transients alone
   the MEMS die capacitance (each with every other parameter held at the truth, started
   30 % high): what each phase can identify by itself;
3. coupling: the Kalman observer of the identified model estimates every node; `fit_bias`
   fits the bias model (cubic in T̂_pm, gradient T̂_mems − T̂_asic, exact rate of
   T̂_mems, one strain state on the MEMS node with τ by bounded search) on the whole record.

Residual = noise-free true bias − correction (and measured bias − correction), RMS per
phase window, °/h, for the static polynomial (in the ASIC reading) and the observer model.

    python experiments/seed_calibration_phases.py [--out DIR] [--force] [--quick]

writes `DIR` (default `results/seed_calibration_phases-<UTC time>/`; an existing folder is
refused, exit 2, unless `--force`) with `phases.md`, `results.json` and
`phase_residuals.png`. About 1 min on two cores; `--quick` (0…50 °C, 30 min soaks,
8 min transient dwells, 45 min viscoelastic dwell) about 30 s.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import thermojax as tj
from thermojax._plots import new_figure, save_figure
from thermojax.calibration import find_plateaus, fit_static_polynomial
from thermojax.dynamics._lag import first_order_lag
from thermojax.fitting._bias import fit_bias
from thermojax.measurements import Experiment
from thermojax.measurements import _profiles as profiles
from thermojax.model import ThermalModel
from thermojax.model._spec import Bias, Effect, Parameter

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
from _study_cli import results_folder, study_parser, write_results  # noqa: E402
IMU = ROOT / "configs" / "imu6.toml"

COLUMN = "gyro_x_dph"
P_ASIC = 0.05  # W
POLY = (0.5, 0.03, 5e-4, -2e-6)  # °/h per K^p about 25 °C, in T_proof_mass
K_GRAD = 0.8  # °/h per K of T_mems − T_asic
K_RATE = 4.0  # °/h per K/s of dT_mems/dt
TAU = 1500.0  # s
K_STRAIN = 0.05  # °/h per K of T_mems − ε
BIAS_NOISE = 0.02  # °/h per 1 Hz sample
SENSOR_NOISE = 0.01  # °C
DT = 1.0  # s
T_REF = 25.0
STATIC_ORDER = 2  # three soak plateaus carry a quadratic at most

#: The seed's phase table, row by row.
SEED_TABLE = {
    "static_soak": {"phase": "Static Soak", "profile": "-40 °C, +25 °C, +85 °C dwells (2 hrs each)",
                    "target": "Static Polynomial Coefficients", "residual_dph": 0.04,
                    "status": "Optimal Baseline"},
    "slow_ramp": {"phase": "Slow Dynamic Ramp", "profile": "1.0 °C/min continuous (-40 °C to +85 °C)",
                  "target": "Bulkhead-to-Housing Conductance", "residual_dph": 0.08,
                  "status": "Parameter Identified"},
    "fast_shock": {"phase": "Fast Thermal Shock", "profile": "10.0 °C/min step transients",
                   "target": "Silicon Die Thermal Capacitance", "residual_dph": 0.12,
                   "status": "Parameter Identified"},
    "viscoelastic_dwell": {"phase": "Viscoelastic Dwell",
                           "profile": "+85 °C rapid step followed by 3 hr soak",
                           "target": "Polymer Relaxation Strain States", "residual_dph": 0.06,
                           "status": "Asymptotic Match"},
}
#: The thermal parameter each transient phase identifies alone (dotted report name).
PHASE_PARAMETER = {"slow_ramp": "links.housing-bulkhead.conductance",
                   "fast_shock": "nodes.mems.capacitance"}
START_FACTOR = 1.3

FULL = {"lo": -40.0, "hi": 85.0, "room": 25.0, "soak_s": 7200.0, "shock_dwell_s": 1800.0,
        "visco_s": 3 * 3600.0}
QUICK = {"lo": 0.0, "hi": 50.0, "room": 25.0, "soak_s": 1800.0, "shock_dwell_s": 480.0,
         "visco_s": 2700.0}

TRUTH = {"model": "configs/imu6.toml (the thermal part of configs/imu6_bias.toml)",
         "P_asic_W": P_ASIC, "column": COLUMN, "poly_dph": list(POLY), "poly_node": "proof_mass",
         "poly_centre_C": T_REF, "gradient_dph_per_K": K_GRAD, "gradient": "T_mems - T_asic",
         "rate_dph_per_K_per_s": K_RATE, "rate_node": "mems (exact A x + B u)",
         "strain_node": "mems", "tau_s": TAU, "k_dph_per_K": K_STRAIN,
         "bias_noise_dph": BIAS_NOISE, "sensor_noise_C": SENSOR_NOISE, "dt_s": DT}


# ---------------------------------------------------------------------------
# The record


def calibration_profile(cfg: dict) -> tuple[profiles.Profile, dict]:
    """The multi-phase record and its phase windows: name -> list of (start_s, end_s)."""
    lo, hi, room = cfg["lo"], cfg["hi"], cfg["room"]
    segs = [("static_soak", profiles.soak(room, cfg["soak_s"], dt=DT)),
            ("transition", profiles.ramp(room, lo, 1.0, dt=DT)),
            ("static_soak", profiles.soak(lo, cfg["soak_s"], dt=DT)),
            ("slow_ramp", profiles.ramp(lo, hi, 1.0, dt=DT)),
            ("static_soak", profiles.soak(hi, cfg["soak_s"], dt=DT)),
            ("fast_shock", profiles.concatenate(
                profiles.ramp(hi, lo, 10.0, dt=DT), profiles.soak(lo, cfg["shock_dwell_s"], dt=DT),
                profiles.ramp(lo, hi, 10.0, dt=DT), profiles.soak(hi, cfg["shock_dwell_s"], dt=DT),
                profiles.ramp(hi, room, 10.0, dt=DT),
                profiles.soak(room, cfg["shock_dwell_s"], dt=DT))),
            ("viscoelastic_dwell", profiles.step_shock(room, hi, 0.0, cfg["visco_s"], dt=DT))]
    windows: dict[str, list] = {}
    t = 0.0
    for name, p in segs:
        windows.setdefault(name, []).append((t, t + p.duration))
        t += p.duration
    return profiles.concatenate(*(p for _, p in segs)), windows


def imu_spec():
    return tj.parse_model(IMU.read_text(), source=str(IMU))


@eqx.filter_jit
def _simulate(model, inputs, ts):
    sol = tj.simulate(model, inputs, ts)
    return sol.states, sol.outputs


@eqx.filter_jit
def _observe(observer, inputs, readings, x0):
    return tj.run_observer(observer, inputs, readings, x0).states


def node_rates(model: ThermalModel, states: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """The model's exact state derivative `A x + B u` at every sample (K/s)."""
    sys_ = model.linear_system()
    return states @ np.asarray(sys_.A).T + inputs @ np.asarray(sys_.B).T


def true_bias(states, rates, ts, names) -> np.ndarray:
    """The synthetic truth's noise-free gyro bias (°/h)."""
    pm, mems, asic = (states[:, names.index(n)] for n in ("proof_mass", "mems", "asic"))
    d = pm - T_REF
    eps = first_order_lag(mems, np.diff(ts), TAU)
    return (sum(c * d ** p for p, c in enumerate(POLY)) + K_GRAD * (mems - asic)
            + K_RATE * rates[:, names.index("mems")] + K_STRAIN * (mems - eps))


def simulate_record(model: ThermalModel, temperature: np.ndarray, ts: np.ndarray, rng,
                    sensor_noise: float = SENSOR_NOISE, bias_noise: float = BIAS_NOISE) -> dict:
    """True states, noisy readings, the true and the measured bias of one chamber record."""
    inputs = np.column_stack([temperature, np.full(ts.size, P_ASIC)])
    states, clean = (np.asarray(a) for a in _simulate(model, jnp.asarray(inputs), jnp.asarray(ts)))
    names = list(model.network.topology.node_names)
    readings = clean + sensor_noise * rng.standard_normal(clean.shape)
    bias = true_bias(states, node_rates(model, states, inputs), ts, names)
    return {"ts": ts, "chamber": temperature, "inputs": inputs, "states": states,
            "readings": readings, "bias": bias,
            "measured": bias + bias_noise * rng.standard_normal(ts.size), "names": names,
            "sensors": list(model.network.topology.sensor_names)}


def estimate(model: ThermalModel, rec: dict) -> tuple[np.ndarray, np.ndarray]:
    """The Kalman observer's node estimates (°C) and their exact rates (K/s)."""
    observer = tj.design_observer(model, DT)
    x0 = model.linear_system().steady_state(jnp.asarray(rec["inputs"][0]))
    est = np.asarray(_observe(observer, jnp.asarray(rec["inputs"]), jnp.asarray(rec["readings"]),
                              x0))
    return est, node_rates(model, est, rec["inputs"])


# ---------------------------------------------------------------------------
# The stages


def only_free(spec, free: str, factor: float = START_FACTOR):
    """`spec` with every parameter fixed at its value except `free` (started `factor` ×)."""
    def par(p: Parameter, name: str) -> Parameter:
        return Parameter(p.value * factor, False) if name == free else Parameter(p.value, True)
    return dataclasses.replace(
        spec,
        nodes=tuple(dataclasses.replace(n, capacitance=par(n.capacitance, f"nodes.{n.name}.capacitance"))
                    for n in spec.nodes),
        links=tuple(dataclasses.replace(l, conductance=par(l.conductance, f"links.{l.key}.conductance"))
                    for l in spec.links),
        boundaries=tuple(dataclasses.replace(b, conductance=par(b.conductance, "")) for b in spec.boundaries),
        heat_inputs=tuple(dataclasses.replace(h, gain=par(h.gain, "")) for h in spec.heat_inputs),
        sensors=tuple(dataclasses.replace(s, noise=par(s.noise, "")) for s in spec.sensors))


def with_value(spec, name: str, value: float):
    """`spec` with the parameter `name` (a node capacitance or link conductance) set."""
    kind, key, _ = name.split(".")
    if kind == "nodes":
        return dataclasses.replace(spec, nodes=tuple(
            dataclasses.replace(n, capacitance=Parameter(value, n.capacitance.fixed))
            if n.name == key else n for n in spec.nodes))
    return dataclasses.replace(spec, links=tuple(
        dataclasses.replace(l, conductance=Parameter(value, l.conductance.fixed))
        if l.key == key else l for l in spec.links))


def window_mask(ts: np.ndarray, windows) -> np.ndarray:
    m = np.zeros(ts.size, bool)
    for a, b in windows:
        m |= (ts >= a) & (ts <= b)
    return m


def identify_thermal(spec, rec: dict, windows, name: str) -> dict:
    """`thermojax.fit` of the one parameter `name` on the readings inside `windows` (the
    phase's first window, times shifted to start at 0)."""
    a, b = windows[0]
    m = (rec["ts"] >= a) & (rec["ts"] <= b)
    exp = Experiment(ts=rec["ts"][m] - a, inputs=rec["inputs"][m], outputs=rec["readings"][m],
                     name=name)
    res = tj.fit(only_free(spec, name), [exp])
    entry = res.parameters[name]
    return {"name": name, "value": float(entry["value"]), "std": entry["std"],
            "converged": bool(res.converged), "samples": int(m.sum())}


def bias_spec() -> tuple[Bias, list[Effect]]:
    return (Bias(column=COLUMN, temperature="proof_mass", order=3, gradients=(("mems", "asic"),),
                 rates=("mems",)),
            [Effect("viscoelastic", ("mems", COLUMN))])


def calibrate(quick: bool = False, seed: int = 0, bias_noise: float = BIAS_NOISE) -> dict:
    """Simulate the record and run the three stages. Returns everything (arrays included)."""
    cfg = QUICK if quick else FULL
    rng = np.random.default_rng(seed)
    spec = imu_spec()
    truth_model = ThermalModel.from_spec(spec)
    prof, windows = calibration_profile(cfg)
    rec = simulate_record(truth_model, prof.temperature, prof.ts, rng, bias_noise=bias_noise)
    names, sensors = rec["names"], rec["sensors"]
    t_asic = rec["readings"][:, sensors.index("T_asic")]

    # 1. static polynomial from the dwell plateaus of the on-die sensor
    plateaus = find_plateaus(rec["ts"], t_asic, rec["measured"],
                             min_duration_s=0.4 * cfg["soak_s"], settle_s=0.25 * cfg["soak_s"])
    plateaus = [p for p in plateaus if any(a <= p.start_s <= b for a, b in windows["static_soak"])]
    static = fit_static_polynomial([p.temperature for p in plateaus], [p.bias for p in plateaus],
                                   STATIC_ORDER, [p.bias_std / np.sqrt(p.n) for p in plateaus])

    # 2. thermal parameters, each from its phase alone
    thermal = {ph: identify_thermal(spec, rec, windows[ph], name)
               for ph, name in PHASE_PARAMETER.items()}
    fitted_spec = spec
    for entry in thermal.values():
        fitted_spec = with_value(fitted_spec, entry["name"], entry["value"])
    model = ThermalModel.from_spec(fitted_spec)

    # 3. the observer-based bias model on the whole record
    est, rates = estimate(model, rec)
    bias, effects = bias_spec()
    bfit = fit_bias(bias, effects, [(rec["ts"], est, rec["measured"])], names, [rates])
    return {"cfg": cfg, "windows": windows, "record": rec, "plateaus": plateaus,
            "static": static, "thermal": thermal, "model": model, "spec": fitted_spec,
            "bias_fit": bfit, "estimates": est, "static_correction": static(t_asic),
            "observer_correction": bfit.predictions[0]}


def observer_correction(bfit, est: np.ndarray, rates: np.ndarray, ts: np.ndarray, names) -> np.ndarray:
    """The fitted bias model evaluated on another record's estimates (°/h)."""
    coef = dict(zip(bfit.names, bfit.coefficients))
    pm, mems, asic = (est[:, names.index(n)] for n in ("proof_mass", "mems", "asic"))
    d = pm - T_REF
    tau = bfit.time_constants["viscoelastic.mems"][0]
    eps = first_order_lag(mems, np.diff(ts), tau)
    return (sum(coef[f"poly{p}"] * d ** p for p in range(4))
            + coef["gradient.mems-asic"] * (mems - asic) + coef["rate.mems"] * rates[:, names.index("mems")]
            + coef["viscoelastic.mems.k"] * (mems - eps))


def study(quick: bool = False, seed: int = 0, bias_noise: float = BIAS_NOISE) -> dict:
    cal = calibrate(quick, seed, bias_noise)
    rec, w = cal["record"], cal["windows"]
    ts = rec["ts"]
    bfit = cal["bias_fit"]
    rms = lambda r: float(np.sqrt(np.mean(r ** 2)))  # noqa: E731
    coef = dict(zip(bfit.names, bfit.coefficients))
    std = dict(zip(bfit.names, bfit.std))
    tau, tau_std = bfit.time_constants["viscoelastic.mems"]
    truth_params = {"links.housing-bulkhead.conductance": 0.5, "nodes.mems.capacitance": 0.05}
    identified = {
        "static_soak": [{"name": f"static poly{p} (°/h per K^{p}, in T_asic)", "truth": None,
                         "value": float(c), "std": float(s)}
                        for p, (c, s) in enumerate(zip(cal["static"].coefficients,
                                                       cal["static"].std))],
        **{ph: [{"name": e["name"] + (" (W/K)" if "conductance" in e["name"] else " (J/K)"),
                 "truth": truth_params[e["name"]], "value": e["value"], "std": e["std"]}]
           for ph, e in cal["thermal"].items()},
        "viscoelastic_dwell": [
            {"name": "strain tau (s)", "truth": TAU, "value": float(tau),
             "std": None if tau_std is None else float(tau_std)},
            {"name": "strain k (°/h/K)", "truth": K_STRAIN, "value": float(coef["viscoelastic.mems.k"]),
             "std": float(std["viscoelastic.mems.k"])}]}
    rows = []
    for ph, seed_row in SEED_TABLE.items():
        m = window_mask(ts, w[ph])
        r_static = rec["bias"][m] - cal["static_correction"][m]
        r_obs = rec["bias"][m] - cal["observer_correction"][m]
        rows.append({"phase": ph, "seed": seed_row,
                     "duration_s": float(sum(b - a for a, b in w[ph])),
                     "identified": identified[ph],
                     "static_rms_dph": rms(r_static), "observer_rms_dph": rms(r_obs),
                     "static_measured_rms_dph": rms(rec["measured"][m] - cal["static_correction"][m]),
                     "observer_measured_rms_dph": rms(rec["measured"][m] - cal["observer_correction"][m]),
                     "static_peak_dph": float(np.max(np.abs(r_static))),
                     "observer_peak_dph": float(np.max(np.abs(r_obs)))})
    for rows_ in identified.values():
        for p in rows_:
            p["error_in_std"] = (None if p["truth"] is None or not p["std"]
                                 else (p["value"] - p["truth"]) / p["std"])
    bias_coefs = [{"name": n, "truth": t, "value": float(coef[n]), "std": float(std[n])}
                  for n, t in zip(bfit.names, [*POLY, K_GRAD, K_RATE, K_STRAIN])]
    out = {"config": {**cal["cfg"], "quick": quick, "seed": seed, "dt_s": DT,
                      "samples": int(ts.size), "duration_h": float(ts[-1] / 3600)},
           "truth": {**TRUTH, "bias_noise_dph": bias_noise},
           "windows": cal["windows"], "rows": rows, "bias_model": bias_coefs,
           "bias_model_tau_s": [float(tau), tau_std],
           "plateaus": [dataclasses.asdict(p) for p in cal["plateaus"]],
           "thermal_fits": cal["thermal"],
           "_cal": cal}
    return out


def table(res: dict) -> str:
    cfg, tr = res["config"], res["truth"]
    lines = ["# The seed's calibration phases: identified parameter and residual RMS bias", "",
             f"Six-node IMU ({tr['model']}), P_asic {tr['P_asic_W']:g} W, 1 Hz, sensors 0.01 °C. "
             f"Gyro truth (°/h): cubic in T_pm ({', '.join(f'{c:g}' for c in POLY)} per K^p about "
             f"25 °C) + {K_GRAD:g} (T_mems − T_asic) + {K_RATE:g} dT_mems/dt + {K_STRAIN:g} "
             f"(T_mems − ε), τ {TAU:g} s; white noise {tr['bias_noise_dph']:g} °/h per sample. "
             f"Record {cfg['duration_h']:.1f} h over {cfg['lo']:g}…{cfg['hi']:g} °C, soaks "
             f"{cfg['soak_s'] / 3600:g} h, transient dwells {cfg['shock_dwell_s'] / 60:g} min, "
             f"viscoelastic dwell {cfg['visco_s'] / 3600:g} h.", "",
             "Residual = noise-free true bias − correction, RMS over the phase's windows (°/h); "
             "static = quadratic through the three soak plateaus in the ASIC sensor reading; "
             "observer = fitted bias model on the Kalman observer's estimates of the identified "
             "model. The thermal parameters are fitted on their phase's readings alone with all "
             "others held at the truth (start 30 % high).", "",
             "| phase (seed) | seed's profile | seed's target | identified here: truth → value ± std | "
             "seed's residual RMS | static RMS (peak) | observer RMS (peak) | measured − observer RMS |",
             "|---|---|---|---|---:|---:|---:|---:|"]
    for r in res["rows"]:
        s = r["seed"]
        ids = "; ".join(
            f"{p['name']}: " + ("" if p["truth"] is None else f"{p['truth']:g} → ")
            + f"{p['value']:.6g} ± " + ("—" if p["std"] is None else f"{p['std']:.2g}")
            + ("" if p["error_in_std"] is None else f" ({p['error_in_std']:+.2f} std)")
            for p in r["identified"])
        lines.append(f"| {s['phase']} | {s['profile']} | {s['target']} | {ids} | "
                     f"{s['residual_dph']:g} °/h | {r['static_rms_dph']:.3f} ({r['static_peak_dph']:.2f}) | "
                     f"{r['observer_rms_dph']:.4f} ({r['observer_peak_dph']:.3f}) | "
                     f"{r['observer_measured_rms_dph']:.4f} |")
    lines += ["", "Bias model fitted on the whole record (observer estimates): truth → value ± std", ""]
    lines += [f"- {c['name']}: {c['truth']:g} → {c['value']:.5g} ± {c['std']:.2g}"
              + (f" ({(c['value'] - c['truth']) / c['std']:+.2f} std)" if c["std"] > 0 else "")
              for c in res["bias_model"]]
    tau, tau_std = res["bias_model_tau_s"]
    lines += [f"- strain τ: {TAU:g} → {tau:.5g} ± {tau_std if tau_std is None else round(tau_std, 1)} s", ""]
    lines += ["## The seed's numbers beside these", "",
              "- The seed's residuals (0.04–0.12 °/h) sit a factor of a few above a 0.02 °/h "
              "white-noise floor; here the observer model's residual against the noise-free "
              "truth is far below the noise (exact model structure, only the two identified "
              "thermal parameters and the bias coefficients estimated), and the measured "
              "residual equals the injected noise. The static quadratic's residual is largest in "
              "the phases the seed calls dynamic, as the seed says; its size depends on the "
              "gradient, rate and strain coefficients of the truth, which the seed does not give.",
              "- A fifth-order static polynomial (the seed's pipeline) cannot be fitted from the "
              "three soaks of its own table: three plateaus carry at most a quadratic.",
              "- Each phase alone identifies its target parameter here, with every other "
              "parameter known; in a joint fit the proof-mass parameters stay unidentifiable at "
              "1 Hz (see imu6_three_ramps.py)."]
    return "\n".join(lines) + "\n"


def plot(res: dict, path: Path) -> Path:
    cal = res["_cal"]
    rec = cal["record"]
    t = rec["ts"] / 3600.0
    fig = new_figure(figsize=(13, 8.5))
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ax1.plot(t, rec["chamber"], color="0.5", label="chamber")
    ax1.plot(t, rec["states"][:, rec["names"].index("proof_mass")], label="proof mass (true)")
    ax1.plot(t, rec["readings"][:, rec["sensors"].index("T_asic")], "--", label="ASIC sensor")
    colors = {"static_soak": "C2", "slow_ramp": "C0", "fast_shock": "C3", "viscoelastic_dwell": "C4"}
    for ph, ws in cal["windows"].items():
        if ph in colors:
            for k, (a, b) in enumerate(ws):
                for ax in (ax1, ax2):
                    ax.axvspan(a / 3600, b / 3600, color=colors[ph], alpha=0.08,
                               label=SEED_TABLE[ph]["phase"] if (k == 0 and ax is ax1) else None)
    ax1.set_ylabel("temperature (°C)")
    ax1.set_title("The seed's multi-phase calibration profile (shaded: its phases)")
    ax1.legend(loc="lower left", ncol=2)
    ax2.plot(t, rec["bias"] - cal["static_correction"], label="static quadratic (ASIC sensor)")
    ax2.plot(t, rec["bias"] - cal["observer_correction"], label="observer-based bias model")
    ax2.set_xlabel("time (h)")
    ax2.set_ylabel("residual gyro bias (°/h)")
    ax2.set_title("Residual bias (noise-free truth − correction)")
    ax2.legend(loc="upper left")
    return save_figure(fig, path)


def main(argv=None) -> Path:
    parser = study_parser("seed_calibration_phases", __doc__,
                          "test-sized run: 0…50 °C, 30 min soaks, 45 min viscoelastic dwell")
    args = parser.parse_args(argv)
    folder = results_folder("seed_calibration_phases", args.out, args.force)
    res = study(quick=args.quick, seed=args.seed)
    write_results(folder, res, table(res), "phases.md")
    plot(res, folder / "phase_residuals.png")
    return folder


if __name__ == "__main__":
    main()
