"""Bias columns inside the fit's likelihood (docs/formats.md §4, issue 10 item 1).

A two-node package: a measured case and an unmeasured MEMS node whose accelerometer
bias carries a polynomial, an exact-rate term and a viscoelastic strain. The truth is
simulated with SciPy (`scipy.signal.lsim`, inputs linear between samples), independently
of thermojax. The MEMS node (16 s, 1.6 J/K against the case's 20 J/K) barely loads the
case sensor; the bias column, indexed to it, is what pins its time constant.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys

import jax
import numpy as np
import pytest
import scipy.signal

from thermojax.fitting._bias_residuals import node_temperatures
from thermojax.fitting._fit import fit
from thermojax.fitting._output_error import _oe_blocks, _oe_blocks_jacobian
from thermojax.fitting._problem import make_problem, prepare
from thermojax.measurements._data import Experiment
from thermojax.model._model_file import parse_model
from thermojax.model._parameters import free_parameters

CC, CM, G, GB = 20.0, 1.6, 0.1, 0.2  # J/K, J/K, W/K, W/K
POLY, GRAD, RATE = (10.0, 2.0, 0.01), 3.0, 30.0  # µg, µg/K, µg/K²; µg/K; µg s/K
PRONY = ((300.0, 0.4), (3000.0, 0.3))  # (τ s, k µg/K) of the two strain terms
SIGMA_T, SIGMA_B = 0.01, 0.5  # °C, µg
A = np.array([[-(G + GB) / CC, G / CC], [G / CM, -G / CM]])
B = np.array([[GB / CC, 0.0], [0.0, 1.0 / CM]])  # chamber °C, MEMS power W

MODEL = """
name = "package"
[[nodes]]
name = "case"
capacitance = {{ value = 20.0, fixed = true }}
initial = "steady"  # the runs start at the first input's equilibrium
[[nodes]]
name = "mems"
capacitance = {cm}
initial = "steady"
[[links]]
between = ["case", "mems"]
conductance = {g}
[[boundaries]]
node = "case"
input = "T_chamber"
conductance = {gb}
[[heat_inputs]]
node = "mems"
input = "P_mems"
gain = {{ value = 1.0, fixed = true }}
[[sensors]]
node = "case"
column = "T_case"
[[biases]]
column = "accel_x_ug"
temperature = "mems"
order = 2
gradients = [["case", "mems"]]
rates = ["mems"]
[[effects]]
kind = "viscoelastic"
where = ["mems", "accel_x_ug"]
time_constant = {tau1}
k = 0.1
[[effects]]
kind = "viscoelastic"
where = ["mems", "accel_x_ug"]
time_constant = {tau2}
k = 0.1
"""


def truth_run(knots_t, knots_T, seed):
    """`(ts, inputs (T, 2), node temperatures (T, 2), their exact rates, case reading,
    bias)`; the MEMS power switches between 0 and 0.05 W every 900 s (ramped over 10 s)."""
    ts = np.arange(knots_t[-1] + 1.0)
    power = 0.05 * np.interp(ts % 1800, [0, 890, 900, 1790, 1800], [0, 0, 1, 1, 0])
    u = np.column_stack([np.interp(ts, knots_t, knots_T), power])
    x0 = np.linalg.solve(A, -B @ u[0])
    plant = scipy.signal.StateSpace(A, B, np.eye(2), np.zeros((2, 2)))
    _, _, x = scipy.signal.lsim(plant, u, ts, X0=x0, interp=True)
    xdot = x @ A.T + u @ B.T
    mems = x[:, 1]
    bias = sum(c * (mems - 25) ** p for p, c in enumerate(POLY)) + RATE * xdot[:, 1] \
        + GRAD * (x[:, 0] - mems)
    for tau, k in PRONY:
        lag = scipy.signal.StateSpace([[-1 / tau]], [[1 / tau]], [[1.0]], [[0.0]])
        _, eps, _ = scipy.signal.lsim(lag, mems, ts, X0=[mems[0]], interp=True)
        bias = bias + k * (mems - eps)
    rng = np.random.default_rng(seed)
    y = x[:, 0] + SIGMA_T * rng.standard_normal(ts.size)
    b = bias + SIGMA_B * rng.standard_normal(ts.size)
    b[rng.random(ts.size) < 0.03] = np.nan  # dropped bias samples
    return ts, u, x, xdot, y, b


PROFILES = [([0, 600, 1320, 4320, 5040, 7200], [25, 25, 85, 85, 25, 25], 0),
            ([0, 600, 840, 3240, 4440, 5400], [25, 25, 45, 45, -15, -15], 1)]


@pytest.fixture(scope="module")
def runs():
    return [truth_run(*p) for p in PROFILES]


def experiments(runs):
    return [Experiment(ts, u, y[:, None], f"run{i}", b[:, None])
            for i, (ts, u, _, _, y, b) in enumerate(runs)]


START = MODEL.format(cm=0.5, g=0.08, gb=0.12, tau1=100.0, tau2=5000.0)


def test_joint_fit_recovers_the_unmeasured_node_and_the_bias(runs):
    result = fit(parse_model(START, "start.toml"), experiments(runs))
    assert result.converged
    p = result.parameters
    strain = "effects.viscoelastic.mems-accel_x_ug"
    truth = {"nodes.mems.capacitance": CM, "links.case-mems.conductance": G,
             "boundaries.case-T_chamber.conductance": GB,
             f"{strain}.time_constant": PRONY[0][0], f"{strain}.k": PRONY[0][1],
             f"{strain}#2.time_constant": PRONY[1][0], f"{strain}#2.k": PRONY[1][1],
             "biases.accel_x_ug.poly0": POLY[0], "biases.accel_x_ug.poly1": POLY[1],
             "biases.accel_x_ug.poly2": POLY[2], "biases.accel_x_ug.rate.mems": RATE,
             "biases.accel_x_ug.gradient.case-mems": GRAD,
             "biases.accel_x_ug.noise": SIGMA_B, "sensors.T_case.noise": SIGMA_T}
    for name, value in truth.items():
        assert p[name]["std"] is not None, name
        assert abs(p[name]["value"] - value) < 3.5 * p[name]["std"], (name, p[name], value)
    # the MEMS node's own time constant C/G (16 s)
    tau_m = p["nodes.mems.capacitance"]["value"] / p["links.case-mems.conductance"]["value"]
    assert tau_m == pytest.approx(CM / G, rel=0.05)
    # the bias column is part of the likelihood: nll and counts include it, independently
    b = result.biases["accel_x_ug"]
    r_t = np.concatenate([y - pred[:, 0] for (_, _, _, _, y, _), pred in
                          zip(runs, result.predictions)])
    r_b = np.concatenate(b.residuals)
    r_b = r_b[np.isfinite(r_b)]
    s_t, s_b = p["sensors.T_case.noise"]["value"], p["biases.accel_x_ug.noise"]["value"]
    nll = sum(0.5 * r.size * math.log(2 * math.pi * s * s) + 0.5 * np.sum(r * r) / (s * s)
              for r, s in ((r_t, s_t), (r_b, s_b)))
    assert result.nll == pytest.approx(nll, rel=1e-9)
    assert result.n_samples == r_t.size + r_b.size
    # 3 physical + 2 τ + 2 noise stds + 3 polynomial + gradient + rate + 2 k
    assert result.n_params == 14
    assert set(result.rmse) == {"T_case", "accel_x_ug"}
    # the fitted model file carries the bias coefficients and both strain terms
    spec = result.spec
    assert len(spec.biases[0].coefficients) == 5
    visco = [e for e in spec.effects if e.kind == "viscoelastic"]
    for e, name in zip(visco, (strain, f"{strain}#2")):
        assert e.parameters["time_constant"].value == pytest.approx(
            p[f"{name}.time_constant"]["value"])
        assert e.parameters["k"].value == pytest.approx(p[f"{name}.k"]["value"])


def test_rates_are_the_models_exact_state_derivative(runs):
    """`A x + B u` at the samples, against SciPy's states and the analytic derivative."""
    spec = parse_model(MODEL.format(cm=CM, g=G, gb=GB, tau1=PRONY[0][0], tau2=PRONY[1][0]),
                       "truth.toml")
    prep = prepare(spec, experiments(runs), "output_error")
    x, xdot = (np.asarray(a) for a in node_temperatures(prep.template.model, prep.data,
                                                        prep.template.run_initial))
    for r, (ts, _, x_true, xdot_true, _, _) in enumerate(runs):
        np.testing.assert_allclose(x[r, :ts.size], x_true, atol=1e-6)
        np.testing.assert_allclose(xdot[r, :ts.size], xdot_true, atol=1e-7)


def test_bias_jacobian_is_the_derivative_of_the_projected_residuals(runs):
    """Forward sensitivities + `jax.jvp` through the least squares equal `jax.jacfwd` of
    the whole residual function (variable projection's exact derivative)."""
    short = [tuple(a[:900] for a in run) for run in runs]
    prep = prepare(parse_model(START, "start.toml"), experiments(short), "output_error")
    theta = free_parameters(prep.template, prep.index)
    problem = make_problem(prep.template, prep.index, prep.data, prep.sigma, theta,
                           bias=prep.bias)
    (r, _), (J, _), _ = _oe_blocks_jacobian(theta, problem)
    J_ref = jax.jacfwd(lambda t: _oe_blocks(t, problem)[0])(theta)
    assert len(r) == 2  # the sensor, then the bias column
    for got, ref in zip(J, J_ref):
        np.testing.assert_allclose(np.asarray(got), np.asarray(ref), rtol=1e-7,
                                   atol=1e-9 * float(np.max(np.abs(np.asarray(ref)))))


def test_fit_command_reports_bias_channels(runs, tmp_path):
    """`thermojax fit` on a model with a bias column: the column's coefficients, RMSE and
    noise in report.json, its coefficients in model.toml."""
    ts, u, _, _, y, b = runs[0]
    data = tmp_path / "run.csv"
    with open(data, "w") as f:
        f.write("time_s,T_chamber,P_mems,T_case,accel_x_ug\n")
        for row in zip(ts, u[:, 0], u[:, 1], y, b):
            f.write(",".join("" if not np.isfinite(v) else repr(float(v)) for v in row) + "\n")
    model = tmp_path / "start.toml"
    model.write_text(START)
    out = tmp_path / "fit"
    proc = subprocess.run([sys.executable, "-m", "thermojax", "fit", "--model", str(model),
                           "--data", str(data), "--out", str(out), "--quiet"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "report.json").read_text())
    assert "accel_x_ug" in report["rmse"]
    assert report["rmse"]["accel_x_ug"] == pytest.approx(SIGMA_B, rel=0.1)
    for name in ("poly0", "poly1", "poly2", "gradient.case-mems", "rate.mems", "noise"):
        assert report["parameters"][f"biases.accel_x_ug.{name}"]["std"] is not None
    fitted = parse_model((out / "model.toml").read_text(), "model.toml")
    assert fitted.biases[0].coefficients is not None
    assert "accel_x_ug" in proc.stdout
