"""Kalman-fit benchmark on the six-node IMU: thermojax against SciPy on a NumPy filter
(issue 31 item 4: "the six-node IMU Kalman fit (4,921 samples, 3 sensors) <= 20 s first
fit", beside SciPy on a NumPy filter in the same run).

The data: `thermojax simulate --model imu6 --profile calibration --dt 7.68 --noise`
(4,923 samples, sensors on the housing, the pcb and the asic, 0.01 °C noise; the profile
drives the chamber temperature only, so the common scale of every C and G is
unidentifiable). The model: the built-in `imu6.toml`, 22 free parameters (6
capacitances, 7 conductances, 3 sensor noises, 6 process noises; the power gain is
fixed), started from the
file's values by both fitters.

- thermojax: `thermojax fit --model imu6 --data imu6.csv --likelihood kalman --no-cache`
  in a fresh process (compilation included, no persistent cache), wall time from the
  process's start to its end, the import included.
- SciPy, the peer a user would write: a NumPy continuous-discrete Kalman filter (update
  before predict, every sample; the initial mean the equilibrium at the first input, P0 =
  I °C²; exact foh (chamber) and zoh (power) sampling by `scipy.linalg.expm` of the
  augmented block matrix; Van Loan's block exponential for the process noise, on a
  step halved until ‖A‖₁h <= 1 and doubled back, as stiff nodes need), minimised by
  `scipy.optimize.minimize(method="L-BFGS-B")` with SciPy's finite-difference gradient:
  logs of the capacitances, conductances and sensor noises, the process-noise stds as
  q >= 0 (bounds, so zero is reachable), all read from the TOML by `tomllib`, not by
  thermojax (`_numpy_kalman.py`). The ratio's numerator is the time at which its −log L
  first comes within 1 of thermojax's optimum (each filter run takes about 0.4 s here,
  a finite-difference gradient 23 of them); it is stopped after `--scipy-budget`
  seconds, and if it never came that close, its whole time is given as a lower bound.
- thermojax's fitted `model.toml` is evaluated by the NumPy filter too: it must agree with
  thermojax's reported −log L (the same likelihood), and the two optima are compared on it.

BLAS threads: the script re-executes itself with `OPENBLAS_NUM_THREADS=1`
(`--default-blas-threads` keeps the environment), and removes the compilation-cache
variables, as `kalman_fit.py` does.

Usage:  python benchmarks/kalman_imu6.py [--scipy-budget 1800] [--scipy-maxiter 1000]
                                         [--out results.json]
"""

from __future__ import annotations

import os

import _cold_process  # beside this script

_cold_process.reexec()

import argparse  # noqa: E402
import json  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tomllib  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

import _numpy_kalman as numpy_kalman  # noqa: E402  (beside this script)

MODEL = Path(__file__).resolve().parent.parent / "thermojax" / "data" / "imu6.toml"
DT = 7.68


def simulate(folder: Path, seed: int) -> Path:
    csv = folder / "imu6.csv"
    subprocess.run(["thermojax", "simulate", "--model", "imu6", "--profile", "calibration",
                    "--dt", str(DT), "--noise", "--seed", str(seed), "--out", str(csv),
                    "--quiet", "--no-cache"], check=True)
    return csv


def thermojax_fit(csv: Path, folder: Path) -> dict:
    out = folder / "fit"
    t = time.perf_counter()
    subprocess.run(["thermojax", "fit", "--model", "imu6", "--data", str(csv), "--likelihood",
                    "kalman", "--no-cache", "--quiet", "--out", str(out)], check=True,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t
    report = json.loads((out / "report.json").read_text())
    with open(out / "model.toml", "rb") as f:
        fitted = tomllib.load(f)
    return dict(wall=wall, nll=report["nll"], converged=report["converged"],
                message=report["message"], n_steps=report["n_steps"], toml=fitted,
                report=report)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scipy-maxiter", type=int, default=1000)
    ap.add_argument("--scipy-budget", type=float, default=1800.0,
                    help="seconds after which SciPy is stopped (default 1800)")
    ap.add_argument("--scipy-ftol", type=float, default=None,
                    help="L-BFGS-B's relative-reduction tolerance (default SciPy's 2.2e-9, "
                         "which stops about 6 short of the optimum here)")
    ap.add_argument("--reuse", type=Path, help="a previous --out file: take thermojax's "
                    "fit from it instead of fitting again (the data are the same per seed)")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--default-blas-threads", action="store_true")
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} CPUs", flush=True)
    folder = Path(tempfile.mkdtemp(prefix="kalman_imu6_"))
    try:
        csv = simulate(folder, args.seed)
        with open(MODEL, "rb") as f:
            net = numpy_kalman.Network(tomllib.load(f))
        U, Y = numpy_kalman.read_log(csv, net.inputs, net.columns)
        print(f"{len(Y)} samples x {Y.shape[1]} sensors, {net.x().size} parameters",
              flush=True)

        if args.reuse:
            old = json.loads(args.reuse.read_text())
            tj, tj_numpy, one_eval = old["thermojax"], old["thermojax_numpy_nll"], np.nan
        else:
            tj = thermojax_fit(csv, folder)
            t = time.perf_counter()
            tj_numpy = net.nll(net.x(net.fitted(tj.pop("toml"), tj.pop("report"))), U, Y, DT)
            one_eval = time.perf_counter() - t
        print(f"thermojax: {tj['wall']:.1f} s cold (process wall, import and compilation "
              f"included), -log L {tj['nll']:.4f} (NumPy filter at its optimum "
              f"{tj_numpy:.4f}), converged {tj['converged']}", flush=True)
        print(f"SciPy L-BFGS-B on the NumPy filter ({one_eval:.2f} s per evaluation) ...",
              flush=True)
        sp = numpy_kalman.fit_lbfgsb(net, U, Y, DT, args.scipy_budget, tj_numpy,
                                     args.scipy_maxiter, args.scipy_ftol)
        reached = sp["reached_within_1"]
        print(f"SciPy: {sp['wall']:.1f} s, -log L {sp['nll']:.4f}, {sp['nit']} iterations, "
              f"{sp['nfev']} filter runs, {sp['message']}; within 1 of thermojax's optimum "
              + (f"after {reached:.1f} s" if reached is not None else "never"), flush=True)
        ratio = (reached if reached is not None else sp["wall"]) / tj["wall"]
        bound = "" if reached is not None else ", never reached: a lower bound"
        print(f"\nratio SciPy (to within 1 of thermojax's -log L{bound}) / thermojax wall: "
              f"{ratio:.2f}; target thermojax <= 20 s: "
              f"{'met' if tj['wall'] <= 20 else 'not met'}; optima (NumPy filter): thermojax "
              f"{tj_numpy:.4f}, SciPy {sp['nll']:.4f} (difference "
              f"{sp['nll'] - tj_numpy:+.4f})")
        if args.out:
            args.out.write_text(json.dumps(dict(thermojax=tj, thermojax_numpy_nll=tj_numpy,
                                                scipy=sp, ratio=ratio, seed=args.seed,
                                                numpy_eval_s=one_eval), indent=1))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
