"""`simulate` writes a model's bias columns (docs/formats.md §4) from their fitted
coefficients and viscoelastic strains, as the independent simulator of the hidden suite
computes them; an entry with nothing fitted is refused by name."""

from __future__ import annotations

import numpy as np

from helpers import CONFIGS, assert_refused, run_cli
from hidden import generator as g
from thermojax.measurements import read_telemetry

RTD2_TEXT = (CONFIGS / "rtd2.toml").read_text()
BIAS = """
[[biases]]
column = "gyro_x"
temperature = "core"
order = 2
gradients = [["sheath", "core"]]
rates = ["core"]
coefficients = [0.3, -0.02, 0.004, 1.5, 40.0]

[[effects]]
kind = "viscoelastic"
where = ["core", "gyro_x"]
time_constant = 30.0
k = 0.25
"""


def test_bias_columns_are_written_as_the_independent_simulator_computes_them(capsys, tmp_path):
    model = tmp_path / "gyro.toml"
    model.write_text(RTD2_TEXT + BIAS)
    out = tmp_path / "sim.csv"
    rc, _, err = run_cli(capsys, "simulate", "--model", model, "--profile", "ramp10",
                         "--dt", "1", "--out", out)
    assert rc == 0, err
    got = read_telemetry(out)
    truth = g.simulate_truth(g.read_model(model), got.ts, {"T_fluid": got.channels["T_fluid"]},
                             noise=False, holds={"T_fluid": "foh"})
    np.testing.assert_allclose(got.channels["T_core"], truth["T_core"], atol=1e-4)
    assert np.ptp(truth["gyro_x"]) > 1.0  # the column moves with the ramp
    np.testing.assert_allclose(got.channels["gyro_x"], truth["gyro_x"], atol=2e-3)


def test_a_bias_without_coefficients_is_refused_by_name(capsys, tmp_path):
    model = tmp_path / "gyro.toml"
    model.write_text(RTD2_TEXT + BIAS.replace("coefficients = [0.3, -0.02, 0.004, 1.5, 40.0]",
                                              ""))
    rc, _, err = run_cli(capsys, "simulate", "--model", model, "--profile", "ramp10",
                         "--out", tmp_path / "sim.csv")
    assert_refused(rc, err, "gyro_x", "coefficients")
    assert not (tmp_path / "sim.csv").exists()
