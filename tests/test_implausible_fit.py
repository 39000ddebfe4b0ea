"""A fit whose own numbers contradict the model file is marked, not just "converged": a
noise far above the written one, a run far shorter than the model's time scale (a clock
in minutes), every capacitance moved the same way by a large factor."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

from helpers import run_cli
from own_data import heater, model_text, write_csv
from thermojax import parse_model
from thermojax.fitting._implausible_fit import capacitances_all_scaled, noise_far_above_written

TWO_NODES = """
name = "two"
[[nodes]]
name = "a"
capacitance = {ca}
[[nodes]]
name = "b"
capacitance = {cb}
[[links]]
between = ["a", "b"]
conductance = 1.0
[[boundaries]]
node = "b"
input = "T_env"
conductance = 1.0
[[sensors]]
node = "a"
column = "T_a"
noise = {noise}
"""


def _spec(ca=10.0, cb=100.0, noise="0.02"):
    return parse_model(TWO_NODES.format(ca=ca, cb=cb, noise=noise))


def test_capacitances_scaled_together_are_named_apart_from_one_moved():
    written = _spec()
    said = capacitances_all_scaled(written, _spec(10.0 / 60, 100.0 / 55))
    assert len(said) == 1 and "below" in said[0] and "minutes" in said[0], said
    assert "median 58×" in said[0], said  # the median of 60 and 55
    assert "milliseconds" in capacitances_all_scaled(written, _spec(10.0 * 1000, 100 * 900))[0]
    assert capacitances_all_scaled(written, _spec(10.0 / 60, 100.0)) == []  # one moved: a guess
    assert capacitances_all_scaled(written, _spec(10.0 / 60, 100.0 * 60)) == []  # both ways
    assert capacitances_all_scaled(written, _spec(10.0 / 9, 100.0 / 9)) == []  # under 10×


def test_noise_far_above_the_written_one_is_named_unless_fixed():
    written = _spec()
    said = noise_far_above_written(written, _spec(noise="0.5"))
    assert len(said) == 1 and "T_a" in said[0] and "25×" in said[0], said
    assert noise_far_above_written(written, _spec(noise="0.15")) == []  # 7.5×: noise
    fixed = _spec(noise="{ value = 0.02, fixed = true }")
    assert noise_far_above_written(fixed, _spec(noise="0.5")) == []


@pytest.mark.slow
@pytest.mark.parametrize("unit", ["s", "min"])
def test_a_log_in_minutes_is_marked_and_one_in_seconds_is_not(tmp_path, capsys, unit):
    """The heater block of `own_data` (time constants 20 s and 164 s, 2 s samples for
    20 min, sensor noise 0.02 °C written in the model): logged with `time_s` in seconds
    it fits to its noise with no warning; with `time_s` in minutes the run seems to last
    20 s: the fit reaches the data with every capacitance 60× too small, and both the
    run's length and the capacitances name the clock, in the report too."""
    net, ts, inputs, outputs, _ = heater()
    data = write_csv(tmp_path / "log.csv", ts / (60.0 if unit == "min" else 1.0),
                     {**inputs, **outputs})
    model = tmp_path / "heater.toml"
    model.write_text(model_text(net, "heater").replace('column = "T_block"',
                                                       'column = "T_block"\nnoise = 0.02'))
    out = tmp_path / "fit"
    rc, _, err = run_cli(capsys, "fit", "--model", model, "--data", data, "--out", out)
    assert rc == 0, err
    report = json.loads((out / "report.json").read_text())
    md = (out / "report.md").read_text(encoding="utf-8")
    if unit == "s":
        assert report["rmse"]["T_block"] < 0.03, report["rmse"]
        assert report["warnings"] == [] and "Warning" not in md and "warning" not in err, err
    else:
        assert "If `time_s` counts minutes" in err, err
        said = "every capacitance ended 10× or more below its value in the model file"
        assert said in err and "(minutes make them 60× too small)" in err, err
        assert any(said in w for w in report["warnings"])
        assert f"**Warning:** {said}" in md


def _rtd_run(core):
    from thermojax.measurements import Telemetry

    ts = np.arange(len(core), dtype=float)
    fluid = np.linspace(25.0, 85.0, len(core))
    return Telemetry(ts, {"T_fluid": fluid, "T_core": core}, path="log.csv")


def test_a_sensor_in_fahrenheit_beside_boundaries_in_celsius_is_warned_of():
    from helpers import CONFIGS
    from thermojax import load_model
    from thermojax.measurements import check_plausibility

    spec = load_model(CONFIGS / "rtd2.toml")
    celsius = np.linspace(25.0, 85.0, 200) - 0.5  # lags the fluid a little
    with pytest.warns(UserWarning, match=r"column 'T_core' .* in °F, convert it"):
        check_plausibility(spec, _rtd_run(celsius * 1.8 + 32.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # in °C: no word, heated well above the fluid too
        check_plausibility(spec, _rtd_run(celsius))
        check_plausibility(spec, _rtd_run(celsius + 25.0))
