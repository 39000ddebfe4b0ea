"""`thermojax demo`: the missing-physics story end to end on built-in data.

The built-in data are simulated here from `data/chain3_truth.toml` (the believed
model `data/chain3.toml` plus two effects); the investigation sees only the believed
model and the data, and has to find what is missing.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import numpy as np

from ..measurements._profiles import builtin_profile

NOISE = 0.01  # °C, white sensor noise of the built-in data
SLOT_S = 90.0  # s, PRBS slot of the die power


def _data_path(name: str) -> Path:
    return Path(str(resources.files("thermojax") / "data" / name))


def demo_runs(seed: int = 0):
    """The built-in runs as `(ts, columns)`: a 10 °C/min and a 5 °C/min chamber ramp
    (25 → 85 → 25 °C, 1 Hz) with the die dissipating PRBS power (0 / 0.4 W, 90 s slots)."""
    from .. import io
    from ..measurements._data import Dataset, Experiment
    from ..model._model import ThermalModel
    from ..dynamics._nonlinear import dataset_outputs_nonlinear

    truth = io.load_model(_data_path("chain3_truth.toml"))
    model = ThermalModel.from_spec(truth)
    rng = np.random.default_rng(seed)
    runs = []
    for name in ("ramp10", "ramp5"):
        prof = builtin_profile(name, dt=1.0)
        ts = np.asarray(prof.ts, float)
        slots = rng.integers(0, 2, size=int(ts[-1] // SLOT_S) + 1)
        power = 0.4 * slots[(ts // SLOT_S).astype(int)]
        cols = {"T_chamber": np.asarray(prof.temperature, float), "P_die": power}
        u = np.stack([cols[c] for c in truth.input_columns], 1)
        data = Dataset.from_experiments([Experiment(ts, u, np.zeros((len(ts), 2)))])
        y = np.asarray(dataset_outputs_nonlinear(model, data))[0]
        y = y + NOISE * rng.standard_normal(y.shape)
        cols.update({c: y[:, j] for j, c in enumerate(truth.sensor_columns)})
        runs.append((ts, cols))
    return runs


def run_demo(out: Path, progress=print) -> dict:
    """Write the built-in runs, investigate them from the believed model, and return the
    investigation's report."""
    from .. import io
    from ..investigation._investigate import investigate
    from ..measurements._telemetry import read_telemetry

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, (ts, cols) in enumerate(demo_runs()):
        p = out / f"chamber_run{i}.csv"
        io.write_telemetry(p, ts, cols, comments=[
            "thermojax demo: built-in chamber run simulated from data/chain3_truth.toml"])
        paths.append(p)
    progress(f"wrote {', '.join(str(p) for p in paths)}")
    spec = io.load_model(_data_path("chain3.toml"))
    runs = [read_telemetry(p) for p in paths]
    report = investigate(spec, runs, out=out / "investigation", progress=progress,
                         resume=False)
    progress(f"the error per step against the noise: "
             f"{out / 'investigation' / 'error_by_step.png'}")
    return report
