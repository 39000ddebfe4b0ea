"""`expression` effects (spec §3a): the grammar, validation, simulation against the
independent generator, fitting with ± on every parameter, the model file round trip and
the exported linearization."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import thermojax as tj
from thermojax import Dataset, Experiment, ThermalModel, parse_model
from thermojax.fitting._likelihood import simulate_dataset
from thermojax.model._expression import ExpressionError, evaluate_numpy, parse, resolve
from thermojax.model._model_file import dump_model
from thermojax.model.effects import lower_effects

from helpers import CONFIGS
from hidden import generator as g

POWER_LAW = ('\n[[effects]]\nkind = "expression"\nwhere = ["housing", "T_chamber"]\n'
             'expression = "h * abs(T_chamber - housing)^n * (T_chamber - housing)"\n'
             'parameters = {{ h = {h}, n = {n} }}\n')
QUADRATIC = ('\n[[effects]]\nkind = "expression"\nwhere = ["pcb"]\n'
             'expression = "c * air_speed^2 * exp(k * (pcb - 25))"\n'
             'parameters = {{ c = {c}, k = {k} }}\n')


@pytest.mark.parametrize("text, x, a, expected", [
    ("-x^2", 3.0, 0.0, -9.0),
    ("2^3^2", 0.0, 0.0, 512.0),
    ("a / 2 / 4", 0.0, 8.0, 1.0),
    ("x - a - 1", 5.0, 1.0, 3.0),
    ("(x + a) * 2", 1.0, 2.0, 6.0),
    ("kelvin(x)^4 - kelvin(a)^4", 30.0, 20.0, 303.15 ** 4 - 293.15 ** 4),
    ("min(x, a) + max(x, a) * step(x - a)", 3.0, 2.0, 5.0),
    ("sqrt(abs(a - x)) * sign(a - x)", 1.0, 10.0, 3.0),
    ("exp(log(x)) + 1e-3 * a", 2.0, 1000.0, 3.0),
    ("abs(x)^0.25 * x", -16.0, 0.0, -32.0),
    ("x^-2", 2.0, 0.0, 0.25),
])
def test_grammar_matches_hand_computed_values(text, x, a, expected):
    tree = resolve(parse(text), ["x"], ["a"], [])
    assert math.isclose(float(evaluate_numpy(tree, [x], [a], [])), expected, rel_tol=1e-12)


@pytest.mark.parametrize("text, what", [
    ("", "empty"), ("x +", "position 4"), ("x ** 2", "use \\^"),
    ("__import__('os')", "unexpected character"), ("foo(x)", "unknown function 'foo'"),
    ("min(x)", "takes 2"), ("(x", "expected '\\)'"), ("exp", "is a function"),
])
def test_grammar_refuses_what_it_cannot_read(text, what):
    with pytest.raises(ExpressionError, match=what):
        parse(text)


def _chain3(extra: str) -> str:
    return (CONFIGS.parent / "tests" / "hidden" / "models" / "chain3.toml").read_text() + extra


@pytest.mark.parametrize("extra, field, what", [
    ('expression = "h * (T_chamber - housing"\nparameters = { h = 0.1 }\n',
     "effects[0].expression", "expected '\\)'"),
    ('expression = "h * (T_die - housing)"\nparameters = { h = 0.1 }\n',
     "effects[0].expression", "sensor column"),
    ('expression = "h * (T_chamber - housing)"\nparameters = { h = 0.1, q = 2 }\n',
     "effects[0].parameters.q", "does not appear"),
    ('expression = "h * (T_chamber - housing)"\nparameters = { h = "big" }\n',
     "effects[0].parameters.h", ""),
    ('parameters = { h = 0.1 }\n', "effects[0].expression", ""),
])
def test_bad_expression_is_refused_with_file_line_and_field(tmp_path, extra, field, what):
    path = tmp_path / "m.toml"
    text = _chain3('\n[[effects]]\nkind = "expression"\nwhere = ["housing", "T_chamber"]\n'
                   + extra)
    path.write_text(text)
    line = text.splitlines().index("[[effects]]") + 1
    with pytest.raises(tj.InputError) as err:
        tj.load_model(path)
    message = str(err.value)
    assert field in message and f"line {line}" in message and "m.toml" in message
    assert what == "" or __import__("re").search(what, message)


def _simulate(spec, ts, inputs):
    model = ThermalModel.from_spec(spec)
    u = np.stack([inputs[c] for c in lower_effects(spec).spec.input_columns], 1)
    data = Dataset.from_experiments([Experiment(ts, u, np.zeros((len(ts), 2)))])
    return np.asarray(simulate_dataset(model, data))[0]


@pytest.mark.parametrize("name, extra", [
    ("law_power_convection", POWER_LAW.format(h=0.04, n=0.25)),
    ("law_quadratic_input", QUADRATIC.format(c=0.03, k=0.015)),
])
def test_expression_simulation_matches_generator(name, extra):
    """The generator integrates its own truth-only laws (Radau, tolerance 1e-10, no
    thermojax import); the expression of the same law, by ETD2 at 1 s, agrees."""
    spec = parse_model(_chain3(extra))
    truth = g.generate_case(name, seed=0, horizon_s=1800.0, noise=False)[0]
    ts, cols = truth
    inputs = g.run_inputs(g.load_case(name), 0, [0], 1800.0)[1]
    y = _simulate(spec, ts, inputs)
    for j, c in enumerate(spec.sensor_columns):
        assert np.max(np.abs(y[:, j] - cols[c])) < 2e-4, c


def test_expression_of_radiation_equals_the_radiation_kind():
    """Two implementations of one law: the `radiation` kind's own code and the grammar."""
    rad = parse_model(_chain3('\n[[effects]]\nkind = "radiation"\nwhere = ["housing", '
                              '"T_chamber"]\ncoefficient = 3e-10\n'))
    expr = parse_model(_chain3(
        '\n[[effects]]\nkind = "expression"\nwhere = ["housing", "T_chamber"]\n'
        'expression = "k * (kelvin(T_chamber)^4 - kelvin(housing)^4)"\n'
        'parameters = { k = 3e-10 }\n'))
    ts = np.arange(0.0, 1200.0, 1.0)
    inputs = {"T_chamber": 25 + 60 * np.clip(ts / 600, 0, 1),
              "P_die": np.where(ts % 180 < 90, 0.4, 0.0)}
    np.testing.assert_allclose(_simulate(expr, ts, inputs), _simulate(rad, ts, inputs),
                               rtol=0, atol=1e-12)


def test_fit_recovers_a_power_law_and_the_file_round_trips(tmp_path):
    """Generated with h = 0.04 W/K^1.25, n = 0.25: the fit's estimates are within three
    of their stds of the truth, and the fitted model file loads and simulates again."""
    runs = g.generate_case("law_power_convection", seed=3, horizon_s=2400.0)
    spec = parse_model(_chain3(POWER_LAW.format(h=0.02, n=0.5)))
    exps = [Experiment(ts, np.stack([c[k] for k in spec.input_columns], 1),
                       np.stack([c[k] for k in spec.sensor_columns], 1)) for ts, c in runs]
    res = tj.fit(spec, exps)
    for name, truth in (("h", 0.04), ("n", 0.25)):
        p = res.parameters[f"effects.expression.housing-T_chamber.{name}"]
        assert p["std"] is not None and p["std"] > 0
        assert abs(p["value"] - truth) < 3 * p["std"], (name, p)
    text = dump_model(res.spec)
    again = parse_model(text)
    e = again.effects[0]
    assert e.kind == "expression" and e.expression == spec.effects[0].expression
    assert set(e.parameters) == {"h", "n"}
    assert abs(e.parameters["h"].value - res.parameters[
        "effects.expression.housing-T_chamber.h"]["value"]) < 1e-12
    fixed = again.replace(effects=(dataclasses.replace(e, parameters={
        **e.parameters, "n": tj.Parameter(0.25, True)}),))
    assert parse_model(dump_model(fixed)).effects[0].parameters["n"].fixed


def test_export_linearizes_an_expression_as_the_kind_it_writes(tmp_path):
    from thermojax.observer import export_observer

    base = (CONFIGS / "imu6.toml").read_text()
    rad = tmp_path / "rad.toml"
    rad.write_text(base + '\n[[effects]]\nkind = "radiation"\nwhere = ["housing", '
                   '"T_chamber"]\ncoefficient = 2e-10\n')
    expr = tmp_path / "expr.toml"
    expr.write_text(base + '\n[[effects]]\nkind = "expression"\nwhere = ["housing", '
                    '"T_chamber"]\nexpression = "k * (kelvin(T_chamber)^4 - kelvin(housing)^4)"'
                    '\nparameters = { k = 2e-10 }\n')
    with pytest.warns(UserWarning, match=r"expression.*linearization at a uniform 25 °C"):
        a = export_observer(expr, 20, tmp_path / "a")
    with pytest.warns(UserWarning):
        b = export_observer(rad, 20, tmp_path / "b")
    np.testing.assert_allclose(a.arrays["Phi"], b.arrays["Phi"], rtol=0, atol=1e-14)


def test_a_run_without_the_column_an_expression_reads_is_named():
    """A model whose law reads `air_speed`, given runs built for the model without it:
    the fit names the columns it reads instead of failing inside the simulation."""
    spec = parse_model(_chain3(QUADRATIC.format(c=0.03, k=0.015)))
    ts = np.arange(0.0, 600.0, 1.0)
    run = Experiment(ts, np.zeros((ts.size, 2)), np.zeros((ts.size, 2)) + 25.0, "bench.csv")
    with pytest.raises(tj.InputError) as err:
        tj.fit(spec, [run])
    message = str(err.value)
    assert "bench.csv" in message and "2 input column(s)" in message, message
    assert "T_chamber, P_die, air_speed" in message, message
