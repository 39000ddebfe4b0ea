"""A fit that stops where a sensor is predicted worse than by its own mean is no fit.

The heater of `own_data.py` (independent simulator) with the plate's boundary
conductance written 100× too high: from the file's values the truncated solve stops at
a local optimum (the plate's fit % near −300) that it used to call converged. The first
line of defence is the first-order check (`fitting._stationarity`): the likelihood still
falls along the conductance the solver left out, so the fit walks along it and solves
again. The second, for whatever the first misses, is `thermojax fit` itself: a sensor
fitted worse than its own mean makes it try more starts and keep the better."""

from __future__ import annotations

import json
import subprocess
import sys

from helpers import run_cli
from own_data import heater, model_text, write_csv
from thermojax.fitting import _stationarity


def _bad_start(tmp_path):
    net, ts, inputs, outputs, _ = heater()
    data = write_csv(tmp_path / "log.csv", ts, {**inputs, **outputs})
    node, col, g = net.boundaries[0]
    net.boundaries[0] = (node, col, 100 * g)
    model = tmp_path / "bad.toml"
    model.write_text(model_text(net, "heater"))
    return model, data, g


def _check_truth(report, g):
    assert min(report["fit_percent"].values()) > 95.0, report["fit_percent"]
    # the truth: 1.5 W/K (the generator's), within 3 reported stds
    p = report["parameters"]["boundaries.plate-T_chamber.conductance"]
    assert abs(p["value"] - g) < 3 * p["std"], p


def test_a_start_100x_off_is_walked_out_of_by_the_first_order_check(tmp_path):
    model, data, g = _bad_start(tmp_path)
    run = subprocess.run([sys.executable, "-m", "thermojax", "fit", "--model", str(model),
                          "--data", str(data), "--out", str(tmp_path / "out")],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    said = run.stderr + run.stdout
    assert ("the likelihood still falls along boundaries.plate-T_chamber.conductance"
            in said), said
    assert "predicted worse than by its own mean" not in said  # no more starts needed
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["converged"] is True
    _check_truth(report, g)


def test_a_fit_worse_than_the_mean_tries_more_starts(tmp_path, capsys, monkeypatch):
    model, data, g = _bad_start(tmp_path)
    monkeypatch.setattr(_stationarity, "MAX_ESCAPE_STEPS", 0)  # the first defence off
    rc, out, err = run_cli(capsys, "fit", "--model", model, "--data", data,
                           "--out", tmp_path / "out")
    assert rc == 0, err
    assert "predicted worse than by its own mean: trying" in out + err
    _check_truth(json.loads((tmp_path / "out" / "report.json").read_text()), g)
