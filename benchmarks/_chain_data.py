"""A chain of `n` nodes with known parameters and its simulated runs: the truth the
large-network benchmark (and its scaled-down tests) fit back.

Truth by SciPy: `scipy.linalg.expm` of the augmented matrix, independent of thermojax's
discretization. The chain: nodes `n0 .. n(n-1)`, capacitances `C_i` (J/K) and link
conductances `G_i` (W/K) drawn around 10 J/K and 1 W/K (a node time constant of ~5 s),
both ends to the chamber air `T_amb` (0.5 W/K each), a heater `P` (gain 1, fixed, zero
hold) on every `heater_every`-th node, a sensor on every node (noise 0.01 °C). One run:
`T_amb` at 20 °C with steps, `P` a random binary sequence of 0 / 2 W, the nodes starting
from a random profile around 20 °C (each run's start is estimated).
"""

from __future__ import annotations

import numpy as np


def chain_truth(n: int, seed: int = 0):
    """`(capacitance (n,), conductance (n-1,), boundary (2,))` J/K, W/K."""
    rng = np.random.default_rng(seed)
    return (10.0 * np.exp(rng.uniform(-0.4, 0.4, n)), np.exp(rng.uniform(-0.4, 0.4, n - 1)),
            np.array([0.5, 0.5]))


def chain_text(n: int, capacitance, conductance, boundary, heater_every: int = 5,
               noise: float = 0.01, boundary_hold: str = "zoh") -> str:
    """The chain's model file (TOML) at the given values."""
    lines = [f'name = "chain{n}"']
    for i, c in enumerate(capacitance):
        lines += ["[[nodes]]", f'name = "n{i}"', f"capacitance = {float(c)!r}"]
    for i, g in enumerate(conductance):
        lines += ["[[links]]", f'between = ["n{i}", "n{i + 1}"]', f"conductance = {float(g)!r}"]
    for node, g in zip((0, n - 1), boundary):
        lines += ["[[boundaries]]", f'node = "n{node}"', 'input = "T_amb"', f"conductance = {float(g)!r}",
                  f'hold = "{boundary_hold}"']
    for i in range(heater_every // 2, n, heater_every):
        lines += ["[[heat_inputs]]", f'node = "n{i}"', 'input = "P"',
                  "gain = { value = 1.0, fixed = true }", 'hold = "zoh"']
    for i in range(n):
        lines += ["[[sensors]]", f'node = "n{i}"', f'column = "T{i}"', f"noise = {float(noise)!r}"]
    return "\n".join(lines) + "\n"


def chain_matrices(capacitance, conductance, boundary, heater_every: int = 5):
    """`A` (n, n) 1/s and `B` (n, 2) for inputs `(T_amb, P)`, in NumPy."""
    n = len(capacitance)
    K = np.zeros((n, n))
    for i, g in enumerate(conductance):
        K[i, i] += g
        K[i + 1, i + 1] += g
        K[i, i + 1] -= g
        K[i + 1, i] -= g
    B = np.zeros((n, 2))
    for node, g in zip((0, n - 1), boundary):
        K[node, node] += g
        B[node, 0] += g
    B[heater_every // 2::heater_every, 1] = 1.0
    return -K / capacitance[:, None], B / capacitance[:, None]


def chain_run(n: int, n_times: int = 400, dt: float = 2.0, seed: int = 0,
              heater_every: int = 5, noise: float = 0.01):
    """`(ts, inputs (T, 2), outputs (T, n), x0 (n,))` of one run of the true chain,
    simulated exactly (SciPy) with zero-order hold on both inputs, noise added."""
    import scipy.linalg

    C, G, Gb = chain_truth(n, seed)
    A, B = chain_matrices(C, G, Gb, heater_every)
    rng = np.random.default_rng(seed + 1)
    ts = dt * np.arange(n_times)
    T_amb = 20.0 + 5.0 * (ts > ts[-1] / 3) - 3.0 * (ts > 2 * ts[-1] / 3)
    P = 2.0 * (rng.random(n_times // 10 + 1) < 0.5).repeat(10)[:n_times]
    U = np.stack([T_amb, P], axis=1)
    M = np.zeros((n + 2, n + 2))
    M[:n, :n], M[:n, n:] = A * dt, B * dt
    E = scipy.linalg.expm(M)
    Phi, Gam = E[:n, :n], E[:n, n:]
    x = np.empty((n_times, n))
    x[0] = 20.0 + 2.0 * rng.standard_normal(n)
    for k in range(n_times - 1):
        x[k + 1] = Phi @ x[k] + Gam @ U[k]
    y = x + noise * rng.standard_normal(x.shape)
    return ts, U, y, x[0]
