"""A heat input whose file gives no `hold` is fitted as `foh`, the default; where its data
are switched power (piecewise constant) `fit` says so and what to write, and where they
are not, or the file states the hold, it says nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.linalg

from helpers import run_cli
from own_data import heater, model_text, readings, write_csv
from thermojax import parse_model


def _simulate_zoh(net, U, dt, x0):
    """States (T, n) °C from `x0`, inputs `U` (T, m) held constant over each sample period
    (`expm` of `[[A, B], [0, 0]]`; NumPy and SciPy only)."""
    A, B, _ = net.matrices()
    n, m = B.shape
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = A, B
    E = scipy.linalg.expm(M * dt)
    X = np.empty((U.shape[0], n))
    X[0] = x0
    for k in range(U.shape[0] - 1):
        X[k + 1] = E[:n, :n] @ X[k] + E[:n, n:] @ U[k]
    return X


def _log(tmp_path, held):
    """The heater log of `own_data.heater` (a PRBS power, 2 s samples), its power held as
    `held` says; the model file a user writes from the docs (no `hold`)."""
    net, ts, inputs, ys, X = heater()
    if held == "zoh":
        U = np.column_stack([inputs[c] for c in net.inputs])
        X = _simulate_zoh(net, U, ts[1] - ts[0], X[0])
        ys = readings(net, X, np.random.default_rng(7))
    csv = write_csv(tmp_path / f"{held}.csv", ts, {**inputs, **ys})
    model = tmp_path / "heater.toml"
    model.write_text(model_text(net, "heater"))
    return csv, model


def _fit(capsys, model, csv, out):
    rc, stdout, err = run_cli(capsys, "fit", "--model", model, "--data", csv, "--out", out)
    assert rc == 0, err
    return json.loads((out / "report.json").read_text()), stdout + err


def test_switched_power_fitted_as_foh_is_named_with_what_to_write(tmp_path, capsys):
    csv, model = _log(tmp_path, "zoh")
    assert parse_model(model.read_text()).heat_inputs[0].hold_written is False
    report, err = _fit(capsys, model, csv, tmp_path / "foh")
    said = [w for w in report["warnings"] if w.startswith("P_heater is held \"foh\"")]
    assert len(said) == 1, report["warnings"]
    assert 'write hold = "zoh" on its [[heat_inputs]] entry' in said[0]
    assert f"warning: {said[0]}" in err
    # the gain it states is the gain of the fit with the hold written
    written = tmp_path / "zoh.toml"
    written.write_text(model.read_text().replace('input = "P_heater"',
                                                 'input = "P_heater"\nhold = "zoh"'))
    zoh, err_zoh = _fit(capsys, written, csv, tmp_path / "zoh")
    stated = float(said[0].split("better by ")[1].split(" in log L")[0])
    assert abs(stated - (report["nll"] - zoh["nll"])) < 0.1, (stated, report["nll"], zoh["nll"])
    # and the data were switched: held "zoh" the fit is at the sensors' noise (0.02 °C)
    assert all(abs(v - 0.02) < 0.003 for v in zoh["rmse"].values()), zoh["rmse"]
    assert report["rmse"]["T_block"] > 0.1, report["rmse"]  # the heated block, as foh
    assert "checking the hold" not in err_zoh  # written: nothing to check


def test_power_that_moves_linearly_or_a_written_hold_gets_no_remark(tmp_path, capsys):
    csv, model = _log(tmp_path, "foh")
    report, err = _fit(capsys, model, csv, tmp_path / "foh")
    assert "checking the hold of P_heater" in err  # it was checked ...
    assert not [w for w in report["warnings"] if "hold" in w], report["warnings"]  # ... fine
    csv_zoh, _ = _log(tmp_path, "zoh")
    stated = tmp_path / "stated.toml"
    stated.write_text(model.read_text().replace('input = "P_heater"',
                                                'input = "P_heater"\nhold = "foh"'))
    report, err = _fit(capsys, stated, csv_zoh, tmp_path / "stated")
    assert "checking the hold" not in err
    assert not [w for w in report["warnings"] if "hold" in w], report["warnings"]


@pytest.mark.filterwarnings("always:P_heater is held")  # the warning under test, shown
def test_investigate_goes_on_from_the_hold_the_data_fit_and_says_so(tmp_path, capsys):
    """The same switched-power log under `investigate`: step 0 is the given model held
    "zoh", which is the generated structure, so nothing is added; the report and the final
    model say which hold was taken and why."""
    csv, model = _log(tmp_path, "zoh")
    out = tmp_path / "inv"
    rc, stdout, err = run_cli(capsys, "investigate", "--model", model, "--data", csv,
                              "--out", out, "--max-steps", "2")
    assert rc == 0, err
    report = json.loads((out / "report.json").read_text())
    step0 = report["steps"][0]
    [change] = step0["hold_changes"]
    assert (change["column"], change["hold"]) == ("P_heater", "zoh")
    # step 0 is the fit of the model with the hold written, and the gain is its gain
    written = tmp_path / "zoh.toml"
    written.write_text(model.read_text().replace('input = "P_heater"',
                                                 'input = "P_heater"\nhold = "zoh"'))
    zoh, _ = _fit(capsys, written, csv, tmp_path / "zoh")
    foh, _ = _fit(capsys, model, csv, tmp_path / "foh")
    assert abs(step0["nll"] - zoh["nll"]) < 0.1, (step0["nll"], zoh["nll"])
    assert abs(change["gain_log_l"] - (foh["nll"] - zoh["nll"])) < 0.1
    assert [s["added"] for s in report["steps"][1:]] == []  # the truth's structure
    assert 'warning: P_heater is held "foh"' in err
    assert 'The investigation goes on from hold = "zoh" on P_heater' in err
    final = parse_model((out / "model_final.toml").read_text())
    assert [(h.input, h.hold, h.hold_written) for h in final.heat_inputs] == \
        [("P_heater", "zoh", True)]
    assert "The model file gives no hold for `P_heater`" in (out / "report.md").read_text()
