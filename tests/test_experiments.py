"""The studies in experiments/ run end to end and recover the truth that made their data."""

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def load_study(name):
    spec = importlib.util.spec_from_file_location(name, ROOT / "experiments" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_imu6_three_ramps_study(tmp_path):
    study = load_study("imu6_three_ramps")
    folder = study.main(["--out", str(tmp_path)])
    assert folder.parent == tmp_path
    for name in ("model.toml", "report.json", "recovery.md", "parameter_recovery.png"):
        assert (folder / name).is_file(), name
    report = json.loads((folder / "report.json").read_text())
    truth = study.TRUTH
    rows = study.recovery_rows(report, __import__("thermojax").load_model(truth))
    identifiable = [r for r in rows if r["std"] is not None]
    # The data were made from configs/imu6.toml with 0.01 °C noise: every identifiable
    # parameter within 4 reported std of the truth (a chance of ~1e-3 each if honest).
    assert len(identifiable) >= 12
    assert all(abs(r["error_in_std"]) < 4 for r in identifiable)
    # The proof mass (time constant ~0.06 s against 1 s samples) cannot be determined.
    unidentifiable = {r["name"] for r in rows if r["std"] is None}
    assert "nodes.proof_mass.capacitance" in unidentifiable
