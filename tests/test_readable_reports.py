"""Reports and plots a person reads (issue 11, items 3-5): the fit's parameter table,
the two evidence statistics told apart, the noise yardstick, diagnose titled as a
diagnosis with each plot written once, and PNGs at least 1000 px wide.
"""

import math
import struct

import numpy as np
import pytest

from thermojax._plots import plot_simulation, time_constant_groups
from thermojax.fitting._fit_report import (format_parameter_table, parameter_rows,
                                           parameter_unit)
from thermojax.investigation._candidates import Candidate
from thermojax.investigation._diagnostic_plots import settling_time
from thermojax.investigation._investigation_report import write_investigation_report

from test_diagnostic_report import BOUNDARY, COLUMNS, INPUTS, _report, make_runs, white


def png_size(path) -> tuple[int, int]:
    """(width, height) in px from the PNG header (IHDR)."""
    data = path.read_bytes()[:24]
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


FIT_REPORT = {
    "parameters": {
        "nodes.a.capacitance": {"value": 20.0, "std": 2.0, "free": True},
        "links.a-b.conductance": {"value": 0.5, "std": None, "free": True},
        "boundaries.a-T_ch.conductance": {"value": 1e-9, "std": 1e-9, "free": True},
        "heat_inputs.a-P.gain": {"value": 1.0, "std": None, "free": False},
        "runs.0.nodes.a.initial": {"value": 21.0, "std": 0.1, "free": True},
        "sensors.T_a.noise": {"value": 0.02, "std": 0.001, "free": True},
        "effects.sensor_offset.T_a.offset": {"value": -0.3, "std": 0.05, "free": True},
        "effects.radiation.a-b.coefficient": {"value": 2e-10, "std": 1e-11, "free": True},
        "nodes.b.capacitance": {"value": 3.0, "std": 0.3, "free": True},
    },
    "profile_intervals": {"nodes.b.capacitance": {"level": 0.95, "lower": 2.5,
                                                  "upper": 3.6}},
}


def test_parameter_rows_intervals_units_and_flags():
    rows = {r["name"]: r for r in parameter_rows(
        FIT_REPORT, initial={"boundaries.a-T_ch.conductance": 0.1})}
    # Wald on the log scale for a positive parameter: exp(log v ± 1.96 std/v)
    c = rows["nodes.a.capacitance"]
    assert c["interval"] == "Wald, log scale"
    assert c["lower"] == pytest.approx(20.0 * math.exp(-1.959964 * 0.1), rel=1e-6)
    assert c["upper"] == pytest.approx(20.0 * math.exp(1.959964 * 0.1), rel=1e-6)
    assert (c["unit"], c["flags"]) == ("J/K", [])
    # plain Wald for a signed parameter (an initial temperature, an offset)
    i = rows["runs.0.nodes.a.initial"]
    assert (i["interval"], i["unit"]) == ("Wald", "°C")
    assert (i["lower"], i["upper"]) == pytest.approx((21.0 - 0.196, 21.0 + 0.196), rel=1e-5)
    assert rows["effects.sensor_offset.T_a.offset"]["interval"] == "Wald"
    # the profile interval wins where computed
    b = rows["nodes.b.capacitance"]
    assert (b["interval"], b["lower"], b["upper"]) == ("profile", 2.5, 3.6)
    # flags
    assert rows["links.a-b.conductance"]["flags"] == ["unidentifiable"]
    assert rows["links.a-b.conductance"]["lower"] is None
    assert rows["heat_inputs.a-P.gain"]["flags"] == ["fixed"]
    assert "at bound" in rows["boundaries.a-T_ch.conductance"]["flags"]
    # units per kind
    assert rows["links.a-b.conductance"]["unit"] == "W/K"
    assert rows["sensors.T_a.noise"]["unit"] == "°C"
    assert rows["effects.radiation.a-b.coefficient"]["unit"] == "W/K⁴"
    assert parameter_unit("nodes.a.process_noise") == "°C/√s"
    assert parameter_unit("effects.capacitance_temperature.a.beta") == "1/K"
    assert parameter_unit("effects.sensor_lag.T_a.time_constant") == "s"
    text = format_parameter_table(list(rows.values()))
    assert "unidentifiable" in text and "profile likelihood" in text and "Wald" in text


def test_candidate_keeps_both_statistics():
    c = Candidate("radiation", ("a", "b"), 994.9, 1e-100)
    j = c.as_json()
    assert (j["score"], j["score_test"], j["likelihood_ratio"]) == (994.9, 994.9, None)
    c.score, c.method = -15.8, "refit"  # what a refit does
    j = c.as_json()
    assert (j["score"], j["score_test"], j["likelihood_ratio"]) == (-15.8, 994.9, -15.8)
    born_refit = Candidate("viscoelastic", ("a", "g"), 40.0, 1e-9, method="refit")
    assert born_refit.as_json()["score_test"] is None
    assert born_refit.as_json()["likelihood_ratio"] == 40.0


def _with_statistics(report):
    for s in report["steps"]:
        for c in s["candidates"]:
            refit = c.get("method") == "refit"
            c["score_test"] = 123.0 if refit else c["score"]
            c["likelihood_ratio"] = c["score"] if refit else None
    return report


def test_report_columns_noise_and_effect_std(tmp_path):
    report = _with_statistics(_report(2))
    report["steps"][0]["parameters"] = {
        "sensors.T_die.noise": {"value": 0.03, "std": None, "free": False},
        "sensors.T_housing.noise": {"value": 0.05, "std": 0.001, "free": True}}
    report["steps"][1]["parameters"] = {
        "effects.radiation.bulkhead-pcb.coefficient": {"value": 2.1e-10, "std": 3e-12,
                                                        "free": True}}
    traces = [make_runs(np.random.default_rng(40 + i), white, n_runs=1) for i in range(2)]
    md = write_investigation_report(tmp_path, report, traces, COLUMNS, INPUTS,
                                    BOUNDARY).read_text(encoding="utf-8")
    assert "| score test | likelihood ratio |" in md
    assert "score-test statistic 123" in md and "likelihood-ratio statistic 800" in md
    assert "given in the model" in md and "estimated" in md
    assert "no yardstick" in md
    # the ratio only for the given noise: T_die 0.1 / 0.03, T_housing none
    row = next(line for line in md.splitlines() if line.startswith("| T_housing |"))
    assert row.split("|")[6].strip() == "–"
    assert "coefficient = 2.1e-10 ± 3e-12" in md


def test_the_heat_networks_verdict_is_in_the_report(tmp_path):
    report = _with_statistics(_report(1))
    report["steps"][0]["network"] = {"node": "pcb", "verdict": "a network at pcb removes 12 %"}
    traces = [make_runs(np.random.default_rng(7), white, n_runs=1)]
    md = write_investigation_report(tmp_path, report, traces, COLUMNS, INPUTS,
                                    BOUNDARY).read_text(encoding="utf-8")
    assert "Step 0 asked a heat network: a network at pcb removes 12 %." in md


def test_diagnosis_report_titled_and_each_plot_once(tmp_path):
    report = _report(1)
    report["stopped_because"] = "diagnosis only"
    traces = [make_runs(np.random.default_rng(50), white, n_runs=2)]
    md = write_investigation_report(tmp_path, report, traces, COLUMNS, INPUTS, BOUNDARY,
                                    diagnosis=True).read_text(encoding="utf-8")
    assert md.startswith("# Diagnosis report")
    assert "Investigation report" not in md and "stopped because" not in md
    pngs = sorted(p.name for p in tmp_path.glob("*.png"))
    assert pngs == sorted(f"diagnose_{k}.png" for k in
                          ("fit", "acf", "xcorr", "periodogram", "phases"))
    for p in tmp_path.glob("*.png"):
        assert png_size(p)[0] >= 1000, p.name


def test_investigation_pngs_are_wide(tmp_path):
    report = _report(2)
    traces = [make_runs(np.random.default_rng(60 + i), white, n_runs=1) for i in range(2)]
    write_investigation_report(tmp_path, report, traces, COLUMNS, INPUTS, BOUNDARY)
    pngs = list(tmp_path.glob("*.png"))
    # five per step, the error chart, and the evidence figure of each step with
    # candidates, each once
    assert len(pngs) == 2 * 5 + 1 + 2
    for p in pngs:
        assert png_size(p)[0] >= 1000, p.name


def test_settling_time_and_groups():
    from scipy.linalg import eigh

    params = {"nodes.a.capacitance": {"value": 25.0}, "nodes.b.capacitance": {"value": 5.0},
              "boundaries.a-T.conductance": {"value": 0.12}}
    # b has no path to a boundary (it never settles): left out, so a alone, C/G
    assert settling_time(params) == pytest.approx(25.0 / 0.12, rel=1e-12)  # roundoff only
    params["links.a-b.conductance"] = {"value": 0.4}
    # the slowest mode of K x = λ C x, from scipy's generalized eigensolver
    K, C = np.array([[0.52, -0.4], [-0.4, 0.4]]), np.diag([25.0, 5.0])
    assert settling_time(params) == pytest.approx(1 / eigh(K, C, eigvals_only=True)[0],
                                                  rel=1e-9)  # float64 eigensolvers
    params["effects.sensor_lag.T_a.time_constant"] = {"value": 1e4}  # an effect slower still
    assert settling_time(params) == 1e4
    assert settling_time({}) is None
    groups = time_constant_groups({"slow": 25.0, "slow2": 11.0, "mid": 3.0, "fast": 0.1})
    assert [g for _, g in groups] == [["slow", "slow2"], ["mid"], ["fast"]]
    assert groups[0][0] == "τ ≈ 11–25 s"


def test_simulation_plot_is_wide(tmp_path):
    ts = np.arange(500) * 10.0
    nodes = {"a": 20 + 0.01 * ts, "b": 20.5 + 0.01 * ts, "c": 21 + 0.01 * ts}
    path = plot_simulation(tmp_path / "sim.png", ts, {"T_ch": 20 + 0.01 * ts,
                                                      "P": np.full(500, 0.05)},
                           nodes, {"T_a": nodes["a"]}, reference="a",
                           groups=[("τ ≈ 10 s", ["b"]), ("τ ≈ 1 s", ["c"])],
                           dynamic={"b − a": nodes["b"] - nodes["a"]})
    w, h = png_size(path)
    assert w >= 1000 and h > 500


@pytest.mark.slow  # a fit and the candidate refits (~1 min)
def test_diagnose_cli_titles_prints_and_plots_once(tmp_path, capsys):
    from hidden import generator as g
    from thermojax.cli import main

    files = g.write_case("sensor_offset", tmp_path / "data", seed=0, horizon_s=1200.0)
    argv = ["diagnose", "--model", str(files["model"]), "--out", str(tmp_path / "d"),
            "--quiet"]
    for p in files["data"]:
        argv += ["--data", str(p)]
    capsys.readouterr()
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "score test" in out and "LR" in out
    d = tmp_path / "d"
    md = (d / "report.md").read_text(encoding="utf-8")
    assert md.startswith("# Diagnosis report") and "Investigation report" not in md
    pngs = sorted(p.name for p in d.glob("*.png"))
    five = [f"diagnose_{k}.png" for k in ("fit", "acf", "xcorr", "periodogram", "phases")]
    assert set(five) <= set(pngs) and set(pngs) - set(five) <= {"diagnose_missing_heat.png"}
    for p in d.glob("*.png"):
        assert png_size(p)[0] >= 1000, p.name
    import json

    report = json.loads((d / "report.json").read_text())
    assert sorted(report["plots"].values()) == pngs
    first = report["candidates"][0]
    assert first["method"] == "refit" and first["likelihood_ratio"] == first["score"]
    assert first["score_test"] is not None


def test_story_on_screen_names_near_ties_and_unexplained(capsys):
    from thermojax.cli._main import _print_story

    report = _report(2)
    report["steps"][1]["added"] = {"kind": "radiation", "where": ["bulkhead", "pcb"]}
    report["unexplained"] = "the residuals of T_die stay non-white"
    report["stopped_because"] = "no_supported_candidate"
    _print_story(report)
    out = capsys.readouterr().out
    assert "+ radiation (bulkhead-pcb)" in out
    assert "near-tie: the data could not tell it apart from extra_node (pcb)" in out
    assert "what would separate them: a step in power" in out
    assert "unexplained: the residuals of T_die stay non-white" in out
