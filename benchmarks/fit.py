"""Identification benchmark: thermojax `fit` against `scipy.optimize.least_squares`.

The six-node IMU (configs/imu6.toml) is identified from three 3-hour chamber runs at
1 Hz (ramps between 25 and 85 °C and back at 1, 5 and 10 °C/min, dwells filling the
3 h, built with `thermojax.measurements._profiles`), with 0.01 °C white noise on the housing, PCB
and ASIC sensors. P_asic (gain fixed at 1) dissipates 0.05 W plus a 0.05 W step
between 30 and 60 min in each run: a known heat input fixes the absolute scale of the
capacitances and conductances. All 13 capacitances and conductances are free and
start 30 % off (`thermojax.cli._runner.perturbed(truth, 0.3, seed=1)`), the same start
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

BLAS threads: NumPy, SciPy and JAX's CPU LAPACK calls all go through OpenBLAS, whose
worker threads spin-wait after every call. On a shared machine they take the cores
from everything else: under load the expert SciPy fit was 4x slower with the default
threads (its SVDs and `expm`'s 10 x 10 products) than with one. The script therefore
re-executes itself with `OPENBLAS_NUM_THREADS=1` (the best setting for both sides
here); `--default-blas-threads` keeps the environment as it is.

Usage:  python benchmarks/fit.py [--repeats 3] [--straightforward-repeats 1]
                                 [--default-blas-threads]
"""

from __future__ import annotations

import os
import sys

if "--default-blas-threads" not in sys.argv and os.environ.get("OPENBLAS_NUM_THREADS") != "1":
    os.execve(sys.executable, [sys.executable, *sys.argv],
              {**os.environ, "OPENBLAS_NUM_THREADS": "1"})

import argparse  # noqa: E402
import logging  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402
import scipy.optimize  # noqa: E402
import scipy.signal  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import thermojax as tj  # noqa: E402
from thermojax.measurements import _profiles  # noqa: E402
from thermojax.measurements._data import Experiment  # noqa: E402
from thermojax.cli._runner import perturbed  # noqa: E402

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


def clean_runs(np_model, truth):
    """Noise-free runs (ts, inputs, outputs) simulated by the NumPy modal simulator at the
    true parameters (equal to thermojax's exact hold to ~1e-11 °C; NumPy, so that the first
    thermojax fit starts with nothing compiled)."""
    heat = [j for j, c in enumerate(truth.input_columns) if c in truth.heat_columns]
    out = []
    for rate in RATES:
        prof = chamber_profile(rate)
        u = tj.io.profile_inputs(truth, prof, baseline_power_w=BASE_POWER)
        u[:, heat] += STEP_POWER * ((prof.ts >= 1800) & (prof.ts < 3600))[:, None]
        y = np_model.simulate_modal(np_model.p0, u[None], DT)[0]
        out.append((prof.ts, u, y, f"ramp{rate:g}"))
    return out


def noisy_runs(clean, seed: int) -> list[Experiment]:
    """The clean runs with white sensor noise (std `NOISE`) from `seed`."""
    rng = np.random.default_rng(seed)
    return [Experiment(ts, u, y + NOISE * rng.standard_normal(y.shape), name)
            for ts, u, y, name in clean]


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


class CompileLog(logging.Handler):
    """Collects the XLA compilations that `jax.log_compiles` reports (name, seconds)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.entries: list[tuple[str, float]] = []

    def emit(self, record):
        msg = record.getMessage()
        if msg.startswith("Finished XLA compilation of "):
            name, _, rest = msg[len("Finished XLA compilation of "):].partition(" in ")
            self.entries.append((name, float(rest.split()[0])))

    def take(self):
        out, self.entries = self.entries, []
        return out


def timed(fn, *args):
    t, c = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - t, time.process_time() - c


def rel_errors(values: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return values / truth - 1.0


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3,
                    help="repeated thermojax and expert SciPy fits (new noise seeds)")
    ap.add_argument("--straightforward-repeats", type=int, default=1,
                    help="straightforward SciPy fits (slow: minutes each)")
    ap.add_argument("--default-blas-threads", action="store_true",
                    help="do not set OPENBLAS_NUM_THREADS=1 (see the module docstring)")
    args = ap.parse_args()
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', '(unset)')}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}")

    truth = tj.load_model(ROOT / "configs" / "imu6.toml")
    start = perturbed(truth, 0.3, seed=1)
    np_model = NumpyModel(truth)
    p_true, p_start = np.exp(np_model.p0), NumpyModel(start).p0
    names = np_model.names
    clean = clean_runs(np_model, truth)
    n_samples = len(clean[0][0])
    print(f"six-node IMU: {len(RATES)} runs x {n_samples} samples at {1 / DT:g} Hz "
          f"({HOURS:g} h, ramps {', '.join(f'{r:g}' for r in RATES)} °C/min), "
          f"{NOISE} °C noise, {len(names)} free parameters, start 30 % off")

    log = CompileLog()
    logging.getLogger("jax").addHandler(log)
    logging.getLogger("jax").setLevel(logging.DEBUG)
    jax.config.update("jax_log_compiles", True)

    rows = []  # (fitter, seed, wall, cpu, jacobians, residual evaluations, rmse, values, stds)

    def run_thermojax(seed):
        (res, wall, cpu) = timed(tj.fit, start, noisy_runs(clean, seed))
        compiles = log.take()
        values = np.array([res.parameters[nm]["value"] for nm in names])
        stds = np.array([res.parameters[nm]["std"] if res.parameters[nm]["std"] is not None
                         else np.nan for nm in names])
        rows.append(dict(fitter="thermojax", seed=seed, wall=wall, cpu=cpu, jac=res.n_steps,
                         fev=res.n_evaluations, rmse=np.array(list(res.rmse.values())),
                         values=values, stds=stds, compiles=compiles, result=res))
        return rows[-1]

    def run_scipy(kind, seed):
        sim = np_model.simulate_modal if kind == "expert" else np_model.simulate_loop
        out, wall, cpu = timed(scipy_fit, np_model, noisy_runs(clean, seed), sim, p_start)
        rows.append(dict(fitter=f"scipy {kind}", seed=seed, wall=wall, cpu=cpu,
                         jac=out["njev"], fev=out["nfev"], rmse=out["rmse"],
                         values=np.exp(out["x"]), stds=np.full(len(names), np.nan),
                         compiles=[], message=out["message"]))
        return rows[-1]

    # Interleaved: the machine may be shared, so every comparison is within this run.
    first = run_thermojax(0)
    print(f"  thermojax first fit (seed 0): {first['wall']:.2f} s, "
          f"{len(first['compiles'])} compilations ({sum(t for _, t in first['compiles']):.2f} s "
          "in XLA compilation)")
    expert0 = run_scipy("expert", 0)
    print(f"  scipy expert (seed 0): {expert0['wall']:.2f} s")
    straight = []
    for seed in range(max(args.repeats, args.straightforward_repeats) + 1):
        if seed >= 1 and seed <= args.repeats:
            r = run_thermojax(seed)
            print(f"  thermojax repeated fit (seed {seed}): {r['wall']:.3f} s, "
                  f"{len(r['compiles'])} compilations")
            r = run_scipy("expert", seed)
            print(f"  scipy expert (seed {seed}): {r['wall']:.2f} s")
        if seed < args.straightforward_repeats:
            r = run_scipy("straightforward", seed)
            straight.append(r)
            print(f"  scipy straightforward (seed {seed}): {r['wall']:.1f} s")
    report(rows, names, p_true, first)


def report(rows, names, p_true, first):
    print()
    print("Seed 0 (the same data for all three):")
    hdr = (f"{'fitter':<24}{'wall s':>9}{'cpu s':>9}{'Jacobians':>11}{'residuals':>11}"
           f"{'RMSE housing/pcb/asic (°C)':>32}")
    print(hdr)
    print("-" * len(hdr))
    seed0 = [r for r in rows if r["seed"] == 0]
    for r in seed0:
        label = r["fitter"] + (" (first, compiles)" if r is first else "")
        rm = "/".join(f"{x:.5f}" for x in r["rmse"])
        print(f"{label:<24}{r['wall']:>9.3f}{r['cpu']:>9.3f}{r['jac']:>11}{r['fev']:>11}"
              f"{rm:>32}")
    print("  thermojax: Jacobians = Gauss-Newton iterations (exact, forward sensitivities), "
          "residuals = trial points;")
    print("  scipy: Jacobians by 2-point differences (13 residual evaluations each), "
          "residuals = nfev.")

    print()
    print("Parameter errors (fitted / true - 1) on seed 0; thermojax std relative to the value:")
    fitters = [r for r in seed0]
    hdr = f"{'parameter':<42}{'true':>9}" + "".join(f"{r['fitter'][:15]:>17}" for r in fitters) \
        + f"{'thermojax std':>15}"
    print(hdr)
    print("-" * len(hdr))
    tj0 = first
    for i, nm in enumerate(names):
        cells = "".join(f"{rel_errors(r['values'][i], p_true[i]):>+17.4%}" for r in fitters)
        sd = tj0["stds"][i] / tj0["values"][i]
        sd_txt = f"{sd:.3%}" if np.isfinite(sd) else "unident."
        print(f"{nm:<42}{p_true[i]:>9.4g}{cells}{sd_txt:>15}")
    ident = np.isfinite(tj0["stds"])
    for r in fitters:
        e = np.abs(rel_errors(r["values"], p_true))
        print(f"  {r['fitter']:<22} max |error| over identifiable parameters {e[ident].max():.3%}, "
              f"over all {e.max():.3%}")
    z = (tj0["values"] - p_true) / tj0["stds"]
    print(f"  thermojax |fitted - true| / std: max {np.nanmax(np.abs(z)):.2f}, "
          f"rms {np.sqrt(np.nanmean(z ** 2)):.2f} over {int(ident.sum())} identifiable parameters")

    print()
    print("thermojax identifiability report (seed 0):")
    for m in first["result"].identifiability.messages:
        print("  -", m)

    print()
    tjr = [r for r in rows if r["fitter"] == "thermojax" and r is not first]
    exp = {r["seed"]: r for r in rows if r["fitter"] == "scipy expert"}
    straight = [r for r in rows if r["fitter"] == "scipy straightforward"]
    print("Timings over seeds (wall s):")
    for label, rs in (("thermojax repeated", tjr), ("scipy expert", list(exp.values())),
                      ("scipy straightforward", straight)):
        if rs:
            w = np.array([r["wall"] for r in rs])
            print(f"  {label:<24} median {np.median(w):8.3f}   all " +
                  ", ".join(f"{x:.3f}" for x in w))
    recompiles = sum(len(r["compiles"]) for r in tjr)
    print(f"  repeated thermojax fits compiled {recompiles} programs "
          f"({'jit cache hit' if recompiles == 0 else 'RECOMPILED: ' + str([c for r in tjr for c in r['compiles']])})")
    t_rep = np.median([r["wall"] for r in tjr]) if tjr else np.nan
    compile_s = first["wall"] - t_rep
    print(f"  thermojax compile time: first fit {first['wall']:.2f} s - repeated fit "
          f"{t_rep:.3f} s = {compile_s:.2f} s (XLA compilation alone "
          f"{sum(t for _, t in first['compiles']):.2f} s over {len(first['compiles'])} programs; "
          f"the largest: " + ", ".join(f"{n} {t:.2f} s" for n, t in
                                       sorted(first["compiles"], key=lambda c: -c[1])[:2]) + ")")

    print()
    print("Ratios (same run) and targets:")
    e_med = np.median([r["wall"] for r in exp.values()])
    ratios = [("first thermojax fit (incl. compile) / expert scipy", first["wall"] / exp[0]["wall"],
               "<= 2"),
              ("expert scipy / repeated thermojax (medians)", e_med / t_rep, ">= 10")]
    per_seed = [exp[r["seed"]]["wall"] / r["wall"] for r in tjr if r["seed"] in exp]
    if per_seed:
        ratios.append(("  per seed: expert / thermojax", float(np.median(per_seed)),
                       "(" + ", ".join(f"{x:.1f}" for x in per_seed) + ")"))
    if straight:
        ratios.append(("straightforward scipy / repeated thermojax",
                       np.median([r["wall"] for r in straight]) / t_rep, ">= 50"))
    for label, v, target in ratios:
        print(f"  {label:<55}{v:>9.2f}   target {target}")


if __name__ == "__main__":
    main()
