"""Timing of `thermojax investigate` on the hidden-effect cases at full length.

Each case of `tests/hidden/` (three chamber runs of 1 to 1.6 h at 1 Hz, or its
own runs) is written by the independent generator and investigated from its
believed model, as the command line would; the script prints per case the effect
found, the baseline and final RMSE over the noise, the steps and the wall time.
There is no other tool to compare against: none automates this loop (MATLAB's
System Identification Toolbox, CTSM-R, pySIP and dynax fit a structure you give).

With `--imu6`, the brief's size instead: the six-node IMU (configs/imu6.toml) with a
hidden radiation exchange between housing and chamber and a 3 s lag on the ASIC
sensor, three 3.5 h chamber runs at 1 Hz (1, 5 and 10 °C/min ramps, PRBS ASIC power),
simulated by thermojax from the truth (the hidden-effect generator is the check of
that simulation, in tests/test_effects.py).

Usage:  python benchmarks/investigate.py [--cases a,b,...] [--horizon SECONDS] [--imu6]
                                         [--cache-dir DIR]
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


IMU6_HIDDEN = """
[[effects]]
kind = "radiation"
where = ["housing", "T_chamber"]
coefficient = 4e-10

[[effects]]
kind = "sensor_lag"
where = ["T_asic"]
time_constant = 3.0
"""


def imu6_runs(seed: int = 0, duration_s: float = 12600.0):
    """Three 3.5 h runs of imu6 plus the hidden effects, as `(ts, columns)`."""
    import numpy as np

    from thermojax.measurements._data import Dataset, Experiment
    from thermojax.model._model import ThermalModel
    from thermojax.dynamics._nonlinear import dataset_outputs_nonlinear
    from thermojax.measurements._profiles import builtin_profile

    text = (REPO / "configs" / "imu6.toml").read_text()
    truth = thermojax.parse_model(text + IMU6_HIDDEN)
    model = ThermalModel.from_spec(truth)
    rng = np.random.default_rng(seed)
    runs = []
    for name in ("ramp1", "ramp5", "ramp10"):
        prof = builtin_profile(name, dt=1.0)
        ts = np.arange(int(duration_s) + 1, dtype=float)
        temp = np.interp(ts, prof.ts, prof.temperature)  # holds the last value after the end
        slots = rng.integers(0, 2, size=int(ts[-1] // 120) + 1)
        power = 0.05 + 0.05 * slots[(ts // 120).astype(int)]
        cols = {"T_chamber": temp, "P_asic": power}
        u = np.stack([cols[c] for c in truth.input_columns], 1)
        data = Dataset.from_experiments([Experiment(ts, u, np.zeros((len(ts), 3)))])
        y = np.asarray(dataset_outputs_nonlinear(model, data))[0]
        y = y + 0.01 * rng.standard_normal(y.shape)
        cols.update({c: y[:, j] for j, c in enumerate(truth.sensor_columns)})
        runs.append((ts, cols))
    return runs


def bench_imu6() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        paths = []
        for i, (ts, cols) in enumerate(imu6_runs()):
            p = Path(tmp) / f"run{i}.csv"
            thermojax.write_telemetry(p, ts, cols)
            paths.append(p)
        spec = thermojax.load_model(REPO / "configs" / "imu6.toml")
        runs = [thermojax.read_telemetry(p) for p in paths]
        t0 = time.perf_counter()
        report = thermojax.investigate(spec, runs, out=Path(tmp) / "out", resume=False,
                                       progress=lambda m: print("  ", m, flush=True))
        wall = time.perf_counter() - t0
    for i, s in enumerate(report["steps"]):
        added = s["added"] and f"{s['added']['kind']} {s['added']['where']} " \
            f"{s['added']['parameters']}"
        print(f"step {i}: {added or 'start'}; RMSE/noise " +
              ", ".join(f"{c} {v / 0.01:.2f}" for c, v in s["rmse"].items()) +
              (f"; step wall {s['wall_time_s']:.0f} s" if s.get("wall_time_s") else ""))
    print(f"imu6, 3 x 3.5 h at 1 Hz: {wall:.1f} s in all ({report['stopped_because']})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", default=",".join(g.case_names()))
    ap.add_argument("--horizon", type=float, default=None,
                    help="cut every run to this many seconds (default: full runs)")
    ap.add_argument("--imu6", action="store_true", help="the six-node IMU scenario instead")
    ap.add_argument("--cache-dir", default=None,
                    help="keep compiled programs in this folder, as the command line does "
                    "(run twice: the first run is cold, the second warm); default: no "
                    "persistent cache")
    args = ap.parse_args()
    if args.cache_dir:
        from thermojax.compilation._cache import enable_compilation_cache

        enable_compilation_cache(args.cache_dir)
    if args.imu6:
        bench_imu6()
        return
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
