"""Issue 11 leftovers: cross-correlation lags scaled to the model's slowest time constant
(text and plots, in seconds), bias columns in their own units in the plots and tables,
and the story printed on screen (near-ties; no "unexplained" line when nothing is).
"""

import argparse
import re
from pathlib import Path

import numpy as np
import pytest

from thermojax._plots import column_unit, column_units
from thermojax.fitting._fit_report import parameter_unit
from thermojax.investigation import _diagnostic_plots as dp
from thermojax.investigation._diagnostics import MAX_LAG_SAMPLES, diagnose_traces, lag_span
from thermojax.investigation._investigation_report import write_investigation_report

from test_diagnostic_report import BOUNDARY, INPUTS, _report, make_runs, white

DT = 1.0  # s
TAU = 600.0  # s, the model's slow time constant
DELAY = 300  # samples: the residual follows the input this much later


def _delayed_runs(n=6000, n_runs=2, seed=0):
    """Runs at 1 Hz whose first column's residual is a rough input delayed by `DELAY`
    samples (plus a little white noise), the second column's white."""
    rng = np.random.default_rng(seed)
    runs = []
    for r in range(n_runs):
        ts = np.arange(n) * DT
        e = rng.standard_normal(n + DELAY)
        u = np.zeros(n + DELAY)
        for k in range(1, n + DELAY):  # AR(1): a rough input, sharp correlation peak
            u[k] = 0.5 * u[k - 1] + e[k]
        drive, lagged = u[DELAY:], u[:n]  # lagged[t] = drive[t - DELAY]
        res = np.column_stack([0.5 * lagged + 0.05 * rng.standard_normal(n),
                               0.05 * rng.standard_normal(n)])
        inputs = np.column_stack([np.full(n, 25.0), 25.0 + drive, np.zeros(n)])
        predicted = np.full((n, 2), 25.0)
        runs.append({"name": f"run{r}", "ts": ts, "measured": predicted + res,
                     "predicted": predicted, "inputs": inputs})
    return runs


def test_lag_span_rule():
    assert lag_span(1.0, 100_000, TAU) == 2 * TAU  # ceil(2 τ / dt)
    assert lag_span(0.5, 100_000, 10.2) == 41
    assert lag_span(1.0, 2000, TAU) == 500  # a quarter of the shortest run
    assert lag_span(0.01, 10**7, TAU) == MAX_LAG_SAMPLES  # the cap for speed
    assert lag_span(1.0, 2000, None) == 30  # no time constant known: the old default
    assert lag_span(1.0, 2000, TAU, max_lag=7) == 7  # as given


def test_text_lags_cover_the_slow_time_constant_in_seconds():
    runs = _delayed_runs()
    cols = ["T_die", "T_housing"]
    d = diagnose_traces(cols, runs, INPUTS, BOUNDARY, time_scale=TAU)
    xc = d["tests"]["cross_correlation"]
    assert xc["lags_s"] >= TAU and xc["lags_samples"] == 2 * TAU / DT
    assert xc["slowest_time_constant_s"] == TAU
    entries = {e["label"]: e for e in d["columns"]["T_die"]["cross_correlation"]}
    top = entries["T_in"]
    assert top["lag_samples"] == DELAY and top["significant"]  # built in: a 300 s delay
    sentence = next(f for f in d["findings"] if f.startswith("T_die") and "correlates" in f)
    quoted = float(re.search(r"at lag (-?[0-9.]+) s", sentence).group(1))
    assert quoted == DELAY * DT and abs(quoted) <= xc["lags_s"]
    assert f"lags searched ±{xc['lags_s']:.0f} s" in sentence
    for e in d["columns"]["T_die"]["cross_correlation"]:
        assert abs(e["lag_s"]) <= xc["lags_s"]
    # without the time constant the old ±30 samples miss the delay altogether
    short = diagnose_traces(cols, runs, INPUTS, BOUNDARY)
    assert short["tests"]["cross_correlation"]["lags_samples"] == 30
    assert not any("T_in (peak" in f and "at lag 300 s" in f for f in short["findings"])


def _capture_figures(monkeypatch) -> dict:
    figs = {}
    monkeypatch.setattr(dp, "_save", lambda fig, path: figs.__setitem__(Path(path).name, fig))
    return figs


def test_plot_lags_in_seconds_span_the_slow_time_constant(tmp_path, monkeypatch):
    figs = _capture_figures(monkeypatch)
    runs = _delayed_runs(n=3000, n_runs=1)
    dp.diagnostic_plots(tmp_path, "step0", ["T_die", "T_housing"], runs, INPUTS, BOUNDARY,
                        time_scale=TAU)
    for key in ("step0_xcorr.png", "step0_acf.png"):
        axes = figs[key].axes
        assert axes[-1].get_xlabel().startswith("lag, s")
        assert max(abs(x) for x in axes[0].get_xlim()) >= TAU * 0.99  # samples 1..2 τ (fewer: ¼ run)
        assert figs[key]._suptitle.get_text().startswith("Step 0")


def test_column_units():
    assert column_unit("T_die") == "°C"
    assert column_unit("gyro_x_dph", bias=True) == "deg/h"
    assert column_unit("accel_x_ug", bias=True) == "µg"
    assert column_unit("mag_x", bias=True) == "bias unit"
    assert column_units(["T_die"], ["gyro_x_dph", "accel_x_ug"]) == {
        "T_die": "°C", "gyro_x_dph": "deg/h", "accel_x_ug": "µg"}
    # the fit's parameter table takes the same mapping
    assert parameter_unit("biases.gyro_x_dph.noise") == "deg/h"
    assert parameter_unit("biases.accel_x_ug.noise") == "µg"
    assert parameter_unit("biases.gyro_x_dph.poly1") == "deg/h/°C"
    assert parameter_unit("effects.viscoelastic.die-gyro_x_dph.k") == "deg/h/K"
    assert parameter_unit("sensors.T_die.noise") == "°C"


def test_bias_column_units_in_plots_and_tables(tmp_path, monkeypatch):
    figs = _capture_figures(monkeypatch)
    cols = ["T_die", "gyro_x_dph"]
    report = _report(2)
    for s in report["steps"]:
        s["rmse"] = {"T_die": s["rmse"]["T_die"], "gyro_x_dph": s["rmse"]["T_housing"]}
        s["whiteness_p"] = {"T_die": 0.3, "gyro_x_dph": 0.3}
    # a bias channel is known by its `biases.<column>.*` parameters
    report["steps"][0]["parameters"] = {"biases.gyro_x_dph.noise": {"value": 0.02, "std": None,
                                                                    "free": False}}
    report["noise"] = {"T_die": 0.03, "gyro_x_dph": 0.02}
    traces = [make_runs(np.random.default_rng(70 + i), white, n_runs=1) for i in range(2)]
    md = write_investigation_report(tmp_path, report, traces, cols, INPUTS,
                                    BOUNDARY).read_text(encoding="utf-8")
    assert "RMSE gyro_x_dph, deg/h" in md and "RMSE T_die, °C" in md  # steps table
    row = next(line for line in md.splitlines() if line.startswith("| gyro_x_dph |"))
    assert row.rstrip(" |").endswith("deg/h")  # summary table's unit column
    assert re.search(r"gyro_x_dph [0-9.e-]+ → [0-9.e-]+ deg/h", md)  # the evidence paragraph
    fit = figs["step0_fit.png"]
    labels = [ax.get_ylabel() for ax in fit.axes]
    assert "gyro_x_dph, deg/h" in labels and "residual, deg/h" in labels
    assert "T_die, °C" in labels and "residual, °C" in labels
    phases = [ax.get_ylabel() for ax in figs["step0_phases.png"].axes]
    assert sorted(phases) == ["mean residual, deg/h", "mean residual, °C"]


def test_error_chart_one_panel_per_unit(tmp_path, monkeypatch):
    import thermojax.investigation._diagnostic_plots as mod

    saved = {}
    monkeypatch.setattr(mod, "save_figure", lambda fig, path: saved.setdefault("fig", fig))
    steps = [{"rmse": {"T_die": 0.3, "gyro_x_dph": 0.1}},
             {"added": {"kind": "radiation"}, "rmse": {"T_die": 0.1, "gyro_x_dph": 0.05}}]
    mod.error_chart(tmp_path / "e.png", steps, ["T_die", "gyro_x_dph"], {},
                    units={"T_die": "°C", "gyro_x_dph": "deg/h"})
    assert sorted(ax.get_ylabel() for ax in saved["fig"].axes) == [
        "free-run RMSE, deg/h", "free-run RMSE, °C"]


# ---------------------------------------------------------------------------
# On screen


def _tied_report():
    report = _report(2)
    report["steps"][1]["added"] = {"kind": "radiation", "where": ["bulkhead", "pcb"]}
    return report


def test_investigate_story_shows_near_tie_and_no_empty_unexplained(capsys):
    from thermojax.cli._main import _print_story

    report = _tied_report()  # residuals white: `unexplained` is None
    _print_story(report)
    out = capsys.readouterr().out
    assert "near-tie: the data could not tell it apart from extra_node (pcb)" in out
    assert "unexplained" not in out
    report["unexplained"] = "the residuals of T_die stay non-white"
    _print_story(report)
    assert "unexplained: the residuals of T_die stay non-white" in capsys.readouterr().out


def test_diagnose_prints_near_tie(tmp_path, monkeypatch, capsys):
    import thermojax.cli._main as cli
    import thermojax.investigation._diagnose as diag

    cand = {"kind": "radiation", "where": ["bulkhead", "pcb"], "score_test": 812.0,
            "likelihood_ratio": 800.0, "p_value": 1e-40, "supported": True,
            "tied_with": [["extra_node", ["pcb"]]]}
    other = {"kind": "sensor_lag", "where": ["T_die"], "score_test": 3.0,
             "likelihood_ratio": None, "p_value": 0.2, "supported": False, "tied_with": []}
    monkeypatch.setattr(diag, "diagnose", lambda *a, **k: {"candidates": [cand, other],
                                                           "whiteness_p": {"T_die": 0.4}})
    monkeypatch.setattr(cli, "_read_runs", lambda paths: [])
    model = Path(__file__).parent / "hidden" / "models" / "chain3.toml"
    args = argparse.Namespace(model=str(model), data=["unused.csv"], out=str(tmp_path / "d"),
                              force=False, likelihood="output_error", progress=None)
    assert cli.cmd_diagnose(args) == 0
    out = capsys.readouterr().out
    assert "radiation (bulkhead-pcb)" in out
    assert "near-tie: the data could not tell it apart from extra_node (pcb)" in out
    assert "unexplained" not in out
