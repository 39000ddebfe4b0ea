"""A user's own first logs, made outside thermojax: an independent simulator and the files
a user writes from docs/formats.md alone.

The simulator is exact for piecewise-linear inputs (the default `foh` hold): over each
sample period, `expm` of the augmented system `[[A, B, 0], [0, 0, I/dt], [0, 0, 0]]`
(NumPy and SciPy only; it never imports thermojax). Runs start where the user's unit
really was, not at an equilibrium: the state a first log catches a building or a
sensor in. Telemetry is a plain CSV (a header row, no comment lines), the model file has
no `initial`, no `process_noise` and no `hold`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.linalg


@dataclass
class Network:
    """A linear RC network in SI units: nodes (name -> capacitance J/K), links (a, b, G
    W/K), boundaries (node, column, G W/K), heats (node, column, gain), sensors
    (column, node, noise °C), and optional extra truth terms the user's model lacks."""

    nodes: dict
    links: list
    boundaries: list
    heats: list
    sensors: list
    inputs: tuple = field(init=False)

    def __post_init__(self):
        cols = [c for _, c, _ in self.boundaries] + [c for _, c, _ in self.heats]
        self.inputs = tuple(dict.fromkeys(cols))

    def matrices(self):
        names = list(self.nodes)
        n, m = len(names), len(self.inputs)
        C = np.array([self.nodes[k] for k in names], float)
        K = np.zeros((n, n))
        Bq = np.zeros((n, m))
        for a, b, g in self.links:
            i, j = names.index(a), names.index(b)
            K[i, i] += g
            K[j, j] += g
            K[i, j] -= g
            K[j, i] -= g
        for node, col, g in self.boundaries:
            i = names.index(node)
            K[i, i] += g
            Bq[i, self.inputs.index(col)] += g
        for node, col, gain in self.heats:
            Bq[names.index(node), self.inputs.index(col)] += gain
        A = -K / C[:, None]
        B = Bq / C[:, None]
        Cy = np.zeros((len(self.sensors), n))
        for k, (_, node, _) in enumerate(self.sensors):
            Cy[k, names.index(node)] = 1.0
        return A, B, Cy


def simulate(net: Network, U: np.ndarray, dt: float, x0: np.ndarray) -> np.ndarray:
    """States (T, n) °C from `x0`, inputs `U` (T, m) linear between samples."""
    A, B, _ = net.matrices()
    n, m = B.shape
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n], M[:n, n:n + m] = A, B
    M[n:n + m, n + m:] = np.eye(m) / dt
    E = scipy.linalg.expm(M * dt)
    Phi, G0, G1 = E[:n, :n], E[:n, n:n + m], E[:n, n + m:]
    X = np.empty((U.shape[0], n))
    X[0] = x0
    for k in range(U.shape[0] - 1):
        # u(t) = u_k + (u_k+1 − u_k) t/dt: G0 carries u_k, G1 the slope times dt
        X[k + 1] = Phi @ X[k] + G0 @ U[k] + G1 @ (U[k + 1] - U[k])
    return X


def readings(net: Network, X: np.ndarray, rng) -> dict[str, np.ndarray]:
    _, _, Cy = net.matrices()
    Y = X @ Cy.T
    return {col: Y[:, k] + rng.standard_normal(len(Y)) * noise
            for k, (col, _, noise) in enumerate(net.sensors)}


def model_text(net: Network, name: str, initial: dict | None = None) -> str:
    """The model file a user writes from the docs: every value a number to fit (the
    heater gains of measured electric powers fixed at 1), no initial states unless
    `initial` (node -> text) says."""
    out = [f'name = "{name}"']
    for node, c in net.nodes.items():
        out += ["", "[[nodes]]", f'name = "{node}"', f"capacitance = {c:.6g}"]
        if initial and node in initial:
            out.append(f"initial = {initial[node]}")
    for a, b, g in net.links:
        out += ["", "[[links]]", f'between = ["{a}", "{b}"]', f"conductance = {g:.6g}"]
    for node, col, g in net.boundaries:
        out += ["", "[[boundaries]]", f'node = "{node}"', f'input = "{col}"',
                f"conductance = {g:.6g}"]
    for node, col, gain in net.heats:
        value = "{ value = 1.0, fixed = true }" if col.startswith("P") else f"{gain:.6g}"
        out += ["", "[[heat_inputs]]", f'node = "{node}"', f'input = "{col}"', f"gain = {value}"]
    for col, node, _ in net.sensors:
        out += ["", "[[sensors]]", f'node = "{node}"', f'column = "{col}"']
    return "\n".join(out) + "\n"


def write_csv(path: Path, ts: np.ndarray, columns: dict[str, np.ndarray]) -> Path:
    """A plain telemetry CSV: `time_s` then the columns, a header row and numbers."""
    data = np.column_stack([ts, *columns.values()])
    path.write_text(",".join(["time_s", *columns]) + "\n"
                    + "\n".join(",".join(f"{v:.6f}" for v in row) for row in data) + "\n")
    return path


def prbs(n: int, rng, slot: int, low: float, high: float) -> np.ndarray:
    """A random binary sequence held for `slot` samples at a time."""
    levels = rng.integers(0, 2, size=n // slot + 1)
    return np.where(np.repeat(levels, slot)[:n] == 1, high, low).astype(float)


# ---------------------------------------------------------------------------------------
# The cases


def _building_inputs(n: int, dt: float, rng):
    """Half-hourly building inputs (times s, (n, 3) T_out °C, P_heat W, solar W/m²):
    outdoor 5 ± 3 °C daily with a random walk, a 3 kW heater on a random binary sequence
    in 3 h slots, a daytime sun up to 400 W/m²."""
    ts = np.arange(n) * dt
    day = ts / 86400.0
    return ts, np.column_stack([
        5.0 + 3.0 * np.sin(2 * np.pi * (day - 0.3)) + np.cumsum(rng.normal(0, 0.05, n)),
        prbs(n, rng, 6, 0.0, 3000.0),
        np.clip(400.0 * np.sin(2 * np.pi * (day - 0.25)), 0.0, None)])


def building(n: int = 400, seed: int = 0):
    """A room and its envelope, half-hourly, outdoor ~5 °C, a 3 kW heater on a random
    binary sequence, solar gain through windows; the log starts with the room at 26.7 °C
    and the envelope at 22 °C, far from the first sample's equilibrium (5 °C)."""
    rng = np.random.default_rng(seed)
    net = Network(nodes={"room": 2.0e6, "envelope": 2.0e7},
                  links=[("room", "envelope", 300.0)],
                  boundaries=[("envelope", "T_out", 150.0)],
                  heats=[("room", "P_heat", 1.0), ("room", "solar", 3.0)],
                  sensors=[("T_room", "room", 0.05)])
    dt = 1800.0
    ts, U = _building_inputs(n, dt, rng)
    X = simulate(net, U, dt, np.array([26.7, 22.0]))
    return net, ts, dict(zip(net.inputs, U.T)), readings(net, X, rng), X


def heater(n: int = 600, seed: int = 1):
    """A heater block on a plate in a chamber at 25 °C, 2 s samples, a power PRBS; the log
    starts with the block still hot (48 °C) from an earlier test."""
    rng = np.random.default_rng(seed)
    net = Network(nodes={"block": 40.0, "plate": 200.0},
                  links=[("block", "plate", 2.0)],
                  boundaries=[("plate", "T_chamber", 1.5)],
                  heats=[("block", "P_heater", 1.0)],
                  sensors=[("T_block", "block", 0.02), ("T_plate", "plate", 0.02)])
    dt = 2.0
    ts = np.arange(n) * dt
    U = np.column_stack([25.0 + 0.0 * ts, prbs(n, rng, 15, 0.0, 20.0)])
    X = simulate(net, U, dt, np.array([48.0, 33.0]))
    return net, ts, dict(zip(net.inputs, U.T)), readings(net, X, rng), X


def sensor_module(n: int = 500, seed: int = 2):
    """A housing, a board and a die in a chamber ramp, 1 s samples, the die's power
    switched; the log starts with the die warm from power-on (an unmeasured board)."""
    rng = np.random.default_rng(seed)
    net = Network(nodes={"housing": 30.0, "board": 4.0, "die": 0.5},
                  links=[("housing", "board", 0.4), ("board", "die", 0.25)],
                  boundaries=[("housing", "T_chamber", 0.8)],
                  heats=[("die", "P_die", 1.0)],
                  sensors=[("T_housing", "housing", 0.01), ("T_die", "die", 0.01)])
    dt = 1.0
    ts = np.arange(n) * dt
    U = np.column_stack([np.interp(ts, [0, 100, 400, n], [25.0, 25.0, 45.0, 45.0]),
                         prbs(n, rng, 25, 0.0, 0.5)])
    X = simulate(net, U, dt, np.array([26.0, 29.0, 31.0]))
    return net, ts, dict(zip(net.inputs, U.T)), readings(net, X, rng), X


CASES = {"building": building, "heater": heater, "sensor_module": sensor_module}


def building_one_node_truth(n: int = 400, seed: int = 4):
    """The null case: the room alone is the truth (the user's one-node model is right),
    with the same inputs as `building` and a start 8 K off equilibrium."""
    rng = np.random.default_rng(seed)
    net = Network(nodes={"room": 6.0e6},
                  links=[],
                  boundaries=[("room", "T_out", 120.0)],
                  heats=[("room", "P_heat", 1.0), ("room", "solar", 3.0)],
                  sensors=[("T_room", "room", 0.05)])
    dt = 1800.0
    ts, U = _building_inputs(n, dt, rng)
    X = simulate(net, U, dt, np.array([13.0]))
    return net, ts, dict(zip(net.inputs, U.T)), readings(net, X, rng), X


def one_node_guess(name: str = "room") -> Network:
    """The model a user writes first for a building log: one node, the outdoor boundary,
    the heater and the sun, at round guesses."""
    return Network(nodes={name: 1.0e7}, links=[], boundaries=[(name, "T_out", 100.0)],
                   heats=[(name, "P_heat", 1.0), (name, "solar", 1.0)],
                   sensors=[("T_room", name, 0.05)])


def sensor_module_hidden_heat(n: int = 500, seed: int = 5):
    """`sensor_module` whose board also dissipates a regulator's power, recorded as
    `P_aux` (switched on its own, 0/0.3 W) but left out of the user's model:
    `(truth, user)` networks and the log."""
    rng = np.random.default_rng(seed)
    user = Network(nodes={"housing": 30.0, "board": 4.0, "die": 0.5},
                   links=[("housing", "board", 0.4), ("board", "die", 0.25)],
                   boundaries=[("housing", "T_chamber", 0.8)],
                   heats=[("die", "P_die", 1.0)],
                   sensors=[("T_housing", "housing", 0.01), ("T_die", "die", 0.01)])
    truth = Network(nodes=user.nodes, links=user.links, boundaries=user.boundaries,
                    heats=[("die", "P_die", 1.0), ("board", "P_aux", 1.0)],
                    sensors=user.sensors)
    dt = 1.0
    ts = np.arange(n) * dt
    U = np.column_stack([np.interp(ts, [0, 100, 400, n], [25.0, 25.0, 45.0, 45.0]),
                         prbs(n, rng, 25, 0.0, 0.5), prbs(n, rng, 40, 0.0, 0.3)])
    X = simulate(truth, U, dt, np.array([26.0, 29.0, 31.0]))
    return truth, user, ts, dict(zip(truth.inputs, U.T)), readings(truth, X, rng), X


def heater_lagging_sensor(n: int = 600, seed: int = 6):
    """`heater` whose block thermometer lags its block by 10 s (a probe in a loose
    well), a sensor artifact the user's model lacks: `(truth, user)` and the log."""
    rng = np.random.default_rng(seed)
    user = Network(nodes={"block": 40.0, "plate": 200.0},
                   links=[("block", "plate", 2.0)],
                   boundaries=[("plate", "T_chamber", 1.5)],
                   heats=[("block", "P_heater", 1.0)],
                   sensors=[("T_block", "block", 0.02), ("T_plate", "plate", 0.02)])
    c_probe = 1e-3  # J/K: a probe this light takes no heat worth counting from the block
    truth = Network(nodes={**user.nodes, "probe": c_probe},
                    links=[*user.links, ("block", "probe", c_probe / 10.0)],
                    boundaries=user.boundaries, heats=user.heats,
                    sensors=[("T_block", "probe", 0.02), ("T_plate", "plate", 0.02)])
    dt = 2.0
    ts = np.arange(n) * dt
    U = np.column_stack([25.0 + 0.0 * ts, prbs(n, rng, 15, 0.0, 20.0)])
    X = simulate(truth, U, dt, np.array([48.0, 33.0, 47.0]))
    return truth, user, ts, dict(zip(truth.inputs, U.T)), readings(truth, X, rng), X
