"""Initial states follow the data by default (docs/formats.md §2).

Every log here starts far from the equilibrium of its first input sample, as a user's
first log does, and comes from the independent simulator of `own_data.py`. The model
files are the ones a user writes from the docs: no `initial`. The truth the default fit
is held to is the fit of the same model with the true start written in the file (the
"initialized" fit, what someone who knows the tool would write), and the generated
parameters.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys

import numpy as np
import pytest

import thermojax as tj
from thermojax.fitting._initial_states import conditional_equilibrium
from thermojax.measurements._data import Experiment

from own_data import CASES, model_text, write_csv


def _experiment(spec, ts, inputs, outputs):
    return Experiment(ts, np.column_stack([inputs[c] for c in spec.input_columns]),
                      np.column_stack([outputs[c] for c in spec.sensor_columns]))


def _fit(text, case, likelihood="output_error"):
    net, ts, inputs, outputs, X = case
    spec = tj.parse_model(text, source="user.toml")
    return tj.fit(spec, [_experiment(spec, ts, inputs, outputs)], likelihood=likelihood)


@pytest.mark.parametrize("name,likelihood", [("building", "output_error"),
                                             ("building", "kalman"),
                                             ("heater", "output_error"),
                                             ("sensor_module", "output_error")])
def test_default_fit_reaches_the_initialized_fit(name, likelihood):
    """Without `initial`, the fit reaches the likelihood of the fit that is told the true
    start (within 2), and each node's estimated start is the generated one. The
    equilibrium start (`initial = "steady"`: the behaviour before estimation) is far
    worse on the same data: the check can fail."""
    case = CASES[name]()
    net, _, _, _, X = case
    default = _fit(model_text(net, name), case, likelihood)
    told = _fit(model_text(net, name, {n: f"{x:.4f}" for n, x in zip(net.nodes, X[0])}),
                case, likelihood)
    import contextlib
    said = (pytest.warns(UserWarning, match="first readings of")  # and says so
            if likelihood == "output_error" else contextlib.nullcontext())
    with said:
        steady = _fit(model_text(net, name, {n: '"steady"' for n in net.nodes}), case,
                      likelihood)
    assert default.nll <= told.nll + 2.0, (default.nll, told.nll)
    assert steady.nll > told.nll + 50.0, (steady.nll, told.nll)
    for node, x0 in zip(net.nodes, X[0]):
        p = default.parameters[f"runs.0.nodes.{node}.initial"]
        assert p["free"]
        measured = any(s[1] == node for s in net.sensors)
        tol = 0.1 if measured else 1.5  # °C: an unmeasured start is weakly determined
        assert abs(p["value"] - x0) < tol, (node, p, x0)


def test_default_fit_recovers_the_building():
    """The building's capacitances and conductances from a log that starts 20 K off the
    first sample's equilibrium: each within 3 reported stds of the generated value."""
    case = CASES["building"]()
    net = case[0]
    result = _fit(model_text(net, "building"), case)
    truth = {"nodes.room.capacitance": 2.0e6, "nodes.envelope.capacitance": 2.0e7,
             "links.room-envelope.conductance": 300.0,
             "boundaries.envelope-T_out.conductance": 150.0,
             "heat_inputs.room-solar.gain": 3.0}
    for name, value in truth.items():
        p = result.parameters[name]
        assert p["std"] is not None and abs(p["value"] - value) < 3 * p["std"], (name, p)


def test_unmeasured_start_is_the_equilibrium_given_the_measured():
    """`conditional_equilibrium` against a direct solve: the free rows of `A x + B u` are
    zero and the pinned nodes hold their values."""
    rng = np.random.default_rng(3)
    n = 5
    G = rng.uniform(0.1, 1.0, (n, n))
    K = -(G + G.T) * (rng.random((n, n)) < 0.6)
    np.fill_diagonal(K, 0.0)
    K = K - np.diag(K.sum(axis=1) - rng.uniform(0.1, 0.5, n))
    c = rng.uniform(1.0, 10.0, n)
    A = -K / c[:, None]
    B = rng.uniform(0.0, 1.0, (n, 2)) / c[:, None]
    u0 = np.array([20.0, 3.0])
    x = conditional_equilibrium(A, B, u0, np.array([1, 3]), np.array([30.0, 12.0]))
    assert x[1] == 30.0 and x[3] == 12.0
    r = A @ x + B @ u0
    assert np.allclose(r[[0, 2, 4]], 0.0, atol=1e-12)
    assert not np.allclose(r[[1, 3]], 0.0)  # the pinned rows are not at rest


def _cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "thermojax", *args], capture_output=True,
                          text=True, cwd=cwd)


def test_fit_command_estimates_starts_and_keeps_them_out_of_the_model(tmp_path):
    """`thermojax fit` on a plain CSV and a model without `initial`: the report holds each
    run's start with a std, the fitted model file still has no `initial` (the next fit
    estimates it again), and a model that fixes a wrong start is warned about."""
    net, ts, inputs, outputs, X = CASES["heater"]()
    data = write_csv(tmp_path / "log.csv", ts, {**inputs, **outputs})
    model = tmp_path / "heater.toml"
    model.write_text(model_text(net, "heater"))
    run = _cli("fit", "--model", str(model), "--data", str(data), "--out", str(tmp_path / "f"))
    assert run.returncode == 0, run.stderr
    report = json.loads((tmp_path / "f" / "report.json").read_text())
    p = report["parameters"]["runs.0.nodes.block.initial"]
    assert abs(p["value"] - X[0, 0]) < 0.1 and p["std"] > 0
    assert "initial" not in (tmp_path / "f" / "model.toml").read_text()
    assert "from the fitted model's start" not in run.stdout + run.stderr

    wrong = tmp_path / "wrong.toml"
    wrong.write_text(model_text(net, "heater", {"block": "{ value = 25.0, fixed = true }",
                                                "plate": '"steady"'}))
    run = _cli("fit", "--model", str(wrong), "--data", str(data), "--out", str(tmp_path / "w"))
    assert run.returncode == 0, run.stderr
    assert re.search(r"first readings of T_block are \+2\d", run.stdout + run.stderr)
    assert 'initial = "steady"' in (tmp_path / "w" / "model.toml").read_text()


def test_steady_and_bad_initial_in_the_model_file():
    """`initial = "steady"` reads and writes back; any other text is refused naming it."""
    bound = '[[boundaries]]\nnode = "x"\ninput = "T"\nconductance = 1.0\n'
    spec = tj.parse_model('name = "a"\n[[nodes]]\nname = "x"\ncapacitance = 1.0\n'
                          'initial = "steady"\n' + bound, source="a.toml")
    assert spec.nodes[0].steady and spec.nodes[0].initial is None
    assert 'initial = "steady"' in tj.dump_model(spec)
    with pytest.raises(tj.InputError, match="initial"):
        tj.parse_model('name = "a"\n[[nodes]]\nname = "x"\ncapacitance = 1.0\n'
                       'initial = "warm"\n' + bound, source="a.toml")
