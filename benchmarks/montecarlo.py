"""Unit-variance Monte Carlo benchmark: simulation plus per-unit fit, thermojax against
SciPy per-unit loops (issue 14, item 4).

Per unit, the work is the study's identification (`thermojax.montecarlo.Study`): simulate
the unit's calibration run (the six-node IMU with its gyro bias channel,
configs/imu6_bias.toml; the population and profile of configs/montecarlo/imu6_oem.toml,
or a short profile with `--quick`), add sensor and bias-column noise, then fit the
unit's 12 log-deviations (every capacitance and link conductance) by MAP output error:
the readings / 0.01 °C, the bias column / its noise, the population's prior. Fitters:

- thermojax: one compiled program for a chunk of units (`Study.fit_units`: each unit's
  `Study.calibration_data` and `Study.fit`, one unit after another on each device: a
  trust-region Gauss-Newton run to convergence, exact Jacobians by the fitting stage's
  forward sensitivities at accepted points only), the units axis sharded over the
  local devices (`shard_map`). With `--batched`, `jax.vmap` of the same fit instead
  (each iteration for the whole chunk until its slowest unit converges: the layout
  for a GPU). Timed after a warm-up call (compilation reported separately). Also timed:
  the whole study per unit (`Study.compute_chunk`: the fit plus the test-profile
  simulation and three observers), from which a 10,000-unit study is extrapolated.
- SciPy straightforward: per unit, `scipy.optimize.least_squares` (TRF, 2-point
  differences) on the same residuals, the simulation a NumPy time loop
  (`benchmarks/fit.py`'s `NumpyModel.simulate_loop`, `scipy.linalg.expm`
  discretization).
- SciPy expert: the same with `NumpyModel.simulate_modal` (one `scipy.signal.lfilter`
  per mode), the expert variant of the fitting benchmark.

The SciPy fitters simulate each unit's clean run with their own simulator, add NumPy
noise of the same stds, and fit; their estimates are checked against the unit's true
parameters in units of thermojax's posterior std. Device scaling: the thermojax
timing again in subprocesses with `XLA_FLAGS=--xla_force_host_platform_device_count=N`.
BLAS threads: one, as in `benchmarks/fit.py` (its docstring says why).

Usage:  python benchmarks/montecarlo.py [--quick] [--chunk 32] [--straightforward-units 2]
                                        [--expert-units 4] [--devices 1,2,4] [--batched]
"""

from __future__ import annotations

import os
import sys

if "--default-blas-threads" not in sys.argv and os.environ.get("OPENBLAS_NUM_THREADS") != "1":
    os.execve(sys.executable, [sys.executable, *sys.argv],
              {**os.environ, "OPENBLAS_NUM_THREADS": "1"})

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import thermojax as tj  # noqa: E402
from thermojax.montecarlo import load_config, sample_units, shard_units, units_mesh  # noqa: E402
from thermojax.montecarlo._study import POLISH_STEPS  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fit import NumpyModel  # noqa: E402  (the fitting benchmark's SciPy side, reused)

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "montecarlo" / "imu6_oem.toml"
QUICK_PROFILE = {"lo": 0.0, "hi": 40.0, "rate": 10.0, "dwell": 120.0, "dt": 2.0,
                 "power": 0.05, "start": 25.0}


def make_study(quick: bool):
    from thermojax.montecarlo import study_of

    config = load_config(CONFIG)
    if quick:
        config.profile = dict(QUICK_PROFILE)
        config.calibration = dict(QUICK_PROFILE)
    return config, study_of(config)


# ---------------------------------------------------------------------------------------------
# thermojax


def thermojax_programs(study, seed, mesh, batched: bool = False):
    """`fit_program(logdev, units)`: calibration data and MAP fit of every unit
    (`(logdev, log_std, rms, trials, jacobians)` per unit), one unit after another on each
    device (or vmapped, `batched`); the full study per unit is `study.compute_chunk`."""
    from jax.sharding import PartitionSpec as P

    if batched:
        def one(d, u):
            return study.fit(*study.calibration_data(d, u, seed), steps=True)

        return jax.jit(jax.vmap(one))
    return jax.jit(jax.shard_map(lambda d, u: study.fit_units(d, u, seed, steps=True),
                                 mesh=mesh, in_specs=(P("units"), P("units")),
                                 out_specs=P("units"), check_vma=False))


def time_thermojax(study, logdev, units, seed, repeats: int, batched: bool = False):
    """Seconds: (compile + first call, best call) of the fit program and of the full study
    chunk, on this process's devices."""
    mesh = units_mesh()
    fit_program = thermojax_programs(study, seed, mesh, batched)
    args = shard_units((jnp.asarray(logdev), jnp.asarray(units, dtype=jnp.uint32)), mesh)
    t = time.perf_counter()
    out = jax.block_until_ready(fit_program(*args))
    first = time.perf_counter() - t
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fit_program(*args))
        best = min(best, time.perf_counter() - t)
    t = time.perf_counter()
    study.compute_chunk(logdev, units, seed, mesh)
    study_first = time.perf_counter() - t
    study_best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        study.compute_chunk(logdev, units, seed, mesh)
        study_best = min(study_best, time.perf_counter() - t)
    return {"fit_first": first, "fit_best": best, "study_first": study_first,
            "study_best": study_best, "devices": int(mesh.devices.size),
            "fitted": np.asarray(out[0]), "std": np.asarray(out[1]),
            "rms": np.asarray(out[2]), "trials": np.asarray(out[3]),
            "jacobians": np.asarray(out[4])}


# ---------------------------------------------------------------------------------------------
# SciPy: the same residuals with benchmarks/fit.py's NumPy model


class ScipyUnit:
    """The study's calibration residuals in NumPy: `simulate` is `NumpyModel.simulate_loop`
    (straightforward) or `simulate_modal` (expert), reading every node."""

    def __init__(self, study, kind: str):
        self.study = study
        self.model = NumpyModel(study.spec.replace(effects=(), biases=()))
        nodes = list(self.model.sensors)
        self.model.sensors = list(range(self.model.n))  # full states out, for the bias
        self.sensor_nodes = nodes
        self.simulate = (self.model.simulate_loop if kind == "straightforward"
                         else self.model.simulate_modal)
        self.slots = [self.model.names.index(n) for n in study.names]
        self.u = np.asarray(study.inputs_cal)
        self.dt = study.dt_cal
        mean, W = study.prior
        self.mean, self.W = mean, W

    def logp(self, d):
        p = self.model.p0.copy()
        p[self.slots] += d
        return p

    def states(self, d):
        return self.simulate(self.logp(d), self.u[None], self.dt)[0]

    def bias(self, d, x):
        b, c = self.study.bias, self.study.bias.coefficients
        dT = x[:, b.temperature] - 25.0
        out = sum(c[p] * dT ** p for p in range(b.order + 1))
        k = b.order + 1
        for p, q in b.gradients:
            out = out + c[k] * (x[:, p] - x[:, q])
            k += 1
        if b.rates:
            _, A, B = self.model.continuous(self.logp(d))
            xdot = x @ A.T + self.u @ B.T
            for r in b.rates:
                out = out + c[k] * xdot[:, r]
                k += 1
        return out

    def data(self, d_true, rng):
        x = self.states(d_true)
        y = x[:, self.sensor_nodes] + rng.standard_normal((len(x), len(self.sensor_nodes))) \
            * self.study.sensor_std[None, :]
        b = self.bias(d_true, x) + rng.standard_normal(len(x)) * self.study.bias_noise
        return y, b

    def residuals(self, d, y, b):
        x = self.states(d)
        r = [((y - x[:, self.sensor_nodes]) / self.study.sensor_std[None, :]).ravel()]
        if self.study.fit_bias:
            r.append((b - self.bias(d, x)) / self.study.bias_noise)
        r.append(self.W @ (d - self.mean))
        return np.concatenate(r)

    def unit(self, d_true, seed):
        """Simulate one unit's calibration run, fit it: (seconds, estimate, nfev)."""
        t = time.perf_counter()
        y, b = self.data(d_true, np.random.default_rng(seed))
        sol = scipy.optimize.least_squares(self.residuals, self.mean.copy(), method="trf",
                                           jac="2-point", args=(y, b))
        return time.perf_counter() - t, sol.x, sol.nfev


# ---------------------------------------------------------------------------------------------


def worker(args):
    """Subprocess: thermojax timings on this process's (forced) devices, as JSON."""
    config, study = make_study(args.quick)
    units = np.arange(args.chunk)
    params = sample_units(config.spec, config.population, units, seed=config.seed)
    got = time_thermojax(study, params.log_deviation, units, config.seed, args.repeats,
                         args.batched)
    for key in ("fitted", "std", "rms", "trials", "jacobians"):
        got.pop(key)
    print("RESULT " + json.dumps(got))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true",
                    help="a short profile (0..40 °C, 2 s samples) and few SciPy units")
    ap.add_argument("--chunk", type=int, default=32, help="units per thermojax chunk")
    ap.add_argument("--repeats", type=int, default=3, help="timed thermojax calls (best)")
    ap.add_argument("--straightforward-units", type=int, default=None)
    ap.add_argument("--expert-units", type=int, default=None)
    ap.add_argument("--devices", default="1,2,4", help="forced host device counts to time")
    ap.add_argument("--batched", action="store_true",
                    help="thermojax: vmap the fits over the chunk (not one unit after another)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--default-blas-threads", action="store_true",
                    help="do not set OPENBLAS_NUM_THREADS=1")
    args = ap.parse_args()
    if args.worker:
        return worker(args)
    n_straight = args.straightforward_units or (1 if args.quick else 2)
    n_expert = args.expert_units or (2 if args.quick else 4)
    print(f"OPENBLAS_NUM_THREADS={os.environ.get('OPENBLAS_NUM_THREADS', '(unset)')}, "
          f"{os.cpu_count()} CPUs, load average {os.getloadavg()[0]:.1f}, "
          f"jax {jax.__version__}, {jax.devices()[0].platform}")
    config, study = make_study(args.quick)
    T = len(study.ts_cal)
    print(f"six-node IMU, {len(study.names)} varied log-parameters ({config.population.preset} "
          f"preset + voids), calibration run {T} samples at {study.dt_cal:g} s "
          f"({'quick profile' if args.quick else CONFIG.name}); thermojax fits to convergence, "
          f"at most {study.iterations + POLISH_STEPS} steps"
          f"{', vmapped over the chunk' if args.batched else ', one unit after another'}")
    units = np.arange(args.chunk)
    params = sample_units(config.spec, config.population, units, seed=config.seed)

    # SciPy first (nothing compiled yet), interleaved with nothing: per-unit loops
    rows = {}
    for kind, n in (("expert", n_expert), ("straightforward", n_straight)):
        sp = ScipyUnit(study, kind)
        out = [sp.unit(params.log_deviation[i], 1000 + i) for i in range(n)]
        rows[kind] = out
        print(f"  scipy {kind}: {n} unit(s), " + ", ".join(f"{w:.2f} s ({nf} evaluations)"
                                                          for w, _, nf in out))
    tjr = time_thermojax(study, params.log_deviation, units, config.seed, args.repeats,
                         args.batched)
    fit_rate = args.chunk / tjr["fit_best"]
    study_rate = args.chunk / tjr["study_best"]
    print(f"  thermojax, {args.chunk} units on {tjr['devices']} device(s): simulation + fit "
          f"{tjr['fit_best']:.3f} s ({fit_rate:.1f} units/s; first call with compilation "
          f"{tjr['fit_first']:.1f} s); whole study {tjr['study_best']:.3f} s "
          f"({study_rate:.1f} units/s; first call {tjr['study_first']:.1f} s)")

    # estimates against the truth, in thermojax's posterior stds
    print()
    print("Estimates: max over parameters of |fitted - true| / thermojax posterior std")
    z_tj = np.abs(tjr["fitted"] - params.log_deviation) / tjr["std"]
    print(f"  thermojax, {args.chunk} units: median {np.median(z_tj.max(axis=1)):.2f}, "
          f"max {z_tj.max():.2f}; per unit " + ", ".join(f"{v:.2f}" for v in z_tj.max(axis=1)))
    print(f"  thermojax trial points per unit: {tjr['trials'].tolist()}; Jacobians (steps "
          f"taken + 1, cap {study.iterations + POLISH_STEPS} steps): "
          f"{tjr['jacobians'].tolist()}, mean {tjr['jacobians'].mean():.1f}; residual RMS "
          f"{tjr['rms'].min():.3f}-{tjr['rms'].max():.3f} noise stds")
    for kind, out in rows.items():
        z = [np.max(np.abs(x - params.log_deviation[i]) / tjr["std"][i])
             for i, (_, x, _) in enumerate(out)]
        print(f"  scipy {kind}: " + ", ".join(f"{v:.2f}" for v in z))

    print()
    print("Per unit (seconds) and ratios, same run:")
    per_tj = 1.0 / fit_rate
    result = {"thermojax_s_per_unit": per_tj, "thermojax_units_per_s": fit_rate,
              "study_units_per_s": study_rate, "devices": tjr["devices"],
              "fit_compile_s": tjr["fit_first"], "study_compile_s": tjr["study_first"],
              "trials_mean": float(tjr["trials"].mean()),
              "jacobians_mean": float(tjr["jacobians"].mean()),
              "z_max": float(z_tj.max()), "load_average": os.getloadavg()}
    for kind, out in rows.items():
        med = float(np.median([w for w, _, _ in out]))
        result[f"{kind}_s_per_unit"] = med
        result[f"{kind}_ratio"] = med / per_tj
        target = 100 if kind == "straightforward" else 10
        print(f"  scipy {kind:<16} {med:9.3f} s/unit   thermojax {per_tj:.4f} s/unit   "
              f"ratio {med / per_tj:8.1f}   target >= {target}")
    n_big = 10_000
    extrap = n_big / study_rate + tjr["study_first"]
    print(f"  a {n_big}-unit study (fit + three observers per unit), EXTRAPOLATED from the "
          f"{args.chunk}-unit chunk: {extrap / 60:.1f} min ({n_big / study_rate:.0f} s of "
          f"chunks + {tjr['study_first']:.0f} s compilation)")
    result["extrapolated_10000_s"] = extrap

    # device scaling in subprocesses
    print()
    print("Device scaling (forced host devices, subprocesses, same chunk):")
    base = None
    for n in [int(x) for x in args.devices.split(",") if x]:
        env = {**os.environ, "XLA_FLAGS": f"--xla_force_host_platform_device_count={n}"}
        cmd = [sys.executable, __file__, "--worker", "--chunk", str(args.chunk), "--repeats",
               str(args.repeats)] + (["--quick"] if args.quick else []) + (
                   ["--batched"] if args.batched else [])
        proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
        line = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
        if proc.returncode != 0 or not line:
            print(f"  {n} device(s): failed\n{proc.stderr[-2000:]}")
            continue
        got = json.loads(line[0][7:])
        rate = args.chunk / got["fit_best"]
        base = base or rate
        print(f"  {n} device(s): simulation + fit {rate:8.1f} units/s ({rate / base:.2f}x), "
              f"whole study {args.chunk / got['study_best']:.1f} units/s")
        result[f"devices_{n}_units_per_s"] = rate
    print()
    print("RESULT " + json.dumps(result))


if __name__ == "__main__":
    main()
