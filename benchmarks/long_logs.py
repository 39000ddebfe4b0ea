"""Long logs: time and peak memory of an output-error fit against the log's length.

The six-node IMU (configs/imu6.toml) on one generated run at 1 s: the chamber a 2 h
sine between 25 and 85 °C, P_asic a 0.05 W square wave of period 20 min on 0.05 W,
0.01 °C white noise on the three sensors; noise-free outputs from the NumPy modal simulator of `benchmarks/fit.py` (SciPy's `expm` and `lfilter`, not
thermojax; equal to thermojax's free run to 1e-12 °C over 10⁷ samples). Every fit starts 30 %
off (`perturbed(truth, 0.3, seed=1)`) with the proof mass's capacitance and link fixed at
their true values: with τ = 0.1 s they are not identifiable from 1 s samples, and left
free and off they bend the MEMS capacitance (9 stds off at 10⁷ samples: the MEMS and proof
mass capacitances' sum is what the data fix). Free: 11 capacitances and conductances, the
run's six node starts, the three sensors' noise.

For each length, in a fresh process (its peak resident memory is the fit's, with the
data; the data are generated in another process and read from an `.npy` file):

- thermojax `fit` with `jacobian="auto"`, which takes the normal-equations path
  (`thermojax.fitting._normal_equations`) where the residuals' Jacobian would take more
  than 2 GB; up to `--forward-max` also `jacobian="forward"` (the Jacobian held) and
  `jacobian="normal_equations"`;
- SciPy `least_squares` (TRF, 2-point differences) on the modal simulator, the same 11
  capacitances and conductances free (steady start), up to `--scipy-max`.

It prints time, peak memory, −log L (thermojax) and the largest |value − truth| / std
per length, the fitted exponents of time and memory against samples, and the ratios.

Usage:  python benchmarks/long_logs.py [--samples 1e4 1e5 1e6 1e7] [--forward-max 1e6]
                                       [--scipy-max 1e6]
"""

from __future__ import annotations

import os
import sys

if os.environ.get("OPENBLAS_NUM_THREADS") != "1":
    os.execve(sys.executable, [sys.executable, *sys.argv],
              {**os.environ, "OPENBLAS_NUM_THREADS": "1"})

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DT, NOISE = 1.0, 0.01


def _truth():
    import thermojax as tj

    return tj.load_model(ROOT / "configs" / "imu6.toml")


def generate(n: int, path: Path) -> None:
    """The run of `n` samples: columns time, the model's inputs, its sensors."""
    sys.path.insert(0, str(HERE))
    sys.argv = [sys.argv[0], "--default-blas-threads"]   # `fit.py` keeps our environment
    from fit import NumpyModel

    truth = _truth()
    ts = np.arange(n) * DT
    chamber = 55.0 - 30.0 * np.cos(2 * np.pi * ts / 7200.0)
    power = 0.05 + 0.05 * ((ts // 600) % 2)
    cols = {"T_chamber": chamber, "P_asic": power}
    u = np.stack([cols[c] for c in truth.input_columns], axis=1)
    y = NumpyModel(truth).simulate_modal(NumpyModel(truth).p0, u[None], DT)[0]
    y = y + NOISE * np.random.default_rng(0).standard_normal(y.shape)
    np.save(path, np.column_stack([ts, u, y]))


def _start(truth):
    """The fits' start: 30 % off, the proof mass fixed at its true values."""
    import dataclasses

    from thermojax.cli._runner import perturbed
    from thermojax.model._spec import Parameter

    start = perturbed(truth, 0.3, seed=1)
    true = {n.name: n.capacitance.value for n in truth.nodes}
    true |= {k.key: k.conductance.value for k in truth.links}
    nodes = tuple(dataclasses.replace(n, capacitance=Parameter(true[n.name], True))
                  if n.name == "proof_mass" else n for n in start.nodes)
    links = tuple(dataclasses.replace(k, conductance=Parameter(true[k.key], True))
                  if "proof_mass" in k.between else k for k in start.links)
    return start.replace(nodes=nodes, links=links)


def child(kind: str, path: Path) -> dict:
    """One fit in this process: time, peak memory and the result's numbers."""
    table = np.load(path)
    import jax

    jax.config.update("jax_enable_x64", True)
    import thermojax as tj
    from thermojax.measurements._data import Experiment

    truth = _truth()
    m = len(truth.input_columns)
    run = Experiment(*(np.ascontiguousarray(a) for a in
                       (table[:, 0], table[:, 1:1 + m], table[:, 1 + m:])), "sine")
    del table   # the run holds its own columns, as one read from a file
    t = time.perf_counter()
    if kind == "scipy":
        sys.path.insert(0, str(HERE))
        sys.argv = [sys.argv[0], "--default-blas-threads"]
        from fit import NumpyModel, scipy_fit

        model = NumpyModel(truth)
        free = np.array(["proof_mass" not in name for name in model.names])
        start = NumpyModel(_start(truth)).p0

        def _full(logp_free):
            p = model.p0.copy()
            p[free] = logp_free
            return p

        out = scipy_fit(model, [run], lambda lp, u, dt: model.simulate_modal(_full(lp), u, dt),
                        start[free])
        z = np.abs(np.exp(out["x"]) / np.exp(model.p0[free]) - 1)
        result = {"nll": None, "max_z": None, "converged": out["status"] > 0,
                  "max_rel_error": float(z.max()), "method": "least_squares",
                  "evaluations": int(out["nfev"])}
    else:
        fit = tj.fit(_start(truth), [run], restart_plateaus=False,
                     jacobian="auto" if kind == "thermojax" else kind)
        values = {f"nodes.{n.name}.capacitance": n.capacitance.value for n in truth.nodes}
        values |= {f"links.{k.key}.conductance": k.conductance.value for k in truth.links}
        values |= {f"boundaries.{b.key}.conductance": b.conductance.value
                   for b in truth.boundaries}
        z = [abs(fit.parameters[k]["value"] - v) / fit.parameters[k]["std"]
             for k, v in values.items() if fit.parameters.get(k, {}).get("std")]
        result = {"nll": fit.nll, "max_z": float(max(z)), "converged": bool(fit.converged),
                  "method": fit.method.split(" (")[0][:40]}
    result["seconds"] = time.perf_counter() - t
    result["peak_gb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024 / 1e9
    return result


def _run(*args) -> dict:
    out = subprocess.run([sys.executable, __file__, *args], capture_output=True, text=True)
    if out.returncode:
        return {"error": (out.stderr.strip().splitlines() or ["?"])[-1]}
    return json.loads(out.stdout.strip().splitlines()[-1])


def _exponent(xs, ys) -> float:
    ok = [(x, y) for x, y in zip(xs, ys) if y]
    if len(ok) < 2:
        return float("nan")
    x, y = np.log([o[0] for o in ok]), np.log([o[1] for o in ok])
    return float(np.polyfit(x, y, 1)[0])


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", type=float, nargs="+", default=[1e4, 1e5, 1e6, 1e7])
    ap.add_argument("--forward-max", type=float, default=1e6)
    ap.add_argument("--scipy-max", type=float, default=1e6)
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--generate", nargs=2, help=argparse.SUPPRESS)
    ap.add_argument("--default-blas-threads", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.generate:
        generate(int(float(args.generate[0])), Path(args.generate[1]))
        return
    if args.child:
        print(json.dumps(child(args.child[0], Path(args.child[1]))))
        return
    print(f"imu6, one run at {DT:g} s, output error from 30 % off; each fit in a fresh "
          "process (peak resident memory with the data)")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.samples:
            path = Path(tmp) / f"run{int(n)}.npy"
            subprocess.run([sys.executable, __file__, "--generate", str(n), str(path)],
                           check=True)
            row = {"samples": int(n)}
            for kind, limit in (("thermojax", np.inf), ("forward", args.forward_max),
                                ("normal_equations", args.forward_max),
                                ("scipy", args.scipy_max)):
                if n <= limit:
                    row[kind] = _run("--child", kind, str(path))
                    print(f"  {int(n):>10,} {kind:9s} {row[kind]}", flush=True)
            path.unlink()
            rows.append(row)
    print("\n| samples | thermojax (path) | peak | −log L | max \\|z\\| | forward | peak "
          "| normal equations | peak | SciPy | peak | SciPy / thermojax |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")

    def cell(r, key, fmt):
        return fmt.format(r[key]) if r and r.get(key) is not None else "—"

    for row in rows:
        tj_, fw, sp = row.get("thermojax"), row.get("forward"), row.get("scipy")
        ne = row.get("normal_equations")
        ratio = (f"{sp['seconds'] / tj_['seconds']:.1f}×" if sp and tj_ and "seconds" in sp
                 and "seconds" in tj_ else "—")
        print(f"| {row['samples']:,} | {cell(tj_, 'seconds', '{:.1f} s')} "
              f"({(tj_ or {}).get('method', (tj_ or {}).get('error', '?'))}) "
              f"| {cell(tj_, 'peak_gb', '{:.2f} GB')} | {cell(tj_, 'nll', '{:.1f}')} "
              f"| {cell(tj_, 'max_z', '{:.2f}')} | {cell(fw, 'seconds', '{:.1f} s')} "
              f"| {cell(fw, 'peak_gb', '{:.2f} GB')} | {cell(ne, 'seconds', '{:.1f} s')} "
              f"| {cell(ne, 'peak_gb', '{:.2f} GB')} | {cell(sp, 'seconds', '{:.1f} s')} "
              f"| {cell(sp, 'peak_gb', '{:.2f} GB')} | {ratio} |")
    xs = [r["samples"] for r in rows]
    for key in ("seconds", "peak_gb"):
        ys = [(r.get("thermojax") or {}).get(key) for r in rows]
        print(f"thermojax {key}: fitted exponent against samples {_exponent(xs, ys):.2f}")


if __name__ == "__main__":
    main()
