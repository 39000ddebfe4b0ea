"""Whole-file mistakes refused before any work: the same run given twice, a file whose
every temperature is in kelvin. Each exits 2 naming the file and what to do, with no
traceback."""

from __future__ import annotations

import shutil
import subprocess
import sys

from own_data import heater, model_text, write_csv


def _fit(tmp_path, *data):
    net = heater()[0]
    model = tmp_path / "heater.toml"
    model.write_text(model_text(net, "heater"))
    args = [a for d in data for a in ("--data", str(d))]
    return subprocess.run([sys.executable, "-m", "thermojax", "fit", "--model", str(model),
                           *args, "--out", str(tmp_path / "out")], capture_output=True,
                          text=True)


def test_the_same_run_twice_is_refused(tmp_path):
    _, ts, inputs, outputs, _ = heater()
    a = write_csv(tmp_path / "a.csv", ts, {**inputs, **outputs})
    b = tmp_path / "b.csv"
    shutil.copy(a, b)
    for pair, word in (((a, a), "the same file as"), ((a, b), "a copy of")):
        run = _fit(tmp_path, *pair)
        assert run.returncode == 2, run.stderr
        assert word in run.stderr and "Traceback" not in run.stderr, run.stderr
        assert not (tmp_path / "out").exists()


def test_every_temperature_in_kelvin_is_refused(tmp_path):
    _, ts, inputs, outputs, _ = heater()
    cols = {k: (v + 273.15 if k.startswith("T") else v) for k, v in {**inputs,
                                                                    **outputs}.items()}
    run = _fit(tmp_path, write_csv(tmp_path / "k.csv", ts, cols))
    assert run.returncode == 2, run.stderr
    assert "looks like kelvin" in run.stderr and "subtract 273.15" in run.stderr
    assert "Traceback" not in run.stderr
    # the same log in °C is accepted (the check can pass)
    ok = _fit(tmp_path, write_csv(tmp_path / "c.csv", ts, {**inputs, **outputs}))
    assert ok.returncode == 0, ok.stderr
