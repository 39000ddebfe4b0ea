"""The generated C observer on a Cortex-M4: instructions per step, static count of the
step function compiled by `arm-none-eabi-gcc -O2` for Thumb-2 with the single-precision
FPU (`thermojax.reference._arm`), beside the second seed's Cortex-M4 table.

    python benchmarks/observer_arm.py          # a few seconds; needs gcc-arm-none-eabi and
                                                # libnewlib-arm-none-eabi (Debian)

Each observer is `thermojax export`'s (Kalman gains for every sensor subset, the default
supervision) of a model with the seed's row's shape (states, inputs, outputs). The
count is of every instruction of `tj_observer_step` once: the straight-line path plus
the supervision's branches; the seed's figures are cycles of a plain `n² + nm + np + pn`
multiply-accumulate loop with no supervision. "MACs" is that formula; "nonzero" the
multiply-accumulates the straight-line C does (exact zeros are skipped).
"""

import pathlib
import subprocess
import sys
import tempfile
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from thermojax.observer._export import export_observer  # noqa: E402
from thermojax.reference import load_observer  # noqa: E402
from thermojax.reference._arm import M4_FLAGS, count_step_instructions  # noqa: E402

#: the second seed's table: (states, inputs, outputs) -> Cortex-M4 float32 cycles
SEED = {(2, 1, 1): 42, (3, 1, 1): 78, (4, 2, 1): 134, (6, 2, 2): 265}
CASES = [("rtd2", ["T_core"], (2, 1, 1)), ("chain3", ["T_die"], (3, 2, 1)),
         ("imu6", ["T_pcb", "T_asic"], (6, 2, 2)),
         ("imu6", ["T_housing", "T_pcb", "T_asic"], (6, 2, 3))]


def count(model, sensors, build, folder):
    folder.mkdir()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        export_observer(ROOT / "configs" / f"{model}.toml", 20.0, folder, sensors=sensors,
                        c_float="float32", fixed=None if build == "float32" else build)
    prefix = "tj_observer" if build == "float32" else f"tj_observer_{build.replace('.', '_')}"
    obj = folder / f"{prefix}.o"
    subprocess.run(["arm-none-eabi-gcc", "-std=c99", "-O2", "-ffp-contract=off", *M4_FLAGS,
                    "-c", "-o", str(obj), str(folder / f"{prefix}.c")], check=True)
    s = load_observer(folder).system
    nonzero = sum(int(np.count_nonzero(M)) for M in (np.hstack([s.Phi, s.B0, s.B1]),
                                                     np.hstack([s.C, s.D]), s.L))
    return count_step_instructions(obj, prefix), nonzero, (s.n_states, s.n_inputs, s.n_outputs)


def main():
    print("| model, sensors | n, m, p | MACs (seed formula) | nonzero MACs | seed M4 cycles "
          "(float32) | float32 step instructions (FPU, loads/stores, branches) | "
          "Q16.16 step instructions | Q31 step instructions |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for k, (model, sensors, shape) in enumerate(CASES):
            f32, nz, (n, m, p) = count(model, sensors, "float32", pathlib.Path(tmp) / f"f{k}")
            q16, _, _ = count(model, sensors, "q16.16", pathlib.Path(tmp) / f"q{k}")
            q31, _, _ = count(model, sensors, "q31", pathlib.Path(tmp) / f"r{k}")
            macs = n * n + n * m + n * p + p * n
            seed = SEED.get((n, m, p), "–")
            print(f"| {model}, {' '.join(sensors)} | {n}, {m}, {p} | {macs} | {nz} | {seed} | "
                  f"{f32['instructions']} ({f32['fpu']}, {f32['loads_stores']}, "
                  f"{f32['branches']}) | {q16['instructions']} | {q31['instructions']} |")


if __name__ == "__main__":
    main()
