"""Wall-clock timings that used to be asserted in tests (issue 71: a shared CI machine's
clock says nothing about the code, so the tests check results only and the times live
here).

- `read_telemetry` of a four-hour run at 1 Hz (time plus 5 channels, every 13th sample
  of one channel dropped): target under 1 s (measured ~0.05 s when it was a test).
- the hidden-effect truth generator (`tests/hidden/generator.py`): 3.5 h at 1 Hz of the
  3-node chain with radiation and a sensor lag: target well under 60 s.

Usage:  python benchmarks/wallclock.py [--repeats 3]
Prints the best of `--repeats` for each and whether it meets its target; exits 1 if one
does not.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def best_of(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def telemetry(repeats: int) -> float:
    from thermojax.measurements._telemetry import read_telemetry, write_telemetry

    n = 14_400
    rng = np.random.default_rng(1)
    channels = {f"c{i}": rng.standard_normal(n) for i in range(5)}
    channels["c2"][::13] = np.nan
    with tempfile.TemporaryDirectory() as tmp:
        path = write_telemetry(Path(tmp) / "big.csv", np.arange(n, dtype=np.float64), channels)
        return best_of(lambda: read_telemetry(path), repeats)


def generator(repeats: int) -> float:
    from tests.hidden import generator as g

    ts = np.arange(3.5 * 3600 + 1)
    raw = g.chamber_inputs(ts, "ramp5", seed=0)
    doc = tomllib.loads((g.MODELS / "chain3.toml").read_text())
    doc["effects"] = [dict(kind="radiation", where=["housing", "T_chamber"], coefficient=3e-10),
                      dict(kind="sensor_lag", where=["T_housing"], time_constant=5.0)]
    return best_of(lambda: g.simulate_truth(doc, ts, raw, np.random.default_rng(0)), repeats)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    ok = True
    for name, fn, target in (("read_telemetry, 4 h at 1 Hz", telemetry, 1.0),
                             ("hidden generator, 3.5 h at 1 Hz", generator, 60.0)):
        t = fn(args.repeats)
        ok &= t < target
        print(f"{name}: {t:.3f} s (target < {target:g} s){'' if t < target else '  MISSED'}")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
