"""How the loop's time grows with the length of a log: `investigate --likelihood kalman`
from the one-node model on one generated building log at 15-minute sampling, at several
lengths, with each step's wall time split by phase (`steps[i].phase_times_s`: score
tests, refits, held-out folds, the missing heat waited for, the heat network, and the
JAX compilation inside them), and the fitted exponent of time per step against the
number of samples (1: linear).

The data: a four-state building of the hidden suite (`tests/hidden/buildings.py`:
interior, heating medium, envelope and a sensor with its own lag; outdoor temperature,
solar and a PRBS heater; process and sensor noise), by default `building_4state_ct`,
whose heating medium's capacitance varies with its temperature (the one nonlinear
effect: every fit after it is an extended Kalman filter), `--case building_4state` the
linear one; the same seed at every length, so each longer log extends the shorter one. Each length runs in a fresh process with no persistent
cache: cold, compilation included.

The peer, on the same log from the same model file, for as long as thermojax took on it
(`--scipy-factor`: that many times as long):
the forward selection a CTSM-R user scripts, with SciPy's L-BFGS-B (finite-difference
gradients) on a NumPy filter (`_scipy_selection.py`): its steps finished in that budget
and its start's −log L beside thermojax's (the same likelihood: they agree where both
reach the optimum).

Usage:  python benchmarks/loop_scaling.py [--samples 2000,7000,20000] [--max-steps 5]
        [--case building_4state_ct] [--out results.json] [--no-scipy | --scipy-factor F]
"""

from __future__ import annotations

import _cold_process  # beside this script

_cold_process.reexec()

import argparse  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from hidden.buildings import DT, write_building_case  # noqa: E402



def run_length(case: str, n_samples: int, max_steps: int, folder: Path) -> dict:
    """One cold `investigate` on the first `n_samples` of the log: its report and wall time."""
    files = write_building_case(case, folder, seed=0, days=n_samples * DT / 86400)
    out = folder / "out"
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "thermojax", "investigate", "--likelihood",
                           "kalman", "--model", str(files["model"]), "--data",
                           str(files["data"][0]), "--out", str(out), "--max-steps",
                           str(max_steps), "--no-cache"], capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"investigate failed on {n_samples} samples:\n{proc.stderr[-3000:]}")
    report = json.loads((out / "report.json").read_text())
    # what the loop said to expect of each step, before it and once scored
    said = [line.strip() for line in (proc.stdout + proc.stderr).splitlines()
            if "expect" in line]
    return {"samples": n_samples, "wall_s": wall, "report": report, "expected": said,
            "files": files}


def run_peer(files: dict, budget: float) -> dict:
    """The SciPy peer's forward selection (`_scipy_selection.py`) on the same log and
    start model, stopped after `budget` s."""
    import tomllib

    import _numpy_kalman as numpy_kalman
    import _scipy_selection as scipy_selection

    toml = tomllib.loads(Path(files["model"]).read_text())
    net = numpy_kalman.Network(toml)
    U, Y = numpy_kalman.read_log(files["data"][0], net.inputs, net.columns)
    with np.errstate(all="ignore"):  # a trial step far out: its NaN counts as +inf
        return scipy_selection.forward_selection(toml, U, Y, DT, budget)


def growth_exponent(samples, seconds) -> float:
    """The slope of log time against log samples (least squares)."""
    return float(np.polyfit(np.log(samples), np.log(seconds), 1)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--samples", default="2000,7000,20000")
    ap.add_argument("--max-steps", type=int, default=5)
    ap.add_argument("--case", default="building_4state_ct")
    ap.add_argument("--out", default=None, help="also write the numbers as JSON here")
    ap.add_argument("--no-scipy", action="store_true",
                    help="leave out the SciPy peer's forward selection (it runs for as long "
                         "as thermojax took on the same log)")
    ap.add_argument("--scipy-factor", type=float, default=1.0,
                    help="give the SciPy peer this many times thermojax's time (default 1)")
    args = ap.parse_args()
    lengths = [int(s) for s in args.samples.split(",")]
    results = []
    for n in lengths:
        with tempfile.TemporaryDirectory() as tmp:
            r = run_length(args.case, n, args.max_steps, Path(tmp))
            if not args.no_scipy:
                r["peer_budget_s"] = args.scipy_factor * r["wall_s"]
                print(f"\n{n} samples: the SciPy peer for {r['peer_budget_s']:.0f} s "
                      f"({args.scipy_factor:g} × thermojax's {r['wall_s']:.0f} s)", flush=True)
                r["peer"] = run_peer(r["files"], r["peer_budget_s"])
        results.append(r)
        steps = r["report"]["steps"]
        print(f"\n{n} samples ({n * DT / 86400:.0f} days): {r['wall_s']:.0f} s in all, "
              f"stopped: {r['report']['stopped_because']}", flush=True)
        for i, s in enumerate(steps):
            added = s["added"] and f"{s['added']['kind']} {'-'.join(s['added']['where'])}"
            phases = s.get("phase_times_s") or {}
            split = ", ".join(f"{k} {v:.0f}" for k, v in sorted(phases.items(),
                                                                   key=lambda kv: -kv[1]))
            print(f"  step {i} {added or 'start':<40} −log L {s['nll']:10.1f}  "
                  f"{s.get('wall_time_s') or 0:7.0f} s  ({split})", flush=True)
        for line in r["expected"]:
            print(f"  said: {line}", flush=True)
        if "peer" in r:
            peer = r["peer"]
            done = len(peer["steps"]) - 1
            print(f"  SciPy peer in {r['peer_budget_s']:.0f} s: {done} step(s) finished "
                  f"of thermojax's {len(steps) - 1}, {peer['fits']} fits, stopped: "
                  f"{peer['stopped']}; start −log L {peer['steps'][0][1]:.1f} "
                  f"(thermojax {steps[0]['nll']:.1f})", flush=True)
            for label, nll, at in peer["steps"][1:]:
                print(f"    + {label:<38} −log L {nll:10.1f}  at {at:5.0f} s", flush=True)
    if len(results) > 1:
        walls = [r["wall_s"] for r in results]
        # the steps that scored candidates (the last step of a `max_steps` stop did not)
        per_step = [np.mean([s["wall_time_s"] for s in r["report"]["steps"]
                             if s.get("wall_time_s")]) for r in results]
        print(f"\ngrowth exponent of the whole loop's time: "
              f"{growth_exponent(lengths, walls):.2f}; of the time per step: "
              f"{growth_exponent(lengths, per_step):.2f} (1 is linear)")
    if args.out:
        Path(args.out).write_text(json.dumps(
            [{"samples": r["samples"], "wall_s": r["wall_s"],
              "steps": [{"added": s["added"], "nll": s["nll"],
                         "wall_time_s": s.get("wall_time_s"),
                         "phase_times_s": s.get("phase_times_s")}
                        for s in r["report"]["steps"]],
              "peer": {k: v for k, v in r.get("peer", {}).items()}} for r in results],
            indent=2))


if __name__ == "__main__":
    main()
