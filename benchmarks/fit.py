"""Identification benchmark: thermojax `fit` against `scipy.optimize.least_squares`.

The six-node IMU (configs/imu6.toml) is identified from three 3-hour chamber runs at
1 Hz (ramps between 25 and 85 °C and back at 1, 5 and 10 °C/min, dwells filling the
3 h, built with `thermojax._profiles`), with 0.01 °C white noise on the housing, PCB
and ASIC sensors. P_asic (gain fixed at 1) dissipates 0.05 W plus a 0.05 W step
between 30 and 60 min in each run: a known heat input fixes the absolute scale of the
capacitances and conductances. All 13 capacitances and conductances are free and
start 30 % off (`thermojax._runner.perturbed(truth, 0.3, seed=1)`), the same start
for every fitter.

Fitters, all on the same data, in log-parameters, in the same process:

- thermojax: `thermojax.fit(start, runs)` (output error, truncated Gauss-Newton, exact
  Jacobians by forward sensitivities, noise stds re-estimated to their ML values).
  The first fit includes compilation; the repeated fits (same structure, new noise
  seeds) must hit the jit cache, which is checked by counting compilations with
  `jax.log_compiles`.
- SciPy, straightforward: `least_squares` (TRF, 2-point finite differences) on
  residuals from a NumPy time loop `x = Phi x + B0 u[k] + B1 u[k+1]`, the discrete
  matrices from `scipy.linalg.expm` of the augmented FOH/ZOH matrix.
- SciPy, expert: the same least squares and discretization; the simulation is
  modal: the network is reciprocal, so `Phi = P diag(d) P⁻¹` with `P = C^-½ V`
  from `eigh` of the symmetrized `C^½ Phi C^-½`; each mode is one
  `scipy.signal.lfilter` over the modal drive `P⁻¹ (B0 u[k] + B1 u[k+1])`.

The fits are interleaved (thermojax, expert, straightforward, repeated) because the
machine may be shared; ratios are taken within one run of this script.

Usage:  python benchmarks/fit.py [--repeats 3] [--straightforward-repeats 1]
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.signal

import jax

jax.config.update("jax_enable_x64", True)

import thermojax as tj  # noqa: E402
from thermojax import _profiles  # noqa: E402
from thermojax._data import Experiment  # noqa: E402
from thermojax._runner import perturbed  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
HOURS = 3.0
DT = 1.0
RATES = (1.0, 5.0, 10.0)
NOISE = 0.01
BASE_POWER, STEP_POWER = 0.05, 0.05


# ---------------------------------------------------------------------------------------------
# Data


def chamber_profile(rate: float, dt: float = DT, hours: float = HOURS) -> _profiles.Profile:
    """10 min at 25 °C, ramp to 85 °C, dwell, ramp back to 25 °C, dwell: `hours` in all."""
    total, soak = hours * 3600.0, 600.0
    ramp_s = 60.0 / rate * 60.0
    dwell = (total - soak - 2 * ramp_s) / 2
    return _profiles.concatenate(
        _profiles.soak(25.0, soak, dt=dt), _profiles.ramp(25.0, 85.0, rate, dt=dt),
        _profiles.soak(85.0, dwell, dt=dt), _profiles.ramp(85.0, 25.0, rate, dt=dt),
        _profiles.soak(25.0, dwell, dt=dt))


def make_runs(truth, seed: int) -> list[Experiment]:
    """The three noisy chamber runs, simulated from `truth` (thermojax's exact hold)."""
    net = tj.ThermalNetwork.from_spec(truth)
    rng = np.random.default_rng(seed)
    heat = [j for j, c in enumerate(truth.input_columns) if c in truth.heat_columns]
    runs = []
    for rate in RATES:
        prof = chamber_profile(rate)
        u = tj.io.profile_inputs(truth, prof, baseline_power_w=BASE_POWER)
        u[:, heat] += STEP_POWER * ((prof.ts >= 1800) & (prof.ts < 3600))[:, None]
        y = np.asarray(tj.simulate(net, u, prof.ts).outputs)
        y = y + NOISE * rng.standard_normal(y.shape)
        runs.append(Experiment(prof.ts, u, y, f"ramp{rate:g}"))
    return runs


# ---------------------------------------------------------------------------------------------
# The SciPy side: the same model in NumPy


class NumpyModel:
    """The network of a model file as NumPy matrices; parameters = logs of the free ones,
    in thermojax's order (capacitances, link conductances, boundary conductances)."""

    def __init__(self, spec):
        self.spec = spec
        idx = {n: i for i, n in enumerate(spec.node_names)}
        cols = {c: j for j, c in enumerate(spec.input_columns)}
        self.n, self.m = len(spec.nodes), len(spec.input_columns)
        self.links = [(idx[a], idx[b]) for a, b in (k.between for k in spec.links)]
        self.bounds = [(idx[b.node], cols[b.input]) for b in spec.boundaries]
        self.heats = [(idx[h.node], cols[h.input], h.gain.value) for h in spec.heat_inputs]
        self.sensors = [idx[s.node] for s in spec.sensors]
        self.foh = np.array([h == "foh" for h in spec.input_holds])
        self.names = ([f"nodes.{n.name}.capacitance" for n in spec.nodes]
                      + [f"links.{k.key}.conductance" for k in spec.links]
                      + [f"boundaries.{b.key}.conductance" for b in spec.boundaries])
        self.p0 = np.log([n.capacitance.value for n in spec.nodes]
                         + [k.conductance.value for k in spec.links]
                         + [b.conductance.value for b in spec.boundaries])

    def continuous(self, logp):
        p = np.exp(logp)
        n, nl = self.n, len(self.links)
        c, g, gb = p[:n], p[n:n + nl], p[n + nl:]
        K = np.zeros((n, n))
        for (i, j), gij in zip(self.links, g):
            K[i, i] += gij
            K[j, j] += gij
            K[i, j] -= gij
            K[j, i] -= gij
        G = np.zeros((n, self.m))
        for (i, col), gv in zip(self.bounds, gb):
            K[i, i] += gv
            G[i, col] += gv
        for i, col, gain in self.heats:
            G[i, col] += gain
        return c, -K / c[:, None], G / c[:, None]

    def discrete(self, logp, dt):
        """`Phi, B0, B1` by `scipy.linalg.expm` of the augmented matrix (exact FOH/ZOH)."""
        c, A, B = self.continuous(logp)
        n, m = self.n, self.m
        M = np.zeros((n + 2 * m, n + 2 * m))
        M[:n, :n], M[:n, n:n + m], M[n:n + m, n + m:] = A * dt, B * dt, np.eye(m)
        E = scipy.linalg.expm(M)
        B1 = E[:n, n + m:] * self.foh
        return c, A, B, E[:n, :n], E[:n, n:n + m] - B1, B1

    def simulate_loop(self, logp, u, dt):
        """Straightforward: one NumPy step per sample, the runs side by side. u: (runs, T, m)."""
        _, A, B, Phi, B0, B1 = self.discrete(logp, dt)
        x = np.linalg.solve(A, -(u[:, 0] @ B.T).T).T  # steady state at the first sample
        R, T, _ = u.shape
        y = np.empty((R, T, len(self.sensors)))
        PhiT, B0T, B1T = Phi.T, B0.T, B1.T
        for k in range(T - 1):
            y[:, k] = x[:, self.sensors]
            x = x @ PhiT + u[:, k] @ B0T + u[:, k + 1] @ B1T
        y[:, T - 1] = x[:, self.sensors]
        return y

    def simulate_modal(self, logp, u, dt):
        """Expert: `Phi = P diag(d) P⁻¹` (reciprocal network), one `lfilter` per mode."""
        c, A, B, Phi, B0, B1 = self.discrete(logp, dt)
        s = np.sqrt(c)
        d, V = np.linalg.eigh(0.5 * (s[:, None] * Phi / s[None, :]
                                     + (s[:, None] * Phi / s[None, :]).T))
        P, Pinv = V / s[:, None], V.T * s[None, :]
        x0 = np.linalg.solve(A, -(u[:, 0] @ B.T).T).T  # (runs, n)
        drive = (u[:, :-1] @ (Pinv @ B0).T + u[:, 1:] @ (Pinv @ B1).T)  # (runs, T-1, n)
        z0 = x0 @ Pinv.T
        R, T, _ = u.shape
        z = np.empty((R, T, self.n))
        z[:, 0] = z0
        for i in range(self.n):
            z[:, 1:, i], _ = scipy.signal.lfilter([1.0], [1.0, -d[i]], drive[:, :, i], axis=1,
                                                  zi=(d[i] * z0[:, i])[:, None])
        return z @ P[self.sensors].T


def scipy_fit(model: NumpyModel, runs, simulate, p0):
    """`least_squares` (TRF, 2-point differences) on the residuals / 0.01 °C."""
    u = np.stack([r.inputs for r in runs])
    y = np.stack([r.outputs for r in runs])
    dt = runs[0].dt

    def residuals(logp):
        return ((y - simulate(logp, u, dt)) / NOISE).ravel()

    t = time.perf_counter()
    sol = scipy.optimize.least_squares(residuals, p0, method="trf", jac="2-point")
    wall = time.perf_counter() - t
    pred = simulate(sol.x, u, dt)
    return {"wall": wall, "nfev": sol.nfev, "njev": sol.njev, "x": sol.x,
            "rmse": np.sqrt(np.mean((y - pred) ** 2, axis=(0, 1))), "status": sol.status,
            "message": sol.message}


# ---------------------------------------------------------------------------------------------


class CompileCounter(logging.Handler):
    """Counts XLA compilations reported by `jax.log_compiles`."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.count = 0
        self.names: list[str] = []

    def emit(self, record):
        msg = record.getMessage()
        if msg.startswith("Finished XLA compilation"):
            self.count += 1
            self.names.append(msg.split(" in ")[0].replace("Finished XLA compilation of ", ""))


def thermojax_fit(start, runs):
    t = time.perf_counter()
    res = tj.fit(start, runs)
    wall = time.perf_counter() - t
    return res, wall


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3,
                    help="repeated thermojax and expert SciPy fits (new noise seeds)")
    ap.add_argument("--straightforward-repeats", type=int, default=1)
    args = ap.parse_args()

    truth = tj.load_model(ROOT / "configs" / "imu6.toml")
    start = perturbed(truth, 0.3, seed=1)
    np_model = NumpyModel(truth)
    p_true = np_model.p0
    p_start = NumpyModel(start).p0
    print(f"six-node IMU, {len(RATES)} runs x {int(HOURS * 3600 / DT) + 1} samples at "
          f"{1 / DT:g} Hz, {len(p_true)} free parameters, start 30 % off")
    ...


if __name__ == "__main__":
    main()
