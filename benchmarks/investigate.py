"""Timing of `thermojax investigate` on the hidden-effect cases at full length.

Each case of `tests/hidden/` (three chamber runs of 1 to 1.6 h at 1 Hz, or its
own runs) is written by the independent generator and investigated from its
believed model, as the command line would; the script prints per case the effect
found, the baseline and final RMSE over the noise, the steps and the wall time.
There is no other tool to compare against: none automates this loop (MATLAB's
System Identification Toolbox, CTSM-R, pySIP and dynax fit a structure you give).

Usage:  python benchmarks/investigate.py [--cases a,b,...] [--horizon SECONDS]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))

from hidden import generator as g  # noqa: E402

import thermojax  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(g.case_names()))
    ap.add_argument("--horizon", type=float, default=None,
                    help="cut every run to this many seconds (default: full runs)")
    args = ap.parse_args()
    print(f"{'case':<26} {'found':<44} {'steps':>5} {'RMSE/noise start':>18} "
          f"{'final':>8} {'wall s':>8}")
    for case in args.cases.split(","):
        info = g.load_case(case)
        with tempfile.TemporaryDirectory() as tmp:
            files = g.write_case(case, tmp, seed=0, horizon_s=args.horizon)
            spec = thermojax.load_model(files["model"])
            runs = [thermojax.read_telemetry(p) for p in files["data"]]
            t0 = time.perf_counter()
            report = thermojax.investigate(spec, runs, out=Path(tmp) / "out", resume=False)
            wall = time.perf_counter() - t0
        noise = {s["column"]: float(info["noise"]) for s in info["believed"]["sensors"]}
        for b in info["believed"].get("biases", []):
            n = b["noise"]
            noise[b["column"]] = float(n["value"] if isinstance(n, dict) else n)
        steps = report["steps"]
        start = max(steps[0]["rmse"][c] / noise[c] for c in noise)
        final = max(steps[-1]["rmse"][c] / noise[c] for c in noise)
        found = ", ".join(f"{s['added']['kind']} {'-'.join(s['added']['where'])}"
                          for s in steps[1:]) or "nothing"
        print(f"{case:<26} {found:<44.44} {len(steps) - 1:>5} {start:>18.2f} {final:>8.2f} "
              f"{wall:>8.1f}   ({report['stopped_because']})", flush=True)


if __name__ == "__main__":
    main()
