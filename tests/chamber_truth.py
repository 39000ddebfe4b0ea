"""Calibration-chamber logs of an IMU made outside thermojax: the truth of the
calibration tests (issue 71).

This module imports no thermojax. It reads a model file with `tomllib` (nodes, links,
boundaries, heat inputs, sensors, `[[biases]]` and `viscoelastic` effects, docs/formats.md
§2 and §4; anything else is refused), assembles the continuous linear system with NumPy

    C_i dT_i/dt = Σ_links G_ij (T_j − T_i) + Σ_boundaries g (u − T_i) + Σ_heat gain · u
    dε/dt       = (T_node − ε) / τ            (one state per viscoelastic effect)

and steps it exactly with `scipy.linalg.expm` of the system augmented by its inputs:
the chamber temperature linear between samples (a ramp is linear), a heat input held at
its sample's value over the interval that follows (`hold = "zoh"`, the model's). A bias
column is, in plain NumPy at each sample,

    Σ_p c_p (T − 25)^p + Σ d (T_a − T_b) + Σ e dT_n/dt + Σ k (T_node − ε)

with `dT_n/dt` the right-hand side at the sample (state and input sample there: the
right-hand limit of a held power) and `ε` the exact strain state (not a discretized
filter of the sampled temperature). The start is the steady state of the first input
sample (`numpy.linalg.solve`), strains at rest.

The chamber programme (`("soak", T, s)`, `("ramp", T, °C/min)`, `("step", T, s)`,
`("power", W, s)`: the items of `thermojax.calibration._synthetic`'s programmes, whose
tuples are plain data) is sampled here: a soak holds, a ramp is linear, a step reaches
its target one sample later and holds, a power item switches the heat inputs on for its
seconds and off for 600 s more; at a join the later item's power applies. Power is then
smoothed by a moving average over `SOFT_START_S` (each switch a linear ramp). Two logs per
run, as `synthetic_imu_logs` documents them: a temperature log (inputs, sensors with
their `noise` std) and an inertial log on its own clock (each bias column linearly
interpolated between temperature samples, white noise, isolated outliers). The random
draws are made in the same order as `synthetic_imu_logs`, so that a test's noise
realization does not change with the simulator that made the noiseless truth.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.linalg

T_REF = 25.0
SOFT_START_S = 120.0
POWER_OFF_S = 600.0


def _value(v) -> float:
    return float(v["value"] if isinstance(v, dict) else v)


@dataclass
class ChamberModel:
    """The continuous system `dz/dt = A z + B u` of a model file, `z` = node temperatures
    then strain states, `u` = input columns in `inputs` order."""

    nodes: list
    inputs: list
    holds: list
    A: np.ndarray
    B: np.ndarray
    sensors: dict     # column -> (node index, noise std)
    biases: list      # dicts: column, node, poly, grads [(a, b, d)], rates [(n, e)], strains
    #                   [(state, node, k)], noise


def read_chamber_model(model) -> ChamberModel:
    """The system of a model file (path) or of its `tomllib` dict."""
    doc = model if isinstance(model, dict) else tomllib.loads(
        Path(model).read_text(encoding="utf-8"))
    known = {"name", "description", "nodes", "links", "boundaries", "heat_inputs", "sensors",
             "biases", "effects"}
    if set(doc) - known:
        raise ValueError(f"chamber_truth handles {sorted(known)}, not {sorted(set(doc) - known)}")
    nodes = [n["name"] for n in doc["nodes"]]
    idx = {n: i for i, n in enumerate(nodes)}
    effects = doc.get("effects", [])
    if any(e["kind"] != "viscoelastic" for e in effects):
        raise ValueError("chamber_truth handles viscoelastic effects only")
    n, ns = len(nodes), len(effects)
    inputs, holds = [], []
    for e in doc.get("boundaries", []) + doc.get("heat_inputs", []):
        if e["input"] not in inputs:
            inputs.append(e["input"])
            holds.append(e.get("hold", "foh"))
    cap = np.array([_value(x["capacitance"]) for x in doc["nodes"]])
    K = np.zeros((n, n))
    G = np.zeros((n, len(inputs)))
    for lk in doc.get("links", []):
        i, j = (idx[x] for x in lk["between"])
        g = _value(lk["conductance"])
        K[i, i] += g
        K[j, j] += g
        K[i, j] -= g
        K[j, i] -= g
    for b in doc.get("boundaries", []):
        i, g = idx[b["node"]], _value(b["conductance"])
        K[i, i] += g
        G[i, inputs.index(b["input"])] += g
    for h in doc.get("heat_inputs", []):
        G[idx[h["node"]], inputs.index(h["input"])] += _value(h.get("gain", 1.0))
    A = np.zeros((n + ns, n + ns))
    B = np.zeros((n + ns, len(inputs)))
    A[:n, :n] = -K / cap[:, None]
    B[:n] = G / cap[:, None]
    sensors = {s["column"]: (idx[s["node"]], _value(s.get("noise", 0.01)))
               for s in doc.get("sensors", [])}
    for s in doc.get("sensors", []):
        if set(s) - {"node", "column", "noise"}:
            raise ValueError(f"chamber_truth reads plain sensors only: {s}")
    biases = []
    for b in doc.get("biases", []):
        c = [float(v) for v in b["coefficients"]]
        order, grads, rates = int(b["order"]), b.get("gradients", []), b.get("rates", [])
        biases.append(dict(
            column=b["column"], node=idx[b["temperature"]], poly=c[:order + 1],
            grads=[(idx[p], idx[q], d) for (p, q), d in zip(grads, c[order + 1:])],
            rates=[(idx[r], e) for r, e in zip(rates, c[order + 1 + len(grads):])],
            strains=[], noise=_value(b.get("noise", 1.0))))
    by_column = {b["column"]: b for b in biases}
    for s, e in enumerate(effects):
        node, column = e["where"]
        par = e.get("parameters", e)
        tau, k = _value(par["time_constant"]), _value(par["k"])
        A[n + s, n + s] = -1.0 / tau
        A[n + s, idx[node]] = 1.0 / tau
        by_column[column]["strains"].append((n + s, idx[node], k))
    return ChamberModel(nodes, inputs, holds, A, B, sensors, biases)


def programme_samples(programme, dt: float):
    """`(ts, chamber °C, power W)` of a chamber programme at period `dt` s (see the
    module docstring), before the soft start."""
    T = float(programme[0][1])
    temps, powers = [], []
    for kind, target, value in programme:
        if kind == "soak":
            assert target == T, (kind, target, T)
            dur = value
        elif kind == "ramp":
            dur = abs(target - T) / value * 60.0
        elif kind in ("step", "power"):
            dur = value + (POWER_OFF_S if kind == "power" else 0.0)
        else:
            raise ValueError(kind)
        m = dur / dt
        if abs(m - round(m)) > 1e-9:
            raise ValueError(f"{kind} of {dur} s is not a whole number of {dt} s samples")
        t = np.arange(int(round(m)) + 1) * dt
        if kind == "ramp":
            temp = T + (target - T) * t / dur
        elif kind == "step":
            temp = np.where(t >= dt, float(target), T)
        else:
            temp = np.full(t.size, T)
        power = np.where(t < value, float(target), 0.0) if kind == "power" else np.zeros(t.size)
        if temps:  # the joining sample: same temperature, the later item's power
            temps[-1], powers[-1] = temps[-1][:-1], powers[-1][:-1]
        temps.append(temp)
        powers.append(power)
        if kind in ("ramp", "step"):
            T = float(target)
    chamber, power = np.concatenate(temps), np.concatenate(powers)
    return np.arange(chamber.size) * dt, chamber, power


def simulate(model: ChamberModel, ts, U):
    """States `(times, nodes + strains)` from rest at `U[0]`, exact for inputs linear
    (`foh`) or held (`zoh`) between samples of a uniform grid."""
    ts = np.asarray(ts, float)
    dt = ts[1] - ts[0]
    assert np.allclose(np.diff(ts), dt, rtol=0, atol=1e-9 * dt)
    nz, m = model.B.shape
    foh = [j for j, h in enumerate(model.holds) if h == "foh"]
    # augmented state [z, u(t), slopes of the foh inputs]: du/dt = slope, d slope/dt = 0
    M = np.zeros((nz + m + len(foh),) * 2)
    M[:nz, :nz], M[:nz, nz:nz + m] = model.A, model.B
    for i, j in enumerate(foh):
        M[nz + j, nz + m + i] = 1.0
    E = scipy.linalg.expm(M * dt)[:nz]
    Phi, Gam, Slp = E[:, :nz], E[:, nz:nz + m], E[:, nz + m:]
    n = len(model.nodes)
    z = np.empty((ts.size, nz))
    T0 = np.linalg.solve(model.A[:n, :n], -model.B[:n] @ U[0])
    z[0, :n] = T0
    for s in range(n, nz):  # strains at rest: ε = T_node
        z[0, s] = T0[np.flatnonzero(model.A[s, :n])[0]]
    slopes = np.diff(U[:, foh], axis=0) / dt
    for k in range(1, ts.size):
        z[k] = Phi @ z[k - 1] + Gam @ U[k - 1] + Slp @ slopes[k - 1]
    return z


def observe(model: ChamberModel, z, U):
    """Sensor columns (node temperatures) and bias columns at every sample."""
    out = {c: z[:, i].copy() for c, (i, _) in model.sensors.items()}
    zdot = z @ model.A.T + U @ model.B.T  # the right-hand side at each sample
    for b in model.biases:
        d = z[:, b["node"]] - T_REF
        y = sum(c * d ** p for p, c in enumerate(b["poly"]))
        for p, q, g in b["grads"]:
            y = y + g * (z[:, p] - z[:, q])
        for r, e in b["rates"]:
            y = y + e * zdot[:, r]
        for s, node, k in b["strains"]:
            y = y + k * (z[:, node] - z[:, s])
        out[b["column"]] = y
    return out


@dataclass(frozen=True)
class ChamberRun:
    name: str
    temperature_file: Path
    inertial_file: Path
    ts: np.ndarray
    states: np.ndarray
    bias: dict
    outlier_rows: dict


def _write_csv(path: Path, ts, columns: dict, comment: str) -> Path:
    lines = [f"# {comment}", ",".join(["time_s", *columns])]
    cols = [np.asarray(ts, float), *(np.asarray(v, float) for v in columns.values())]
    lines += [",".join("%.17g" % v for v in row) for row in zip(*(c.tolist() for c in cols))]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def chamber_logs(out_dir, model_file, runs, *, temperature_dt_s=1.0, inertial_rate_hz=20.0,
                 clock_offset_s=0.37, n_outliers=5, outlier_size=30.0, seed=0):
    """Write `<run>_temperature.csv` and `<run>_inertial.csv` per run (name -> programme
    or (programme, use)) into `out_dir`; returns name -> `ChamberRun` (noiseless truth on
    the temperature log's times). Inertial noise: 10 × the bias column's `noise`."""
    model = read_chamber_model(model_file)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    written = {}
    for name, item in runs.items():
        programme = item[0] if isinstance(item[0][0], tuple) else item
        ts, chamber, power = programme_samples(programme, temperature_dt_s)
        width = max(1, int(round(SOFT_START_S / temperature_dt_s)))
        padded = np.concatenate([np.full(width - 1, power[0]), power])
        power = np.convolve(padded, np.ones(width) / width, mode="valid")
        heat = {c for c, h in zip(model.inputs, model.holds) if h == "zoh"}
        U = np.column_stack([power if c in heat else chamber for c in model.inputs])
        z = simulate(model, ts, U)
        clean = observe(model, z, U)
        columns = {c: U[:, j] for j, c in enumerate(model.inputs)}
        columns.update({c: clean[c] + std * rng.standard_normal(ts.size)
                        for c, (_, std) in model.sensors.items()})
        t_file = _write_csv(out / f"{name}_temperature.csv", ts, columns,
                            f"chamber_truth (tests/, SciPy expm): run '{name}', seed {seed}")
        t_in = np.arange(clock_offset_s, ts[-1], 1.0 / inertial_rate_hz)
        inertial, rows = {}, {}
        for b in model.biases:
            std = 10.0 * b["noise"]
            v = np.interp(t_in, ts, clean[b["column"]]) + std * rng.standard_normal(t_in.size)
            k = np.sort(rng.choice(np.arange(10, t_in.size - 10), n_outliers, replace=False))
            v[k] += outlier_size * std * rng.choice([-1.0, 1.0], k.size)
            inertial[b["column"]], rows[b["column"]] = v, k
        i_file = _write_csv(out / f"{name}_inertial.csv", t_in, inertial,
                            f"chamber_truth: run '{name}', inertial log at {inertial_rate_hz:g} Hz")
        written[name] = ChamberRun(name, t_file, i_file, ts, z,
                                   {b["column"]: clean[b["column"]] for b in model.biases}, rows)
    return written

