"""`thermojax fit` and `thermojax run` (formats spec §5): files written, report keys, bad input.

The data are helpers' rtd2h runs (simulated by NumPy from a known truth) written as CSV;
the checks compare the written report with that truth, recompute what can be recomputed
(the table's numbers from report.json, the model file through `load_model`), and parse
the JSON strictly. The CLI runs in-process from the folder holding `a.csv` and `b.csv`,
so it fits under the same run names as the library tests and reuses their compilation.
"""

import json
import math
import re

import numpy as np
import pytest

import thermojax as tj
from thermojax import write_telemetry
from thermojax.measurements._data import Experiment
from thermojax.fitting._fit import fit
from thermojax.cli import main

from helpers import (CONFIGS, RTD2H_NAMES, RTD2H_TEXT, RTD2H_TRUTH, rtd2h_data,
                     rtd2h_kalman_fit, rtd2h_oe_fit)

DOTTED = {
    "nodes.sheath.capacitance", "nodes.core.capacitance", "links.sheath-core.conductance",
    "boundaries.sheath-T_fluid.conductance", "heat_inputs.sheath-P_heater.gain",
    "sensors.T_core.noise", "sensors.T_sheath.noise", "runs.0.nodes.core.initial",
    "runs.1.nodes.core.initial",
}


def run(capsys, *argv):
    """`thermojax argv...` in-process: (exit status, stdout, stderr)."""
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def strict_json(text: str):
    """json.loads that refuses NaN and ±Infinity (JSON never holds NaN, spec §5)."""
    def refuse(name):
        raise ValueError(f"report.json holds {name}")

    return json.loads(text, parse_constant=refuse)


def write_runs(folder, process_noise=False, drop_column=None):
    """Write a.csv and b.csv (helpers' rtd2h runs) into `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    for name, (ts, U, Y, *_) in zip(RTD2H_NAMES, rtd2h_data(1, process_noise)):
        channels = {"T_fluid": U[:, 0], "P_heater": U[:, 1], "T_core": Y[:, 0],
                    "T_sheath": Y[:, 1]}
        channels.pop(drop_column, None)
        write_telemetry(folder / name, ts, channels, comments=["rtd2h synthetic run"])
    (folder / "rtd2h.toml").write_text(RTD2H_TEXT)


@pytest.fixture(scope="module")
def oe_cli(tmp_path_factory):
    """One `thermojax fit` run (output error) and what it wrote and printed."""
    folder = tmp_path_factory.mktemp("fit_cli")
    write_runs(folder)
    rtd2h_oe_fit()  # compile (or reuse) the output-error fit first, outside the timing
    mp = pytest.MonkeyPatch()
    mp.chdir(folder)
    capture = _Capture()
    with capture:
        rc = main(["fit", "--model", "rtd2h.toml", "--data", "a.csv", "--data", "b.csv",
                   "--out", "out"])
    mp.undo()
    return {"rc": rc, "out": capture.out, "err": capture.err, "folder": folder,
            "dir": folder / "out"}


class _Capture:
    """stdout/stderr capture usable in a module-scoped fixture (capsys is function-scoped)."""

    def __enter__(self):
        import contextlib
        import io

        self._o, self._e = io.StringIO(), io.StringIO()
        self._stack = contextlib.ExitStack()
        self._stack.enter_context(contextlib.redirect_stdout(self._o))
        self._stack.enter_context(contextlib.redirect_stderr(self._e))
        return self

    def __exit__(self, *exc):
        self._stack.close()
        self.out, self.err = self._o.getvalue(), self._e.getvalue()
        return False


def test_fit_exits_0_and_writes_files(oe_cli):
    assert oe_cli["rc"] == 0, oe_cli["err"]
    d = oe_cli["dir"]
    for name in ("model.toml", "report.json", "fit_run0.png", "fit_run1.png"):
        assert (d / name).is_file() and (d / name).stat().st_size > 0, name
    for png in ("fit_run0.png", "fit_run1.png"):
        assert (d / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "Traceback" not in oe_cli["err"] and "warning" not in oe_cli["err"]


def test_report_keys_and_no_nan(oe_cli):
    report = strict_json((oe_cli["dir"] / "report.json").read_text())
    for key in ("schema", "thermojax_version", "rmse", "fit_percent", "nll", "aic", "bic",
                "n_params", "parameters"):
        assert key in report, key
    assert report["schema"] == 1 and report["thermojax_version"] == tj.__version__
    assert set(report["rmse"]) == set(report["fit_percent"]) == {"T_core", "T_sheath"}
    assert set(report["parameters"]) == DOTTED
    for name, p in report["parameters"].items():
        assert {"value", "std"} <= set(p), name
        assert isinstance(p["value"], float) and math.isfinite(p["value"])
        assert p["std"] is None or (isinstance(p["std"], float) and p["std"] > 0)
    for fixed in ("heat_inputs.sheath-P_heater.gain", "sensors.T_sheath.noise"):
        assert report["parameters"][fixed]["std"] is None
    # Spec §2 definitions, with n_params = 4 physical + 2 initial + 1 noise, N counted here.
    N = sum(int(np.isfinite(Y).sum()) for _, _, Y, *_ in rtd2h_data(1))
    assert report["n_params"] == 7
    assert report["aic"] == pytest.approx(2 * 7 + 2 * report["nll"], rel=1e-12)
    assert report["bic"] == pytest.approx(7 * math.log(N) + 2 * report["nll"], rel=1e-12)


def test_report_recovers_the_truth(oe_cli):
    params = strict_json((oe_cli["dir"] / "report.json").read_text())["parameters"]
    for name, true in RTD2H_TRUTH.items():
        p = params[name]
        assert abs(p["value"] - true) <= 2 * p["std"], (name, p, true)
    truth = rtd2h_data(1)
    for r in range(2):
        p = params[f"runs.{r}.nodes.core.initial"]
        assert abs(p["value"] - truth[r][3][1]) <= 2 * p["std"]


def test_table_shows_rmse_and_fit_percent(oe_cli):
    """The printed table has one row per sensor with the report's RMSE and fit %."""
    report = strict_json((oe_cli["dir"] / "report.json").read_text())
    out = oe_cli["out"]
    assert "RMSE" in out and "fit %" in out
    for col in ("T_core", "T_sheath"):
        row = next(line for line in out.splitlines() if line.startswith(col))
        rmse, fit_pct = (float(x) for x in row.split()[1:3])
        assert rmse == pytest.approx(report["rmse"][col], rel=1e-3)  # printed to 4 digits
        assert fit_pct == pytest.approx(report["fit_percent"][col], abs=0.006)  # 2 decimals
    # And those numbers are the NumPy formulas on the data and the sensor noise: the
    # residuals of a good fit are the noise (0.01 and 0.02 °C).
    assert report["rmse"]["T_core"] == pytest.approx(0.01, rel=0.1)
    assert report["rmse"]["T_sheath"] == pytest.approx(0.02, rel=0.1)


def test_model_file_reads_back_and_is_the_optimum(oe_cli):
    """model.toml loads, holds the reported values with the original fixed flags, and a
    refit started from it stays at the optimum (its -log L does not decrease)."""
    report = strict_json((oe_cli["dir"] / "report.json").read_text())
    spec = tj.load_model(oe_cli["dir"] / "model.toml")
    params = report["parameters"]
    assert spec.nodes[0].capacitance.value == pytest.approx(
        params["nodes.sheath.capacitance"]["value"], rel=1e-12)
    assert spec.links[0].conductance.value == pytest.approx(
        params["links.sheath-core.conductance"]["value"], rel=1e-12)
    assert spec.sensors[0].noise.value == pytest.approx(params["sensors.T_core.noise"]["value"],
                                                        rel=1e-12)
    assert spec.sensors[1].noise.fixed and spec.heat_inputs[0].gain.fixed
    assert not spec.nodes[0].capacitance.fixed and spec.nodes[1].initial is not None
    folder = oe_cli["folder"]
    experiments = [Experiment.from_telemetry(spec, tj.read_telemetry(folder / n), name=n)
                   for n in RTD2H_NAMES]
    refit = fit(spec, experiments)
    # 1e-3 in -log L: far below any statistical meaning (the solver's own tolerance is 1e-4).
    assert refit.nll >= report["nll"] - 1e-3
    for name in RTD2H_TRUTH:  # and does not move by more than a tenth of a std
        p = params[name]
        assert abs(refit.parameters[name]["value"] - p["value"]) <= 0.1 * p["std"], name


@pytest.mark.slow  # the Kalman compilation (shared with test_fit/test_kalman)
def test_fit_kalman(tmp_path, monkeypatch, capsys):
    write_runs(tmp_path, process_noise=True)
    rtd2h_kalman_fit()  # compile first (shared)
    monkeypatch.chdir(tmp_path)
    rc, out, err = run(capsys, "fit", "--model", "rtd2h.toml", "--data", "a.csv", "--data",
                       "b.csv", "--out", "kf", "--likelihood", "kalman")
    assert rc == 0, err
    report = strict_json((tmp_path / "kf" / "report.json").read_text())
    assert report["likelihood"] == "kalman"
    assert set(report["parameters"]) == DOTTED | {"nodes.sheath.process_noise",
                                                 "nodes.core.process_noise"}
    for name, true in RTD2H_TRUTH.items():
        p = report["parameters"][name]
        assert abs(p["value"] - true) <= 2 * p["std"], (name, p)
    spec = tj.load_model(tmp_path / "kf" / "model.toml")
    assert spec.nodes[0].process_noise.value == pytest.approx(
        report["parameters"]["nodes.sheath.process_noise"]["value"], rel=1e-12)
    for name in ("smoothed_run0.csv", "smoothed_run1.csv", "fit_run0.png"):
        assert (tmp_path / "kf" / name).is_file()
    assert "T_core" in out and "RMSE" in out


def assert_user_error(rc, err, *fragments):
    """Exit 2, one paragraph naming each fragment, no traceback."""
    assert rc == 2, err
    assert "Traceback" not in err and err.startswith("thermojax fit: error: ")
    assert err.strip().count("\n") == 0, err
    for fragment in fragments:
        assert fragment in err, (fragment, err)


def test_missing_sensor_column(tmp_path, monkeypatch, capsys):
    write_runs(tmp_path, drop_column="T_sheath")
    monkeypatch.chdir(tmp_path)
    rc, _, err = run(capsys, "fit", "--model", "rtd2h.toml", "--data", "a.csv", "--out", "o")
    assert_user_error(rc, err, "a.csv", "T_sheath")
    assert not (tmp_path / "o").exists()


def test_missing_data_file(tmp_path, monkeypatch, capsys):
    write_runs(tmp_path)
    monkeypatch.chdir(tmp_path)
    rc, _, err = run(capsys, "fit", "--model", "rtd2h.toml", "--data", "a.csv", "--data",
                     "nowhere/c.csv", "--out", "o")
    assert_user_error(rc, err, "nowhere/c.csv", "no such file")


def test_missing_model_file(tmp_path, monkeypatch, capsys):
    write_runs(tmp_path)
    monkeypatch.chdir(tmp_path)
    rc, _, err = run(capsys, "fit", "--model", "missing.toml", "--data", "a.csv", "--out", "o")
    assert_user_error(rc, err, "missing.toml")


def test_fit_help(capsys):
    rc, out, _ = run(capsys, "fit", "--help")
    assert rc == 0
    for option in ("--model", "--data", "--out", "--likelihood"):
        assert option in out


# ---------------------------------------------------------------------------------------------
# thermojax run CONFIG


@pytest.mark.slow  # compiles a fit of the one-run rtd2 problem (~30-60 s)
def test_run_config_makes_a_new_folder_each_time(tmp_path, capsys):
    """Two runs of one small synthetic config (rtd2 through the built-in `shock` profile at
    10 s, 421 samples): two result folders, nothing overwritten, each with the resolved
    config, the package versions, the report and the model."""
    (tmp_path / "cfg").mkdir()
    (tmp_path / "cfg" / "small.toml").write_text(f"""
name = "rtd2_small"
model = "{CONFIGS / 'rtd2.toml'}"
out = "../results"

[synthetic]
truth = "{CONFIGS / 'rtd2.toml'}"
profiles = ["shock"]
dt = 10.0
seed = 3

[options]
perturb = 0.2
""")
    folders = []
    for _ in range(2):
        rc, out, err = run(capsys, "run", tmp_path / "cfg" / "small.toml")
        assert rc == 0, err
        folders.append(re.search(r"results in (.+)$", out.strip().splitlines()[-1]).group(1))
    assert folders[0] != folders[1]
    made = sorted(p.name for p in (tmp_path / "results").iterdir())
    assert len(made) == 2 and all(m.startswith("rtd2_small-") for m in made)
    first_report = (tmp_path / "results" / made[0] / "report.json").read_text()
    for name in made:
        d = tmp_path / "results" / name
        for f in ("config.json", "versions.json", "report.json", "model.toml"):
            assert (d / f).is_file(), (name, f)
        cfg = strict_json((d / "config.json").read_text())
        assert cfg["name"] == "rtd2_small" and cfg["model"] == str(CONFIGS / "rtd2.toml")
        assert strict_json((d / "versions.json").read_text())["thermojax"]
        report = strict_json((d / "report.json").read_text())
        assert report["schema"] == 1
        tj.load_model(d / "model.toml")
        # Same seed, same synthetic data, same fit: the noise std is the 0.01 °C that
        # `[synthetic]` (thermojax's own simulation) put in: a consistency check.
        assert report["parameters"]["sensors.T_core.noise"]["value"] == pytest.approx(0.01,
                                                                                      rel=0.15)
    # The first folder was not touched by the second run.
    assert (tmp_path / "results" / made[0] / "report.json").read_text() == first_report


def _png_width(path) -> int:
    import struct

    data = path.read_bytes()[:24]
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">I", data[16:20])[0]


def test_parameter_table_on_screen_matches_report(oe_cli):
    """Every parameter is printed with the value and std of report.json, its 95 % interval
    (Wald on the log scale for a positive parameter, by hand here) and its unit."""
    report = strict_json((oe_cli["dir"] / "report.json").read_text())
    lines = oe_cli["out"].splitlines()
    assert any(line.split()[:4] == ["parameter", "value", "std", "95"] for line in lines)
    for name, p in report["parameters"].items():
        row = next(line for line in lines if line.startswith(name + " "))
        cells = row.split()
        assert float(cells[1]) == pytest.approx(p["value"], rel=1e-3), name
        if p["std"] is None:
            assert cells[2] == "–"
            continue
        assert float(cells[2]) == pytest.approx(p["std"], rel=0.05), name
        lo, hi = (float(x) for x in re.findall(r"\[([^,]+), ([^\]]+)\]", row)[0])
        v, sd = p["value"], p["std"]
        if name.endswith(".initial"):
            assert "(W)" in row and row.rstrip().endswith("°C")
            want = (v - 1.96 * sd, v + 1.96 * sd)
        else:
            assert "(Wl)" in row
            want = (v * math.exp(-1.96 * sd / v), v * math.exp(1.96 * sd / v))
        assert (lo, hi) == pytest.approx(want, rel=1e-3), name
    gain = next(line for line in lines if line.startswith("heat_inputs.sheath-P_heater.gain"))
    assert gain.rstrip().endswith("fixed")
    units = {"nodes.sheath.capacitance": "J/K", "links.sheath-core.conductance": "W/K",
             "sensors.T_core.noise": "°C"}
    for name, unit in units.items():
        assert f" {unit} " in next(line for line in lines if line.startswith(name)) + " "


def test_fit_writes_report_md_naming_its_plots(oe_cli):
    d = oe_cli["dir"]
    md = (d / "report.md").read_text(encoding="utf-8")
    assert md.startswith("# Fit report")
    refs = re.findall(r"\]\(([^)\s]+\.png)\)", md)
    assert refs == ["fit_run0.png", "fit_run1.png"]
    for ref in refs:
        assert _png_width(d / ref) >= 1000
    assert "| nodes.sheath.capacitance |" in md and "Wald" in md
    # T_sheath's noise is fixed in the model file, T_core's estimated: said so
    assert re.search(r"\| T_sheath \|.*\| given \(fixed\) \|", md)
    assert re.search(r"\| T_core \|.*\| estimated \|", md)


def test_a_law_infinite_where_the_data_go_is_named_not_a_traceback(tmp_path, monkeypatch,
                                                                     capsys):
    """A heat law `c / P` is infinite where the recorded power is 0: the fit stops with
    one line naming the cause, not numpy's 'SVD did not converge'."""
    write_runs(tmp_path)
    (tmp_path / "rtd2h.toml").write_text(RTD2H_TEXT + """
[[effects]]
kind = "expression"
where = ["core"]
expression = "c / P_heater"
parameters = { c = 0.01 }
""")
    monkeypatch.chdir(tmp_path)
    rc, _, err = run(capsys, "fit", "--model", "rtd2h.toml", "--data", "a.csv", "--out", "o")
    assert_user_error(rc, err, "not finite", "1/x of a value reaching 0")
