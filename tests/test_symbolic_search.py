"""The symbolic search over heat laws (`thermojax.discovery.symbolic_search`): on heats
generated from known laws outside today's function library, the front holds the true
structure with its constants within three reported stds of the truth."""

from __future__ import annotations

import numpy as np
import pytest

from thermojax.discovery import (LIBRARY, heat_variables, law_values, learned_law,
                                 symbolic_search)
from thermojax.discovery._symbolic_grammar import PRIMITIVE_INDEX, canonical
from thermojax.model._expression import evaluate_numpy, parse, resolve

NOISE = 0.01  # W, the std of the generated heat
BUDGET = dict(evaluations=600, generations=2, population=256, random_state=0)


@pytest.fixture(scope="module")
def data():
    """Two runs of a node `pcb` (25-85 °C), its neighbour `housing` and a recorded fan
    speed `u` (0-3 m/s), as a missing-heat reconstruction would give them."""
    temps, fans = [], []
    for r, n in enumerate((700, 500)):
        t = np.linspace(0.0, 1.0, n)
        T = 25.0 + 60.0 * np.abs(np.sin(3.0 * t + r))
        Tb = 25.0 + 60.0 * np.abs(np.sin(3.0 * t + r - 0.3))
        temps.append(np.stack([T, Tb], 1))
        fans.append(3.0 * np.clip(np.sin(7.0 * t + 2 * r), 0.0, None))
    variables = heat_variables(temps, ["pcb", "housing"], "pcb", ["housing"], {"u": fans})
    T = np.concatenate([x[:, 0] for x in temps])
    d = np.concatenate([x[:, 1] - x[:, 0] for x in temps])
    u = np.concatenate(fans)
    rng = np.random.default_rng(7)
    return variables, T, d, u, rng.standard_normal(T.size) * NOISE


def _index(variables, name):
    return [v.name for v in variables].index(name)


def _search(variables, q, **kw):
    return symbolic_search(variables, q, np.full(q.size, NOISE),
                           taken=("pcb", "housing", "u"), **{**BUDGET, **kw})


def _on_front(front, tree):
    found = [law for law in front.front if law.tree == tree]
    assert found, [law.expression for law in front.front]
    return found[0]


def _within_three_stds(law, truth):
    for name, value in truth.items():
        est, std = law.parameters[name], law.stds[name]
        assert abs(est - value) < 3.0 * std, (name, est, std, value)
        assert std < 0.15 * abs(value), (name, std, value)  # and the std says something


def test_arrhenius_law_in_kelvin_is_found_with_its_constants(data):
    variables, T, d, u, noise = data
    c0, E = 2.0e6, 5000.0
    q = c0 * np.exp(-E / (T + 273.15))  # 0.10-1.7 W
    front = _search(variables, q + noise)
    law = _on_front(front, canonical([[(PRIMITIVE_INDEX["arrh"],
                                        _index(variables, "kelvin(pcb)"))]]))
    assert law in front.best(3)
    # written with its heat at 25 °C: c exp(-E (1/T - 1/298.15)) = c0 exp(-E/T)
    _within_three_stds(law, {"c": c0 * np.exp(-E / 298.15), "E": E / 1000.0})  # in kK
    assert law.r2 > 0.999


def test_saturating_law_of_a_difference_is_found_with_its_constants(data):
    variables, T, d, u, noise = data
    a, b = 0.3, 0.15
    q = a * d / (1.0 + b * np.abs(d))
    front = _search(variables, q + noise)
    law = _on_front(front, canonical([[(PRIMITIVE_INDEX["sat"],
                                        _index(variables, "(housing - pcb)"))]]))
    assert law in front.best(3)
    _within_three_stds(law, {"c": a, "b": b})
    assert law.far == "housing"  # a flow between the two nodes


def test_sum_of_two_mechanisms_is_found_with_its_constants(data):
    variables, T, d, u, noise = data
    h, n, c, p = 0.05, 0.25, 0.04, 2.0
    q = h * np.abs(d) ** n * d + c * (u / 3.0) ** p
    front = _search(variables, q + noise)
    tree = canonical([[(PRIMITIVE_INDEX["spow"], _index(variables, "(housing - pcb)"))],
                      [(PRIMITIVE_INDEX["pow"], _index(variables, "(u / 3)"))]])
    law = _on_front(front, tree)
    assert law in front.best(3)
    # the canonical order puts the column's term first: c (u/3)^n + c r2 |d|^n2 d
    assert law.expression == ("c * ((u / 3)^n + r2 * abs((housing - pcb))^n2 * "
                              "(housing - pcb))")
    _within_three_stds(law, {"c": c, "n": p, "n2": n})
    ratio, std = law.parameters["r2"], law.stds["r2"]
    assert abs(ratio - h / c) < 3 * std, (ratio, std, h / c)
    assert law.far is None  # the fan's heat is no flow from the housing


def test_the_written_law_computes_the_truth(data):
    """The expression as written (the model's own evaluator) is the truth's formula at
    the truth's constants, for each primitive the three laws above use."""
    variables, T, d, u, _ = data
    front = _search(variables, 2.0e6 * np.exp(-5000.0 / (T + 273.15)), generations=0)
    law = _on_front(front, canonical([[(PRIMITIVE_INDEX["arrh"],
                                        _index(variables, "kelvin(pcb)"))]]))
    truth = {"c": 2.0e6 * np.exp(-5000.0 / 298.15), "E": 5.0}  # kK
    np.testing.assert_allclose(law_values(law, variables, truth),
                               2.0e6 * np.exp(-5000.0 / (T + 273.15)), rtol=1e-12)
    # as a candidate of the loop: the library's form, `c` its coefficient
    learned, where = learned_law(law, "pcb")
    assert where == ("pcb",) and learned.term.shape == ("E",)
    eff = learned.effect(where, truth["c"], (truth["E"],))
    tree = resolve(parse(eff.expression), ["pcb"], [], list(eff.parameters))
    got = evaluate_numpy(tree, T[:, None], T[:, :0] if T.ndim > 1 else np.zeros((T.size, 0)),
                         [p.value for p in eff.parameters.values()])
    np.testing.assert_allclose(got, 2.0e6 * np.exp(-5000.0 / (T + 273.15)), rtol=1e-12)


def test_the_library_is_the_first_generation(data):
    """Today's library law `c u^p exp(k (T − 25))` (the generator's fan losses) is found
    in generation 0, its constants recovered: nothing the library finds is lost."""
    variables, T, d, u, noise = data
    c, p, k = 0.03 * 3.0 ** 2, 2.0, 0.015  # c·u² = c·U²·(u/U)², U = 3
    q = c * (u / 3.0) ** p * np.exp(k * (T - 25.0))
    front = _search(variables, q + noise, generations=0)
    assert front.generations == 0 and front.evaluated < BUDGET["evaluations"]
    law = _on_front(front, canonical([[(PRIMITIVE_INDEX["pow"], _index(variables, "(u / 3)")),
                                       (PRIMITIVE_INDEX["exp"], _index(variables, "pcb"))]]))
    _within_three_stds(law, {"c": c, "n": p, "k": k})
    assert LIBRARY[1].template == "c * {u}^p * exp(k * ({a} - 25))"
    assert law.template == "c * {u}^n * exp(k * ({a} - 25))"  # the same form


def test_same_random_state_same_front_and_the_budget_holds(data):
    variables, T, d, u, noise = data
    q = 0.3 * d / (1.0 + 0.15 * np.abs(d)) + noise
    lines = []
    a = _search(variables, q, evaluations=300, say=lines.append)
    b = _search(variables, q, evaluations=300)
    assert [x.expression for x in a.front] == [x.expression for x in b.front]
    assert [x.parameters for x in a.front] == [x.parameters for x in b.front]
    assert a.evaluated <= 300 and a.stopped == "budget"
    assert lines and all(line.startswith("symbolic search: generation") for line in lines)


def test_an_interruption_keeps_the_front_found_so_far(data):
    variables, T, d, u, noise = data
    q = 0.3 * d / (1.0 + 0.15 * np.abs(d)) + noise

    def say(line):
        if "generation 1" in line:
            raise KeyboardInterrupt

    front = _search(variables, q, say=say)
    assert front.stopped == "interrupted" and front.front
    assert front.evaluated > 0
