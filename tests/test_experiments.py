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


def test_imu_bias_headline_study(tmp_path):
    study = load_study("imu_bias_headline")
    out = tmp_path / "headline"
    folder = study.main(["--out", str(out), "--quick"])
    assert folder == out
    for name in ("headline.md", "results.json", "residual_10cpm.png"):
        assert (folder / name).is_file(), name
    with pytest.raises(SystemExit) as refused:  # an existing folder is not overwritten
        study.main(["--out", str(out), "--quick"])
    assert refused.value.code == 2
    res = json.loads((folder / "results.json").read_text())
    rows = res["rows"]
    assert [r["rate_C_per_min"] for r in rows] == [1.0, 5.0, 10.0, 15.0]
    static = [r["static"]["peak"] for r in rows]
    # The static cubic cannot see the gradient term, which grows with the ramp rate.
    assert all(a < b for a, b in zip(static, static[1:])), static
    for r in rows:
        # Static misses most of the gradient term (K_GRAD x peak gradient, known truth).
        assert r["static"]["peak"] > 0.5 * r["peak_gradient_bias_dph"]
        # Exact model, 0.01 °C sensors: the observer leaves < 0.1 °/h (measured ~0.01).
        assert r["observer"]["peak"] < 0.1

    # Independent truth: with no noise and the true model, the observer reproduces the
    # states exactly (zero innovations), so the bias model is recovered to roundoff.
    clean = study.study(quick=True, sensor_noise=0.0, bias_noise=0.0, rates=(1.0, 10.0),
                        observers=("observer",))
    truth = list(study.POLY) + [study.K_GRAD]
    assert clean["coefficients"]["observer"] == pytest.approx(truth, rel=1e-6)  # roundoff
    assert clean["calibration"]["observer"]["rms"] < 1e-6  # °/h; roundoff only
    assert clean["rows"][1]["static"]["rms"] > clean["rows"][0]["static"]["rms"]
