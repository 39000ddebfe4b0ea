"""The candidate machinery: multiple testing, boundary p-values, places, diagnose, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from thermojax import parse_model
from thermojax.investigation._candidates import (benjamini_hochberg, column_role,
                                   enumerate_places, refit_p_value)
from thermojax.cli import main
from thermojax.model.effects import lower_effects

from hidden import generator as g


def test_benjamini_hochberg_textbook_example():
    # Benjamini & Hochberg (1995), section 3.2: 15 p-values, q = 0.05 rejects the 4 smallest
    p = [0.0001, 0.0004, 0.0019, 0.0095, 0.0201, 0.0278, 0.0298, 0.0344, 0.0459, 0.3240,
         0.4262, 0.5719, 0.6528, 0.7590, 1.0000]
    rejected = benjamini_hochberg(p[::-1], 0.05)[::-1]
    assert rejected.tolist() == [True] * 4 + [False] * 11
    assert benjamini_hochberg([], 0.05).size == 0


def test_boundary_p_values_are_the_chi_bar_square_mixture():
    # one positive parameter: ½χ²₀ + ½χ²₁, so half the χ²₁ tail
    assert refit_p_value("radiation", 3.84, 1) == pytest.approx(0.5 * stats.chi2.sf(3.84, 1))
    # a signed parameter: the plain χ²₁ tail
    assert refit_p_value("sensor_offset", 3.84, 1) == pytest.approx(stats.chi2.sf(3.84, 1))
    # three parameters, the first on its boundary: ½χ²₂ + ½χ²₃
    assert refit_p_value("extra_node", 10.0, 3) == pytest.approx(
        0.5 * stats.chi2.sf(10.0, 2) + 0.5 * stats.chi2.sf(10.0, 3))
    # Monte Carlo: the mixture's 5 % point for a boundary parameter is χ²₁'s 10 % point
    rng = np.random.default_rng(0)
    z = rng.standard_normal(200_000)
    lr = np.maximum(z, 0) ** 2  # LR of a positive mean estimated from one N(0,1) draw
    p = np.array([refit_p_value("radiation", x, 1) for x in lr[:20_000]])
    assert abs(np.mean(p < 0.05) - 0.05) < 0.005


def test_column_guesses():
    assert column_role("T_mount", np.zeros(3)) == "temperature"
    assert column_role("P_aux", np.zeros(3)) == "power"
    assert column_role("air_speed", np.zeros(3)) == "other"


def test_places_cover_every_kind_and_unused_columns():
    spec = parse_model(g.dump_toml(g.load_case("heat_source")["believed"]))
    lowered = lower_effects(spec).spec
    places = enumerate_places(spec, lowered, {"P_aux": "power", "T_mount": "temperature"})
    kinds = {k for k, _ in places}
    assert kinds == {"extra_node", "radiation", "conductance_temperature",
                     "capacitance_temperature", "heat_source", "boundary", "conductance_input",
                     "sensor_lag", "sensor_offset", "sensor_gain"}  # no bias: no viscoelastic
    assert ("heat_source", ("P_aux", "pcb")) in places
    assert ("boundary", ("T_mount", "housing")) in places
    assert ("boundary", ("T_chamber", "die")) in places  # a second path from a used column
    assert not any(k == "heat_source" and w[0] == "T_mount" for k, w in places)
    # an effect the model has is not proposed again
    spec2 = parse_model(g.dump_toml(g.load_case("heat_source")["believed"]) +
                        '\n[[effects]]\nkind = "sensor_offset"\nwhere = ["T_die"]\noffset = 0.0\n')
    places2 = enumerate_places(spec2, lower_effects(spec2).spec, {})
    assert ("sensor_offset", ("T_die",)) not in places2


def test_a_used_heat_input_may_be_routed_to_another_node():
    # Bacher & Madsen's last step: solar radiation that already heats the interior heats
    # the envelope (a node an extra_node effect made) too. Never proposed where it heats.
    from helpers import ROOM_WITH_ENVELOPE

    spec = parse_model(ROOM_WITH_ENVELOPE)

    places = enumerate_places(spec, lower_effects(spec).spec, {})
    assert ("heat_source", ("Ps", "Te")) in places
    assert ("heat_source", ("Ps", "Ti")) not in places
    # the paths the envelope's mass made are its own parameters: not split again
    assert ("extra_node", ("Ti", "Te")) not in places and ("extra_node", ("Te", "Ta")) not in \
        places and ("extra_node", ("Te",)) in places
    assert not any(k == "heat_source" and w[0] == "Ta" for k, w in places)  # a temperature


def _write(case, folder, horizon):
    return g.write_case(case, folder, seed=0, horizon_s=horizon)


@pytest.mark.slow
def test_diagnose_cli_ranks_the_hidden_offset_first(tmp_path):
    files = _write("sensor_offset", tmp_path / "data", 1200.0)
    argv = ["diagnose", "--model", str(files["model"]), "--out", str(tmp_path / "d")]
    for p in files["data"]:
        argv += ["--data", str(p)]
    assert main(argv) == 0
    report = json.loads((tmp_path / "d" / "report.json").read_text())
    first = report["candidates"][0]
    assert (first["kind"], first["where"]) == ("sensor_offset", ["T_die"]) and first["supported"]
    assert report["whiteness_p"]["T_die"] < 1e-6
    assert report["diagnostics"]["findings"]
    assert (tmp_path / "d" / "report.md").is_file()


@pytest.mark.slow
def test_investigate_resumes_from_its_checkpoint(tmp_path, capsys):
    files = _write("sensor_offset", tmp_path / "data", 1200.0)
    out = tmp_path / "inv"
    argv = ["investigate", "--model", str(files["model"]), "--out", str(out)]
    for p in files["data"]:
        argv += ["--data", str(p)]
    assert main(argv) == 0
    first = json.loads((out / "report.json").read_text())
    assert [s["added"] and s["added"]["kind"] for s in first["steps"]] == [None,
                                                                           "sensor_offset"]
    capsys.readouterr()
    # started again with the same inputs: resumes after step 1, no candidate refitted again
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "resuming after step 1" in printed
    again = json.loads((out / "report.json").read_text())
    assert [s["added"] and s["added"]["kind"] for s in again["steps"]] == [None,
                                                                           "sensor_offset"]
    assert again["steps"][0]["candidates"] == first["steps"][0]["candidates"]
    # a data file edited in place (same path, same times, one value changed): refused,
    # naming the file, never resumed on the old steps
    data = files["data"][0]
    lines = data.read_text().splitlines()
    row = lines[-1].split(",")
    row[-1] = repr(float(row[-1]) + 0.5)
    data.write_text("\n".join(lines[:-1] + [",".join(row)]) + "\n")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "other inputs" in err and f"the data of {data}" in err and "--restart" in err
    # --restart starts afresh: nothing of the earlier run is left beside the new report
    (out / "step7_fit.png").write_bytes(b"from a longer earlier run")
    assert main(argv + ["--restart"]) == 0
    assert not (out / "step7_fit.png").exists()
    assert json.loads((out / "checkpoint.json").read_text())["inputs"]["runs"][0][
        "path"] == str(data)


@pytest.mark.slow
def test_investigate_under_the_kalman_likelihood(tmp_path):
    """The loop runs on the Kalman likelihood too (innovations for whiteness; refits
    with the exact-Hessian Newton solver). Scaled down: short runs, one step, one refit
    (the offset ranks first by its score)."""
    import thermojax

    files = _write("sensor_offset", tmp_path / "data", 900.0)
    spec = thermojax.load_model(files["model"])
    runs = [thermojax.read_telemetry(p) for p in files["data"]]
    report = thermojax.investigate(spec, runs, likelihood="kalman", refits=1, max_steps=1,
                                   holdout_check=False)
    assert report["likelihood"] == "kalman"
    added = report["steps"][1]["added"]
    assert (added["kind"], added["where"]) == ("sensor_offset", ["T_die"])
    assert abs(added["parameters"]["offset"] - 0.15) < 0.01
    assert report["steps"][1]["rmse"]["T_die"] < 1.5 * 0.01
