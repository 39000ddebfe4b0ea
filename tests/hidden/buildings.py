"""Synthetic building data for the missing-physics loop, independent of thermojax.

Imitates the FlexHouse PRBS1 experiment (Bacher & Madsen 2011, `../shared/realdata/prbs1/`):
a building heated by a PRBS-switched electric heater, with outdoor temperature and global solar
radiation measured, seen through one indoor thermometer. Shares no code with thermojax and must
never import it (NumPy, SciPy, tomllib only).

Physics: a linear stochastic RC network in SI units (J/K, W/K, W, W/m², °C), per node i

    C_i dT_i = [ Σ_links G_ij (T_j − T_i) + Σ_boundaries G (T_a − T_i) + Σ_heat gain·u ] dt
               + C_i σ_i dW_i

i.e. dx = (A x + B u) dt + diag(σ) dW, with σ_i in °C/√s (the model files' `process_noise`).
Inputs are held constant between samples (zoh, as CTSM-R does), so the sampled process is
simulated EXACTLY: x_{k+1} = Ad x_k + Bd u_k + w_k with [[Ad, Bd], [0, I]] = expm([[A, B], [0, 0]]·dt)
and w_k ~ N(0, Qd), Qd = ∫0^dt e^{As} Q e^{Aᵀs} ds (Q = diag σ²) by Van Loan's method:
expm([[−A, Q], [0, Aᵀ]]·dt) = [[·, M12], [0, M22]], Ad = M22ᵀ, Qd = Ad·M12. The measurement is
y_k = T_sensor(t_k) + v_k, v_k ~ N(0, noise²). The run starts at the steady state of the first input
sample, x0 = −A⁻¹ B u_0. A case with a temperature-dependent capacitance (C_i (1 + β (T_i − 25 °C)),
its process noise still σ_i dW_i in °C) is simulated in `NONLINEAR_SUBSTEPS` substeps per sample,
each exact for the network frozen at the substep's predicted midpoint (second order).

Inputs (15-min sampling, dt = 900 s): `Ta` outdoor °C (2 °C mean, daily sinusoid ±3 °C coldest at
05:00, plus a mean-reverting random walk: 3-day time constant, 2 °C std); `Ps` global radiation W/m²
(a half-sine between 08:00 and 16:00 peaking at U(300, 600) W/m² per day, dimmed by a per-day
cloudiness c ~ U(0, 0.8) that flickers per sample: ×(1 − c·U(0, 1))); `Ph` heater W (a PRBS
alternating 0 / 5000 W in slots of 2–6 h, multiples of dt).

Cases (`building_case_names()`):
  building_4state  the paper's selected structure TiTeThTsAe: interior Ti, envelope Te, heater Th,
                   sensor Ts; Ph heats Th, Ps heats Ti and Te; yTi reads Ts.
  building_wall2   interior Ti and a two-layer wall Ti–Te1–Te2–Ta; Ph and Ps heat Ti, Ps also Te1.
  building_null    the one-node start model itself (other parameter values): nothing to add.
  building_4state_ct  building_4state with the heater's capacitance varying with its temperature,
                   C_h (1 + β (T_h − 25 °C)), β = 0.02 /K (the one temperature-dependent effect).
The believed start model of every case is the one-node model of `prbs1/ti.toml`.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import scipy.linalg

DT = 900.0  # s, sample period
DAYS = 30
COLUMNS = ("Ta", "Ps", "Ph")  # input columns, in CSV order; then the sensor column "yTi"

# Truth parameters. nodes: name -> (capacitance J/K, process noise °C/√s); links: (a, b, G W/K);
# boundaries: (node, column, G W/K); heats: (node, column, gain); sensor: column, node, noise °C.
_CASES = {
    "building_4state": dict(
        nodes={"Ti": (5.0e5, 4e-4), "Te": (1.2e7, 1e-4), "Th": (2.4e6, 3e-4), "Ts": (2.0e5, 1e-4)},
        links=[("Ti", "Te", 1000.0), ("Ti", "Th", 800.0), ("Ti", "Ts", 100.0)],
        boundaries=[("Te", "Ta", 200.0)],
        heats=[("Th", "Ph", 1.0), ("Ti", "Ps", 5.0), ("Te", "Ps", 4.0)],
        sensor=dict(column="yTi", node="Ts", noise=0.01)),
    "building_wall2": dict(
        nodes={"Ti": (8.0e5, 4e-4), "Te1": (4.0e6, 1e-4), "Te2": (1.0e7, 1e-4)},
        links=[("Ti", "Te1", 800.0), ("Te1", "Te2", 400.0)],
        boundaries=[("Te2", "Ta", 300.0)],
        heats=[("Ti", "Ph", 1.0), ("Ti", "Ps", 5.0), ("Te1", "Ps", 4.0)],
        sensor=dict(column="yTi", node="Ti", noise=0.01)),
    "building_4state_ct": dict(
        nodes={"Ti": (5.0e5, 4e-4), "Te": (1.2e7, 1e-4), "Th": (2.4e6, 3e-4), "Ts": (2.0e5, 1e-4)},
        links=[("Ti", "Te", 1000.0), ("Ti", "Th", 800.0), ("Ti", "Ts", 100.0)],
        boundaries=[("Te", "Ta", 200.0)],
        heats=[("Th", "Ph", 1.0), ("Ti", "Ps", 5.0), ("Te", "Ps", 4.0)],
        capacitance_temperature={"Th": 0.02},
        sensor=dict(column="yTi", node="Ts", noise=0.01)),
    "building_null": dict(
        nodes={"Ti": (3.0e6, 3e-4)},
        links=[],
        boundaries=[("Ti", "Ta", 180.0)],
        heats=[("Ti", "Ph", 1.0), ("Ti", "Ps", 4.0)],
        sensor=dict(column="yTi", node="Ti", noise=0.01)),
}


def building_case_names() -> list[str]:
    return sorted(_CASES)


def truth_of(name: str) -> dict:
    """The truth parameters of case `name` (a deep copy)."""
    if name not in _CASES:
        raise KeyError(f"no building case '{name}' (have {building_case_names()})")
    return copy.deepcopy(_CASES[name])


def matrices(truth: dict):
    """`(names, A, B, Q, c)`: dx = (A x + B u) dt + dW with cov(dW) = Q dt, u ordered as COLUMNS,
    y = c·x (the sensor row)."""
    names = list(truth["nodes"])
    idx = {k: i for i, k in enumerate(names)}
    cap = np.array([truth["nodes"][k][0] for k in names])
    sig = np.array([truth["nodes"][k][1] for k in names])
    n, m = len(names), len(COLUMNS)
    K, G = np.zeros((n, n)), np.zeros((n, m))
    for a, b, g in truth["links"]:
        i, j = idx[a], idx[b]
        K[i, i] += g
        K[j, j] += g
        K[i, j] -= g
        K[j, i] -= g
    for a, col, g in truth["boundaries"]:
        K[idx[a], idx[a]] += g
        G[idx[a], COLUMNS.index(col)] += g
    for a, col, gain in truth["heats"]:
        G[idx[a], COLUMNS.index(col)] += gain
    c = np.zeros(n)
    c[idx[truth["sensor"]["node"]]] = 1.0
    return names, -K / cap[:, None], G / cap[:, None], np.diag(sig ** 2), c


def discretize(A, B, Q, dt: float):
    """`(Ad, Bd, Qd)` of the zoh-sampled process over one step `dt` (exact, see module doc)."""
    n, m = B.shape
    aug = np.zeros((n + m, n + m))
    aug[:n, :n], aug[:n, n:] = A, B
    E = scipy.linalg.expm(aug * dt)
    vl = np.zeros((2 * n, 2 * n))
    vl[:n, :n], vl[:n, n:], vl[n:, n:] = -A, Q, A.T
    M = scipy.linalg.expm(vl * dt)
    Ad = M[n:, n:].T
    Qd = Ad @ M[:n, n:]
    return E[:n, :n], E[:n, n:], 0.5 * (Qd + Qd.T)


def time_constants_h(truth: dict) -> list[float]:
    """−1/eigenvalues of A, in hours, ascending."""
    A = matrices(truth)[1]
    return sorted(float(-1.0 / ev.real / 3600.0) for ev in np.linalg.eigvals(A))


def building_inputs(ts, rng) -> dict[str, np.ndarray]:
    """`Ta` °C, `Ps` W/m², `Ph` W at the sample times `ts` (s from midnight of day 0)."""
    ts = np.asarray(ts, float)
    n = len(ts)
    hour = (ts / 3600.0) % 24.0
    day = np.floor(ts / 86400.0).astype(int)
    n_days = day[-1] + 1
    # Ta: daily sinusoid (max at 17:00) + Ornstein–Uhlenbeck drift (3 days, 2 °C std).
    tau, sd = 3 * 86400.0, 2.0
    drift = np.zeros(n)
    drift[0] = sd * rng.standard_normal()
    for k in range(1, n):
        phi = np.exp(-(ts[k] - ts[k - 1]) / tau)
        drift[k] = phi * drift[k - 1] + sd * np.sqrt(1 - phi ** 2) * rng.standard_normal()
    ta = 2.0 - 3.0 * np.cos(2 * np.pi * (hour - 5.0) / 24.0) + drift
    # Ps: half-sine 08:00–16:00, per-day peak and cloudiness, per-sample flicker.
    peak = rng.uniform(300.0, 600.0, n_days)
    cloud = rng.uniform(0.0, 0.8, n_days)
    shape = np.clip(np.sin(np.pi * (hour - 8.0) / 8.0), 0.0, None) * ((hour > 8) & (hour < 16))
    ps = shape * peak[day] * (1.0 - cloud[day] * rng.uniform(0.0, 1.0, n))
    # Ph: PRBS 0/5000 W, slots of 2–6 h (whole samples), random starting level.
    ph = np.zeros(n)
    dt = ts[1] - ts[0] if n > 1 else DT
    level, k = float(rng.integers(2)), 0
    while k < n:
        slot = int(rng.integers(int(round(2 * 3600 / dt)), int(round(6 * 3600 / dt)) + 1))
        ph[k:k + slot] = 5000.0 * level
        level, k = 1.0 - level, k + slot
    return {"Ta": ta, "Ps": ps, "Ph": ph}


NONLINEAR_SUBSTEPS = 8  # per sample period, for a temperature-dependent capacitance


def capacitance_factors(truth: dict, x) -> np.ndarray:
    """`1 + β (T − 25)` per node (1 where the capacitance is constant), at temperatures `x` (°C)."""
    betas = truth.get("capacitance_temperature", {})
    return np.array([1.0 + betas.get(k, 0.0) * (x[i] - 25.0) for i, k in enumerate(truth["nodes"])])


def _nonlinear_step(truth, A, B, Q, x, u, h, rng, noise):
    """One sample period of a network with temperature-dependent capacitances, in
    `NONLINEAR_SUBSTEPS` substeps, each exact for the linear network frozen at the substep's
    midpoint (the midpoint from a first pass frozen at its start): second order in the substep.
    The process noise enters in °C (σ dW), as in the linear cases."""
    hs = h / NONLINEAR_SUBSTEPS
    for _ in range(NONLINEAR_SUBSTEPS):
        d = 1.0 / capacitance_factors(truth, x)
        aug = np.zeros((len(x) + len(u), len(x) + len(u)))
        aug[:len(x), :len(x)], aug[:len(x), len(x):] = d[:, None] * A, d[:, None] * B
        E = scipy.linalg.expm(aug * hs)  # the predictor needs no noise covariance
        mid = 0.5 * (x + E[:len(x), :len(x)] @ x + E[:len(x), len(x):] @ u)
        d = 1.0 / capacitance_factors(truth, mid)
        Ad, Bd, Qd = discretize(d[:, None] * A, d[:, None] * B, Q, hs)
        x = Ad @ x + Bd @ u
        if noise:
            x = x + np.linalg.cholesky(Qd) @ rng.standard_normal(len(x))
    return x


def simulate_building(truth: dict, ts, inputs: dict, rng, noise: bool = True) -> dict:
    """zoh simulation at `ts`: the sensor column (with measurement noise when `noise`) and
    every node's true temperature under its name. `noise=False` drops process noise too.
    Exact for a linear network; second order in `NONLINEAR_SUBSTEPS` substeps per period
    where the truth has a temperature-dependent capacitance."""
    ts = np.asarray(ts, float)
    names, A, B, Q, c = matrices(truth)
    u = np.column_stack([np.asarray(inputs[col], float) for col in COLUMNS])
    x = np.zeros((len(ts), len(names)))
    x[0] = -np.linalg.solve(A, B @ u[0])  # a steady state whatever the capacitances
    steps: dict[float, tuple] = {}
    for k in range(len(ts) - 1):
        h = float(ts[k + 1] - ts[k])
        if truth.get("capacitance_temperature"):
            x[k + 1] = _nonlinear_step(truth, A, B, Q, x[k], u[k], h, rng, noise)
            continue
        if h not in steps:
            Ad, Bd, Qd = discretize(A, B, Q, h)
            steps[h] = (Ad, Bd, np.linalg.cholesky(Qd) if noise else None)
        Ad, Bd, L = steps[h]
        x[k + 1] = Ad @ x[k] + Bd @ u[k]
        if noise:
            x[k + 1] += L @ rng.standard_normal(len(names))
    y = x @ c
    if noise:
        y = y + truth["sensor"]["noise"] * rng.standard_normal(len(ts))
    out = {truth["sensor"]["column"]: y}
    out.update({name: x[:, i] for i, name in enumerate(names)})
    return out


def believed_toml(name: str, initial: float) -> str:
    """The one-node start model, in the style of `prbs1/ti.toml`."""
    return f"""\
# Believed start model of synthetic building case '{name}' (the truth may hide physics).
# Inputs held constant between samples (CTSM-R convention; switched heaters). SI units.
name = "{name}_ti"

[[nodes]]
name = "Ti"
capacitance = 1.0e6
process_noise = 0.002
initial = {initial!r}
initial_std = 1.0

[[boundaries]]
node = "Ti"
input = "Ta"
hold = "zoh"
conductance = 200.0

[[heat_inputs]]
node = "Ti"
input = "Ph"
hold = "zoh"
gain = {{ value = 1.0, fixed = true }}

[[heat_inputs]]
node = "Ti"
input = "Ps"
hold = "zoh"
gain = 5.0                # effective window area, m2

[[sensors]]
node = "Ti"
column = "yTi"
noise = 0.01
"""


def write_building_case(name, folder, seed: int = 0, days=None) -> dict:
    """Write `folder/<name>_model.toml` (believed start model) and `folder/<name>.csv`
    (`time_s,Ta,Ps,Ph,yTi`); return `{"model", "data": [csv], "truth", "noise", "expected_states"}`."""
    truth = truth_of(name)
    days = DAYS if days is None else days
    ts = np.arange(int(round(days * 86400 / DT))) * DT
    inputs = building_inputs(ts, np.random.default_rng([seed, 0]))
    y = simulate_building(truth, ts, inputs, np.random.default_rng([seed, 1]))["yTi"]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    model = folder / f"{name}_model.toml"
    model.write_text(believed_toml(name, round(float(y[0]), 1)))
    data = folder / f"{name}.csv"
    table = np.column_stack([ts, *(inputs[col] for col in COLUMNS), y])
    with data.open("w") as f:
        f.write(",".join(["time_s", *COLUMNS, "yTi"]) + "\n")
        for row in table:
            f.write(",".join("%.17g" % v for v in row) + "\n")
    return {"model": model, "data": [data], "truth": truth, "noise": truth["sensor"]["noise"],
            "expected_states": len(truth["nodes"])}
