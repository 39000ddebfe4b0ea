"""The report's figures (issue: the report shows what the loop found): the missing heat
per step with its band, the error against the noise floor, the evidence per candidate.

A small generated case: a known pulsed heat into a node, a "reconstruction" of it with
a known std, run traces around it, and the report.json entries a loop would write. Each
figure type is rendered and must exist and be non-empty; the text must link it, state
the significance rule once and tell the added candidate from the supported ones not
added. A last test runs the real reconstruction on a generated pulses case and checks
that the truth lies in the drawn ±2σ band."""

import csv
import re
from types import SimpleNamespace

import numpy as np
import pytest

from thermojax.investigation._diagnostic_plots import error_chart, log_ticks
from thermojax.investigation._investigation_report import write_investigation_report
from thermojax.investigation._missing_heat_plots import law_heat, read_missing_heat

DT = 10.0
N = 720  # 2 h at 10 s
COLUMNS = ["T_housing", "T_die"]
INPUTS = ["T_chamber", "P_die"]
BOUNDARY = ["T_chamber"]
NODES = ["housing", "pcb", "die"]
RULE = "likelihood-ratio tests with Benjamini-Hochberg at 0.05 and a BIC drop of 10"


def _pulses(ts, r):
    return 0.3 * (((ts + 600.0 * r) % 1800.0) < 400.0)


def _case(tmp_path, law=True):
    """Two runs: a chamber ramp, PRBS die power, a pulsed heat into the pcb; step 0's
    missing-heat file (truth + a known error, its std), step 1 adds a learned law."""
    rng = np.random.default_rng(0)
    traces, heat_rows, temps = [], [], []
    for r in range(2):
        ts = np.arange(N) * DT
        chamber = 25.0 + 20.0 * np.clip(np.sin(np.pi * ts / ts[-1]), 0, None)
        power = 0.4 * rng.integers(0, 2, N // 9 + 1)[(ts // 90).astype(int)]
        q = _pulses(ts, r)
        std = np.full(N, 0.02)
        rec = q + std * rng.standard_normal(N)
        predicted = np.column_stack([chamber - 0.5, chamber + 2.0])
        measured = predicted + np.column_stack([0.1 * np.convolve(q, np.ones(30) / 30, "same"),
                                                0.01 * rng.standard_normal(N)])
        traces.append({"name": f"run{r}", "ts": ts, "measured": measured,
                       "predicted": predicted, "inputs": np.column_stack([chamber, power])})
        node_t = np.column_stack([chamber - 0.5, chamber + 1.0, chamber + 2.0])
        temps.append(node_t)
        for k in range(N):
            heat_rows.append([ts[k], r, 0.0, 0.0, rec[k], std[k], 0.0, 0.0])
    name = "step0_missing_heat.csv"
    with (tmp_path / name).open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["time_s", "run"] + [c for n in NODES for c in (f"q_{n}_W", f"q_{n}_W_std")])
        w.writerows(heat_rows)
    folds = lambda *v: [{"fold": [k, None], "gain": 5.0 if x == "for" else -5.0,  # noqa: E731
                         "vote": x} for k, x in enumerate(v)]
    law_added = {"kind": "expression", "where": ["pcb", "P_die"],
                 "expression": "c * P_die^p", "parameters": {"c": 0.7, "p": 1.0}}
    added = law_added if law else {"kind": "heat_source", "where": ["P_die", "pcb"],
                                   "parameters": {"gain": 0.7}}
    cands = [
        {**added, "score": 900.0, "score_test": 850.0, "likelihood_ratio": 900.0,
         "delta_bic": -890.0, "p_value": 1e-40, "supported": True, "method": "refit",
         "tied_with": [], "holdout_folds": folds("for", "for", "against"), "note": ""},
        {"kind": "sensor_gain", "where": ["T_die"], "score": 400.0, "score_test": 380.0,
         "likelihood_ratio": 400.0, "delta_bic": -390.0, "p_value": 1e-20, "supported": True,
         "method": "refit", "tied_with": [], "holdout_folds": [], "note": ""},
        {"kind": "radiation", "where": ["housing", "T_chamber"], "score": 30.0,
         "score_test": 30.0, "likelihood_ratio": 30.0, "delta_bic": -20.0, "p_value": 1e-6,
         "supported": True, "method": "refit", "tied_with": [],
         "holdout_folds": folds("against", "against", "for"), "note": ""},
        {"kind": "heat_source", "where": ["P_die", "pcb"], "score": 20.0, "score_test": 20.0,
         "likelihood_ratio": 20.0, "delta_bic": -12.0, "p_value": 1e-4, "supported": False,
         "method": "refit", "tied_with": [], "holdout_folds": folds("for", "against"),
         "note": "held-out check against it (leave one run out): summed gain -3 is not "
                 "positive"},
        {"kind": "sensor_offset", "where": ["T_housing"], "score": 4.0, "score_test": 4.0,
         "likelihood_ratio": None, "delta_bic": 3.0, "p_value": 0.04, "supported": False,
         "method": "score", "tied_with": [], "holdout_folds": [], "note": ""},
    ]
    steps = [
        {"added": None, "n_params": 5, "rmse": {"T_housing": 0.31, "T_die": 0.012},
         "nll": 100.0, "aic": 210.0, "bic": 230.0,
         "whiteness_p": {"T_housing": 1e-40, "T_die": 0.3},
         "whiteness_lags": {"T_housing": 20, "T_die": 20}, "candidates": cands,
         "parameters": {"sensors.T_housing.noise": {"value": 0.01, "free": False},
                        "sensors.T_die.noise": {"value": 0.01, "free": False},
                        "nodes.pcb.capacitance": {"value": 4.0},
                        "links.housing-pcb.conductance": {"value": 0.4}},
         "missing_heat": {"file": name, "nodes_carrying": ["pcb"],
                          "per_node": {"pcb": {"rms_W": 0.14, "peak_W": 0.31,
                                               "median_std_W": 0.02}}},
         "unexplained": [{"where": ["pcb"], "series": name, "what": (
             "an unrecorded heat input: pulses: 8 episodes of about 400 s and 0.3 W")}]},
        {"added": added, "n_params": 7, "rmse": {"T_housing": 0.0104, "T_die": 0.0098},
         "nll": -300.0, "aic": -586.0, "bic": -560.0,
         "whiteness_p": {"T_housing": 0.4, "T_die": 0.5},
         "whiteness_lags": {"T_housing": 20, "T_die": 20}, "candidates": [],
         "parameters": {"nodes.pcb.capacitance": {"value": 4.0},
                        "links.housing-pcb.conductance": {"value": 0.4}}},
    ]
    report = {"schema": 1, "likelihood": "output_error", "steps": steps,
              "stopped_because": "residuals_white", "final_model": "model_final.toml",
              "noise": {"T_housing": 0.01, "T_die": 0.01}, "significance_rule": RULE,
              "white_p": 0.01}
    heat = SimpleNamespace(nodes=tuple(NODES), temperatures=temps)
    return report, [traces, traces], [heat, None]


def _png(path):
    assert path.is_file() and path.stat().st_size > 5000, path
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_each_figure_type_is_rendered_linked_and_the_rule_stated_once(tmp_path):
    report, traces, heat = _case(tmp_path)
    md = write_investigation_report(tmp_path, report, traces, COLUMNS, INPUTS, BOUNDARY,
                                    missing_heat=heat,
                                    nearest={"pcb": ["T_housing", "T_die"]},
                                    input_units={"P_die": "W"}).read_text(encoding="utf-8")
    for name in ("step0_missing_heat.png", "error_by_step.png", "step0_evidence.png",
                 "step0_fit.png", "step0_acf.png", "step0_xcorr.png",
                 "step0_periodogram.png", "step0_phases.png"):
        _png(tmp_path / name)
    assert "![missing heat at step 0](step0_missing_heat.png)" in md
    assert "](step0_missing_heat.csv)" in md
    assert "![evidence per candidate at step 0](step0_evidence.png)" in md
    assert "Over the reconstruction at pcb: the heat the model of step 1" in md
    assert md.count(RULE) == 1  # stated once, at the top ...
    assert md.index(RULE) < md.index("## Step 0")
    assert "significance rule (stated at the top" in md  # ... and referred to by the step
    # the added candidate told apart from the supported ones not added
    rows = {r.split("|")[2].strip(): r for r in md.splitlines()
            if re.match(r"\| \d+ \| ", r)}
    assert "**added**" in rows["expression (pcb–P_die)"]
    assert "2 / 1 / 0" in rows["expression (pcb–P_die)"]
    assert "supported; not added" in rows["sensor_gain (T_die)"]
    assert "rejected by the held-out folds" in rows["radiation (housing–T_chamber)"]
    assert "rejected by the held-out folds" in rows["heat_source (P_die–pcb)"]
    assert "not supported" in rows["sensor_offset (T_housing)"]


def test_law_heat_is_the_expression_at_its_fitted_values():
    """The law drawn over the missing heat is its expression evaluated at the fitted
    parameters: c P^p with c = 0.7, p = 2 on a known power gives 0.7 P²."""
    p = np.linspace(0.0, 1.0, 11)
    added = {"expression": "c * P_die^p + 0 * pcb", "parameters": {"c": 0.7, "p": 2.0}}
    got = law_heat(added, NODES, np.zeros((11, 3)), INPUTS, np.column_stack([p * 0, p]))
    np.testing.assert_allclose(got, 0.7 * p ** 2)
    assert law_heat({"expression": "c * unknown", "parameters": {"c": 1.0}}, NODES,
                    np.zeros((3, 3)), INPUTS, np.zeros((3, 2))) is None


def test_the_law_is_drawn_with_the_terms_refitted_beside_it():
    """Step 1 adds a law c ΔT^2 at the housing and its refit lowers the boundary
    conductance 0.2 -> 0.1 W/K and the capacitance 25 -> 20 J/K: what step 1 accounts for
    beyond step 0 is c ΔT² − 0.1 ΔT − (20 − 25) dT/dt, written out here."""
    from thermojax.investigation._missing_heat_plots import added_heat

    ts = np.arange(0.0, 600.0, 10.0)
    housing = 25.0 + 0.05 * ts
    chamber = 40.0 + 0 * ts
    temps = np.column_stack([housing, housing + 1.0])
    inputs = np.column_stack([chamber, 0 * ts])
    before = {"parameters": {"nodes.housing.capacitance": {"value": 25.0},
                             "boundaries.housing-T_chamber.conductance": {"value": 0.2},
                             "links.housing-pcb.conductance": {"value": 0.4}}}
    after = {"added": {"kind": "expression", "where": ["housing", "T_chamber"],
                       "expression": "c * (T_chamber - housing)^2",
                       "parameters": {"c": 0.003}},
             "parameters": {"nodes.housing.capacitance": {"value": 20.0},
                            "boundaries.housing-T_chamber.conductance": {"value": 0.1},
                            "links.housing-pcb.conductance": {"value": 0.4}}}
    got = added_heat(before, after, "housing", ["housing", "pcb"], ts, temps, INPUTS,
                     inputs)
    dT = chamber - housing
    np.testing.assert_allclose(got, 0.003 * dT ** 2 - 0.1 * dT + 5.0 * 0.05, rtol=1e-9)


def test_log_ticks_never_crowd():
    """The ticks of the error chart: 0.7-0.9 and 0.009-0.01 overlapped on the old axis
    (every minor tick labelled). At most 7 ticks, none closer than a 1.5 ratio when the
    axis spans more than a decade."""
    for lo, hi in ((0.009, 0.9), (0.0098, 0.012), (1e-4, 30.0), (0.5, 0.9)):
        t = log_ticks(lo, hi)
        assert 2 <= len(t) <= 7, (lo, hi, t)
        assert all(lo * 0.5 <= v <= hi * 2 for v in t)
        if hi / lo > 10:
            assert min(b / a for a, b in zip(t, t[1:])) >= 1.5, t


def test_error_chart_draws_given_and_estimated_noise(tmp_path):
    steps = [{"added": None, "rmse": {"T_a": 0.9, "T_b": 0.05}},
             {"added": {"kind": "radiation", "where": ["housing", "T_chamber"]},
              "rmse": {"T_a": 0.011, "T_b": 0.0099}}]
    error_chart(tmp_path / "e.png", steps, ["T_a", "T_b"], {"T_a": 0.01, "T_b": 0.0098},
                {"T_a": "°C", "T_b": "°C"}, {"T_a": True, "T_b": False})
    _png(tmp_path / "e.png")


def _drawn_missing_heat(tmp_path, case_name):
    """`(case, drawn, md)`: the believed model of a hidden-suite case fitted at the truth's
    parameters on runs 0 and 1 (seed 2, cut to 2400 s), its missing heat written and its
    report drawn as the loop does, and the reconstruction read back from the file the
    figure draws (`read_missing_heat`)."""
    from hidden import generator as g

    from test_missing_heat import HORIZON_S, _fit_at_truth
    from thermojax.discovery import missing_heat, unexplained, write_missing_heat

    case, res = _fit_at_truth(case_name)
    mh = missing_heat(res)
    assert "pcb" in mh.carriers
    write_missing_heat(mh, tmp_path / "step0_missing_heat.csv")
    traces = []
    for r in (0, 1):
        ts, cols = g.generate_case(case_name, seed=2, horizon_s=HORIZON_S, runs=[r])[0]
        y = np.column_stack([cols[c] for c in res.spec.sensor_columns])
        u = np.column_stack([cols[c] for c in res.spec.input_columns])
        traces.append({"name": f"run{r}", "ts": ts, "measured": y,
                       "predicted": np.asarray(res.predictions[r]), "inputs": u})
    step = {"added": None, "n_params": 3, "rmse": dict(res.rmse), "nll": 0.0, "aic": 0.0,
            "bic": 0.0, "whiteness_p": {c: 1e-30 for c in res.spec.sensor_columns},
            "candidates": [], "missing_heat": mh.summary("step0_missing_heat.csv"),
            "unexplained": unexplained(mh, "step0_missing_heat.csv")}
    report = {"steps": [step], "stopped_because": "no_supported_candidate",
              "likelihood": "output_error"}
    md = write_investigation_report(
        tmp_path, report, [traces], list(res.spec.sensor_columns),
        list(res.spec.input_columns), list(res.spec.boundary_columns),
        missing_heat=[mh]).read_text(encoding="utf-8")
    _png(tmp_path / "step0_missing_heat.png")
    assert "![missing heat at step 0](step0_missing_heat.png)" in md
    return case, read_missing_heat(tmp_path / "step0_missing_heat.csv"), md


def _inside_band(q, s, truth) -> float:
    """The fraction of samples whose truth lies within ±2 std of the drawn heat."""
    assert len(q) == len(truth)
    return float(np.mean(np.abs(q - truth) <= 2.0 * s))


def test_pulses_truth_lies_in_the_drawn_band(tmp_path):
    """On the generated pulses case (0.3 W pulses into the unmeasured pcb, recorded by no
    column; the hidden suite's generator, cut to 2400 s), the reconstruction the report
    draws, read back from the file it draws from, holds the generator's true heat
    within ±2σ at 90 % of the samples or more, and the figure is written."""
    from hidden import generator as g

    from test_missing_heat import HORIZON_S

    case, drawn, md = _drawn_missing_heat(tmp_path, "out_of_vocabulary")
    assert "Unexplained at pcb: an unrecorded heat input: pulses" in md
    for r, run in enumerate(drawn["runs"]):
        truth = g.run_inputs(case, r, 2, HORIZON_S)[1]["Q_unrecorded"]
        inside = _inside_band(run["q"]["pcb"], run["std"]["pcb"], truth)
        assert inside >= 0.90, (r, inside)


def test_law_truth_lies_in_the_drawn_band(tmp_path):
    """On the generated law case (a fan's winding losses c·air_speed²·exp(k (T − 25)) into
    the pcb; air_speed is recorded but the model reads no such heat), the drawn
    reconstruction holds the truth's law heat, evaluated by the generator on its own
    simulated states, within ±2σ at 90 % of the samples or more."""
    from hidden import generator as g

    from test_missing_heat import HORIZON_S

    case, drawn, _ = _drawn_missing_heat(tmp_path, "law_quadratic_input")
    net = g._Network(case["truth"], None)
    for r, run in enumerate(drawn["runs"]):
        ts, inputs = g.run_inputs(case, r, 2, HORIZON_S)
        _, (X, _) = g.simulate_truth(case["truth"], ts, inputs, noise=False,
                                     return_states=True)
        U = np.column_stack([inputs[c] for c in net.cols])
        T = X[:, :len(net.names)]
        truth = np.array([net._law_heat(T[i], U[i])[0][net.idx["pcb"]]
                          for i in range(len(ts))])
        assert truth.max() > 0.1  # the law heats the pcb by a visible amount
        inside = _inside_band(run["q"]["pcb"], run["std"]["pcb"], truth)
        assert inside >= 0.90, (r, inside)
