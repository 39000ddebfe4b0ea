"""Diagnostics of a model's failure and the investigation report, against known answers.

The traces are built by hand: a chamber profile with known ramps and a power step, a
"model" prediction, and a residual whose structure we choose (white, a derivative of an
input, a heating/cooling asymmetry). The checks compare with formulas written out here.
"""

import json
import re
import subprocess
import sys

import numpy as np
import pytest

from thermojax.investigation._diagnostic_plots import diagnostic_plots
from thermojax.investigation._diagnostics import diagnose_traces
from thermojax.investigation._investigation_report import write_investigation_report

DT = 10.0  # s
INPUTS = ["T_chamber", "T_in", "P_heater"]
BOUNDARY = ["T_chamber", "T_in"]  # T_in: a second boundary (a fluid inlet)
COLUMNS = ["T_die", "T_housing"]


def chamber_profile(n_dwell=180, n_ramp=180):
    """Dwell at 20 °C, ramp up 1 °C/min, dwell, ramp down, dwell; with the known phase
    of each sample (+1 heating ramp, -1 cooling ramp, 0 dwell)."""
    rate = DT / 60.0  # 1 °C/min per sample
    seg = [np.full(n_dwell, 0.0), np.full(n_ramp, rate), np.full(n_dwell, 0.0),
           np.full(n_ramp, -rate), np.full(n_dwell, 0.0)]
    sign = np.concatenate([np.zeros(n_dwell), np.ones(n_ramp), np.zeros(n_dwell),
                           -np.ones(n_ramp), np.zeros(n_dwell)])
    temp = 20.0 + np.concatenate([[0.0], np.cumsum(np.concatenate(seg))[:-1]])
    return temp, sign


def make_runs(rng, residual_fn, n_runs=2):
    """Runs over the chamber profile. `residual_fn(rng, temp, sign, inputs, ts)` returns
    the (T, 2) residual; measured = predicted + residual."""
    runs = []
    for r in range(n_runs):
        temp, sign = chamber_profile()
        n = len(temp)
        ts = np.arange(n) * DT
        e = rng.standard_normal(n) * 0.5
        t_in = np.zeros(n)
        for k in range(1, n):  # AR(1) around 25 °C: a rough input
            t_in[k] = 0.9 * t_in[k - 1] + e[k]
        t_in += 25.0
        power = np.where(ts > ts[n // 2 + 40 * r], 5.0, 0.0)
        inputs = np.column_stack([temp, t_in, power])
        predicted = np.column_stack([temp + 2.0, 0.5 * temp + 10.0])
        res = residual_fn(rng, temp, sign, inputs, ts)
        runs.append({"name": f"run{r}", "ts": ts, "measured": predicted + res,
                     "predicted": predicted, "inputs": inputs})
    return runs


def white(rng, temp, sign, inputs, ts):
    return rng.standard_normal((len(ts), 2)) * 0.05


def test_white_residuals_are_reported_white_with_no_correlation():
    runs = make_runs(np.random.default_rng(10), white)
    d = diagnose_traces(COLUMNS, runs, INPUTS, BOUNDARY)
    json.dumps(d, allow_nan=False)
    for c in COLUMNS:
        lb = d["columns"][c]["ljung_box"]
        assert lb["p"] > 1e-3 and lb["white"]  # seeded white noise: a fixed, non-extreme draw
        assert lb["lags"] == 20  # min(20, N/5) with N = 2 x 900
        assert not any(e["significant"] for e in d["columns"][c]["cross_correlation"])
        assert not d["columns"][c]["phases"]["asymmetry"]["significant"]
        assert any(f.startswith(f"{c}: residuals white") for f in d["findings"])
    assert not any("correlates" in f for f in d["findings"])
    assert not any("asymmetry" in f for f in d["findings"])


def test_derivative_residual_is_found_at_lag_zero():
    def deriv(rng, temp, sign, inputs, ts):
        r = 0.3 * np.gradient(inputs[:, 1], ts) + 0.003 * rng.standard_normal(len(ts))
        return np.column_stack([r, 0.05 * rng.standard_normal(len(ts))])

    runs = make_runs(np.random.default_rng(11), deriv)
    d = diagnose_traces(COLUMNS, runs, INPUTS, BOUNDARY, max_lag=10)
    xc = {e["label"]: e for e in d["columns"]["T_die"]["cross_correlation"]}
    top = max(xc.values(), key=lambda e: e["abs_peak"])
    assert top["label"] == "d(T_in)/dt" and top["lag_samples"] == 0 and top["lag_s"] == 0.0
    assert top["peak"] > 0.8 and top["significant"]  # residual is mostly 0.3 du/dt
    assert top["band"] == pytest.approx(1.96 / np.sqrt(2 * 900))  # pooled N
    first_corr = next(f for f in d["findings"] if f.startswith("T_die") and "correlates" in f)
    assert "d(T_in)/dt" in first_corr and "at lag 0 s" in first_corr
    assert not d["columns"]["T_die"]["ljung_box"]["white"]
    assert not any(f.startswith("T_housing") and "correlates" in f for f in d["findings"])


def test_heating_cooling_asymmetry_has_the_right_sign():
    def asym(rng, temp, sign, inputs, ts):
        r = np.where(sign > 0, 0.08, np.where(sign < 0, -0.07, 0.0))
        r = r + 0.02 * rng.standard_normal(len(ts))
        return np.column_stack([r, -r])

    rng = np.random.default_rng(12)
    runs = make_runs(rng, asym)
    d = diagnose_traces(COLUMNS, runs, INPUTS, BOUNDARY)
    ph = d["columns"]["T_die"]["phases"]
    assert ph["heating_ramp"]["mean"] == pytest.approx(0.08, abs=0.01)  # label edges: a sample
    assert ph["cooling_ramp"]["mean"] == pytest.approx(-0.07, abs=0.01)
    assert ph["heating_minus_cooling"] == pytest.approx(0.15, abs=0.01)
    assert ph["asymmetry"]["significant"]
    assert d["columns"]["T_housing"]["phases"]["heating_minus_cooling"] == pytest.approx(-0.15, abs=0.01)
    for c, sign in (("T_die", 1), ("T_housing", -1)):
        f = next(f for f in d["findings"] if f.startswith(f"{c}: heating-ramp residual"))
        h, cool = (float(x) for x in re.findall(r"([+-][0-9.]+(?:e-?\d+)?) °C", f)[:2])
        assert np.sign(h) == sign and np.sign(cool) == -sign
        assert "asymmetry" in f


def test_rmse_and_fit_percent_match_the_formulas():
    rng = np.random.default_rng(13)
    runs = make_runs(rng, white)
    runs[0]["measured"][::7, 0] = np.nan  # dropped samples
    runs[1]["measured"][:5, 1] = np.nan
    d = diagnose_traces(COLUMNS, runs, INPUTS, BOUNDARY)
    for j, c in enumerate(COLUMNS):
        y = np.concatenate([r["measured"][:, j] for r in runs])
        p = np.concatenate([r["predicted"][:, j] for r in runs])
        ok = ~np.isnan(y)
        e = y[ok] - p[ok]
        rmse = np.sqrt(np.sum(e ** 2) / ok.sum())
        fit = 100 * (1 - np.sqrt(np.sum(e ** 2)) / np.sqrt(np.sum((y[ok] - y[ok].mean()) ** 2)))
        col = d["columns"][c]
        assert col["rmse"] == pytest.approx(rmse, rel=1e-12)  # same sums; roundoff only
        assert col["fit_percent"] == pytest.approx(fit, rel=1e-12)
        assert col["n_samples"] == ok.sum()
        for r, pr in zip(runs, col["per_run"]):
            okr = ~np.isnan(r["measured"][:, j])
            er = r["measured"][okr, j] - r["predicted"][okr, j]
            assert pr["rmse"] == pytest.approx(np.sqrt(np.mean(er ** 2)), rel=1e-12)


def test_no_nan_in_json_and_bad_shapes_rejected():
    runs = make_runs(np.random.default_rng(14), white, n_runs=1)
    runs[0]["measured"][:, 1] = np.nan  # a column never measured
    runs[0]["measured"][:, 0] = 3.0  # constant: fit % undefined
    d = diagnose_traces(COLUMNS, runs, INPUTS, BOUNDARY)
    json.dumps(d, allow_nan=False)
    assert d["columns"]["T_die"]["fit_percent"] is None
    assert d["columns"]["T_housing"]["rmse"] is None
    bad = dict(runs[0], inputs=runs[0]["inputs"][:, :2])
    with pytest.raises(ValueError, match="'inputs' has shape"):
        diagnose_traces(COLUMNS, [bad], INPUTS, BOUNDARY)


def test_diagnostic_plots_written(tmp_path):
    runs = make_runs(np.random.default_rng(15), white)
    names = diagnostic_plots(tmp_path, "x", COLUMNS, runs, INPUTS, BOUNDARY)
    assert set(names) == {"fit", "acf", "xcorr", "periodogram", "phases"}
    for name in names.values():
        assert (tmp_path / name).stat().st_size > 1000


def _report(n_steps):
    kinds = [None, {"kind": "radiation", "where": ["bulkhead", "pcb"],
                    "parameters": {"coefficient": 2.1e-10}},
             {"kind": "sensor_lag", "where": ["T_die"], "parameters": {"tau": 12.0}}]
    steps = []
    for i in range(n_steps):
        nxt = kinds[i + 1] if i + 1 < n_steps else None
        cands = []
        if nxt:
            cands.append({"kind": nxt["kind"], "where": nxt["where"], "score": 800.0 / (i + 1),
                          "delta_bic": -790.0 / (i + 1), "tied_with": [["extra_node", ["pcb"]]],
                          "p_value": 1e-40, "supported": True, "method": "refit"})
        cands += [{"kind": f"k{k}", "where": ["a", "b"], "score": 5.0 - k, "delta_bic": 3.0,
                   "tied_with": []} for k in range(10)]
        steps.append({"added": kinds[i], "n_params": 13 + i,
                      "rmse": {"T_die": 0.3 / 3 ** i, "T_housing": 0.2 / 2 ** i},
                      "nll": 1000.0 - 100 * i, "aic": 2000.0 - 200 * i, "bic": 2100.0 - 190 * i,
                      "whiteness_p": {"T_die": 1e-30 * 10 ** (14 * i), "T_housing": 0.2},
                      "candidates": cands, "wall_time_s": 3.5,
                      "separation": "a step in power at a constant chamber temperature"})
    return {"schema": 1, "thermojax_version": "0", "steps": steps,
            "stopped_because": "residuals_white", "final_model": "model_final.toml",
            "noise": {"T_die": 0.03, "T_housing": 0.05},
            "significance_rule": "likelihood-ratio p < 0.001 and delta BIC < 0",
            "likelihood": "output_error", "unexplained": None}


def _pngs_exist(md: str, folder):
    refs = re.findall(r"\]\(([^)\s]+\.png)\)", md)
    assert refs
    for ref in refs:
        assert (folder / ref).is_file(), ref
    return refs


def test_report_tells_each_step(tmp_path):
    report = _report(3)
    traces = [make_runs(np.random.default_rng(20 + i), white, n_runs=1) for i in range(3)]
    path = write_investigation_report(tmp_path, report, traces, COLUMNS, INPUTS, BOUNDARY)
    md = path.read_text(encoding="utf-8")
    assert path == tmp_path / "report.md"
    assert "radiation (bulkhead–pcb)" in md and "sensor_lag (T_die)" in md
    assert "## Step 1: added radiation" in md and "## Step 2: added sensor_lag" in md
    assert "residuals became white" in md
    assert "error_by_step.png" in md
    refs = _pngs_exist(md, tmp_path)
    assert "step0_fit.png" in refs and "step2_fit.png" in refs
    # top 8 per step: the added one + k0..k6, or k0..k7 at the last step (nothing to add)
    assert md.count("| k6 ") == 3 and md.count("| k7 ") == 1 and "| k8 " not in md
    assert "extra_node (pcb)" in md  # tied candidate named
    json.loads((tmp_path / "diagnostics.json").read_text(),
               parse_constant=lambda c: pytest.fail(f"non-finite {c} in JSON"))


def test_report_with_one_step_and_bare_keys(tmp_path):
    report = {"steps": [{"added": None, "n_params": 5, "rmse": {"T_die": 0.1},
                         "nll": 1.0, "aic": 2.0, "bic": 3.0, "whiteness_p": {}, "candidates": [
                             {"kind": "radiation", "where": ["a", "b"], "score": 1.0,
                              "delta_bic": 4.0, "tied_with": []}]}],
              "stopped_because": "no_supported_candidate", "final_model": "model_final.toml"}
    traces = [make_runs(np.random.default_rng(30), white, n_runs=1)]
    path = write_investigation_report(tmp_path, report, traces, COLUMNS, INPUTS)
    md = path.read_text(encoding="utf-8")
    assert "added no effect" in md and "no candidate effect passed" in md
    _pngs_exist(md, tmp_path)
    # no traces at all still gives a report
    path = write_investigation_report(tmp_path / "bare", report, [], COLUMNS, INPUTS)
    _pngs_exist(path.read_text(encoding="utf-8"), tmp_path / "bare")


def test_writing_pngs_leaves_the_matplotlib_backend_alone(tmp_path):
    # A user's session with its own backend: importing thermojax and writing every kind of
    # PNG it makes (report, diagnostics, fit, simulation) must not switch it.
    code = f"""
import sys
import matplotlib
matplotlib.use("svg")
import numpy as np
import thermojax
from thermojax._plots import plot_fit, plot_simulation
from thermojax.investigation._investigation_report import write_investigation_report

out = {str(tmp_path)!r}
ts = np.arange(200) * 10.0
u = np.column_stack([20 + 0.01 * ts, np.where(ts > 1000, 5.0, 0.0)])
y = np.column_stack([u[:, 0] + 1.0, u[:, 0] + 2.0])
noise = np.random.default_rng(0).normal(0, 0.05, y.shape)
trace = {{"name": "r", "ts": ts, "measured": y + noise, "predicted": y, "inputs": u}}
report = {{"steps": [{{"added": None, "rmse": {{"a": 0.05, "b": 0.05}}, "candidates": []}}]}}
write_investigation_report(out, report, [[trace]], ["a", "b"], ["T_ch", "P_h"], ["T_ch"])
plot_fit(out + "/fit.png", ts, y + noise, y, ["a", "b"])
plot_simulation(out + "/sim.png", ts, {{"T_ch": u[:, 0], "P_h": u[:, 1]}}, {{"n": y[:, 0]}},
                {{"s": y[:, 0]}})
print(matplotlib.get_backend(), "matplotlib.pyplot" in sys.modules)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["svg", "False"]  # backend kept; pyplot never imported
    for name in ("fit.png", "sim.png", "error_by_step.png", "step0_fit.png"):
        assert (tmp_path / name).stat().st_size > 1000, name
