"""The Kalman loop on real data: `investigate --likelihood kalman` on PRBS1 from Ti, and
one Kalman fit of the paper's selected model, thermojax against SciPy on a NumPy filter
(issue 31 item 4: "investigate --likelihood kalman on PRBS1 from Ti <= 60 s cold", beside
SciPy on a NumPy filter in the same run).

The data: Bacher & Madsen's FlexHouse PRBS1 experiment (`../shared/realdata/prbs1/`, 1,691
samples at 300 s; one sensor, the interior air; inputs the outdoor temperature, the solar
irradiance and the heating power, all held constant between samples).

- thermojax, each in a fresh process with no persistent cache (compilation included, the
  import too): `thermojax investigate --likelihood kalman --model ti.toml --data
  prbs1.csv` (the loop from the one-node model, no hints), and `thermojax fit
  --likelihood kalman --model titethtsae.toml` (the paper's selected model from its
  published values, 19 free parameters).
- SciPy, the peer: the same selected model fitted by `scipy.optimize.minimize(method=
  "L-BFGS-B")` on the NumPy filter of `_numpy_kalman.py` from the same start (the model
  read from the TOML by `tomllib`; finite-difference gradients), stopped after
  `--scipy-budget` s. A forward selection by hand fits at least the four models of the
  paper's path and the candidates each step rejects; the SciPy fit of the final model is
  the smallest piece of that work, so the investigate-to-fit ratio is a lower bound of the
  SciPy user's cost, not an estimate of it.
- thermojax's fitted model is evaluated by the NumPy filter too (the same likelihood).

Usage:  python benchmarks/kalman_prbs1.py [--scipy-budget 1200] [--out results.json]
"""

from __future__ import annotations

import os
import sys

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

import _numpy_kalman as numpy_kalman  # noqa: E402  (beside this script)

DATA = Path(__file__).resolve().parent.parent.parent / "shared" / "realdata" / "prbs1"
DT = 300.0


def timed(args: list[str]) -> float:
    """Wall time (s) of a thermojax command in a fresh process."""
    t = time.perf_counter()
    subprocess.run(["thermojax", *args, "--no-cache", "--quiet"], check=True,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - t


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scipy-budget", type=float, default=1200.0)
    ap.add_argument("--skip-investigate", action="store_true",
                    help="time only the fits of the selected model")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--default-blas-threads", action="store_true")
    args = ap.parse_args()
    csv = DATA / "prbs1.csv"
    if not csv.is_file():
        sys.exit(f"error: the PRBS1 data are not at {DATA}; this benchmark needs the shared "
                 "real-data folder beside the repository.")
    print(f"load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} CPUs", flush=True)
    folder = Path(tempfile.mkdtemp(prefix="kalman_prbs1_"))
    out = {}
    try:
        if not args.skip_investigate:
            wall = timed(["investigate", "--likelihood", "kalman", "--model",
                          str(DATA / "ti.toml"), "--data", str(csv), "--out",
                          str(folder / "investigation")])
            report = json.loads((folder / "investigation" / "report.json").read_text())
            added = [f"{s['added']['kind']} {s['added']['where']}"
                     for s in report["steps"][1:]]
            out["investigate"] = dict(wall=wall, log_l=-report["steps"][-1]["nll"],
                                      added=added, stopped=report["stopped_because"])
            print(f"thermojax investigate from Ti: {wall:.1f} s cold, log L "
                  f"{out['investigate']['log_l']:.2f}, added {added}; target <= 60 s: "
                  f"{'met' if wall <= 60 else 'not met'}", flush=True)

        wall = timed(["fit", "--likelihood", "kalman", "--model",
                      str(DATA / "titethtsae.toml"), "--data", str(csv), "--out",
                      str(folder / "fit")])
        report = json.loads((folder / "fit" / "report.json").read_text())
        nll = report["nll"]
        with open(DATA / "titethtsae.toml", "rb") as f:
            net = numpy_kalman.Network(tomllib.load(f))
        with open(folder / "fit" / "model.toml", "rb") as f:
            fitted = net.fitted(tomllib.load(f), report)
        U, Y = numpy_kalman.read_log(csv, net.inputs, net.columns)
        at_tj = net.nll(net.x(fitted), U, Y, DT)
        out["thermojax_fit"] = dict(wall=wall, nll=nll, numpy_nll=at_tj)
        print(f"thermojax fit of TiTeThTsAe: {wall:.1f} s cold, log L {-nll:.2f} (NumPy "
              f"filter at its optimum {-at_tj:.2f}); {net.x().size} parameters", flush=True)

        sp = numpy_kalman.fit_lbfgsb(net, U, Y, DT, args.scipy_budget, at_tj)
        out["scipy_fit"] = sp
        reached = sp["reached_within_1"]
        print(f"SciPy L-BFGS-B of TiTeThTsAe: {sp['wall']:.1f} s, log L {-sp['nll']:.2f}, "
              f"{sp['nit']} iterations, {sp['nfev']} filter runs, {sp['message']}; within 1 "
              "of thermojax's optimum " + (f"after {reached:.1f} s" if reached is not None
                                           else "never"), flush=True)
        peer = reached if reached is not None else sp["wall"]
        print(f"\nratio SciPy fit / thermojax fit: {peer / wall:.2f}"
              + ("" if reached is not None else " (SciPy never within 1: a lower bound)"))
        if "investigate" in out:
            print(f"ratio thermojax investigate / SciPy fit of the final model: "
                  f"{out['investigate']['wall'] / peer:.2f} (the loop fits many models; "
                  "the SciPy user fits at least five)")
        if args.out:
            args.out.write_text(json.dumps(out, indent=1))
    finally:
        shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
