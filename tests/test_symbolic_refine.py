"""Refining a held law (`investigation._symbolic_step.refine_laws`): the search around a
law the model holds fits the heat that law carries plus the missing heat, so a law that
approximates one mechanism of two is replaced by the sum of both, with the truth's
constants; the candidates it makes replace the held law, and the report matches the
added law by its expression."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from thermojax.discovery._missing_heat import MissingHeat
from thermojax.investigation._evidence import is_added
from thermojax.investigation._symbolic_step import SearchSettings, refine_laws
from thermojax.model._expression import names, parse
from thermojax.model._model_file import parse_model

KELVIN = 273.15
NOISE = 0.002  # W, the std of the reconstructed missing heat
FAN_C, LEAK_C, LEAK_E = 0.05, 0.004, 6.0  # W at 3 m/s, W at 25 °C, kK

MODEL = """
name = "die"

[[nodes]]
name = "die"
capacitance = 0.3

[[boundaries]]
node = "die"
input = "T_chamber"
conductance = 0.06

[[effects]]
kind = "expression"
where = ["die"]
expression = "c * (air_speed / 3)^p"
parameters = { c = %r, p = 2.0 }
""" % FAN_C


class _Run:
    """The columns a run gives the search: `names` and `column(name)`."""

    def __init__(self, columns: dict):
        self._columns = columns
        self.names = tuple(columns)

    def column(self, name):
        return self._columns[name]


def _truth(T, u):
    """The die's heat (W): a fan's losses plus an Arrhenius leakage (E in kK)."""
    leak = LEAK_C * np.exp(-LEAK_E * (1000.0 / (T + KELVIN) - 1000.0 / 298.15))
    return FAN_C * (u / 3.0) ** 2 + leak


@pytest.fixture(scope="module")
def refined():
    spec = parse_model(MODEL)
    rng = np.random.default_rng(3)
    ts, heat, temps, runs = [], [], [], []
    for r, n in enumerate((600, 450)):
        t = np.arange(n, dtype=float)
        T = 25.0 + 60.0 * np.abs(np.sin(3.0 * t / n + r))
        chamber = T - 2.0
        u = 3.0 * np.clip(np.sin(11.0 * t / n + 2 * r), 0.0, None)
        held = FAN_C * (u / 3.0) ** 2  # the fan alone: what the model holds
        ts.append(t)
        heat.append((_truth(T, u) - held + NOISE * rng.standard_normal(n))[:, None])
        temps.append(T[:, None])
        runs.append(_Run({"T_chamber": chamber, "air_speed": u}))
    mh = MissingHeat(("die",), ("die",), 1.0, 100.0, ts, heat,
                     [np.full((len(t), 1), NOISE) for t in ts], temps)
    step = SimpleNamespace(spec=spec, result=SimpleNamespace(lowered_spec=spec))
    said = []
    laws, entry = refine_laws(step, runs, mh, {}, SearchSettings(evaluations=800,
                                                                 seconds=None), said.append)
    return laws, entry, said


def test_the_search_around_a_held_law_finds_the_sum_of_both_mechanisms(refined):
    laws, entry, said = refined
    assert entry["replaces"] == ["c * (air_speed / 3)^p"] and entry["node"] == "die"
    assert any("refining the law(s) at die" in s for s in said)
    both = [found for _, _, _, found in laws
            if {"air_speed", "die"} <= set(names(parse(found.expression)))
            and "kelvin(die)" in found.expression]
    assert both, [found.expression for _, _, _, found in laws]
    law = both[0]
    # the Arrhenius constant (kK) and the fan's exponent, within three of their stds
    assert abs(law.parameters["E"] - LEAK_E) < 3 * law.stds["E"], law
    exponent = next(k for k in law.parameters if k.startswith("n"))
    assert abs(law.parameters[exponent] - 2.0) < 3 * law.stds[exponent], law
    assert all(replaces == (0,) for _, _, replaces, _ in laws)  # the held law's index
    assert any(row["picked"] for row in entry["front"])


def test_no_held_law_no_refining_search():
    spec = parse_model(MODEL.split("[[effects]]")[0])
    step = SimpleNamespace(spec=spec, result=SimpleNamespace(lowered_spec=spec))
    t = np.arange(50.0)
    mh = MissingHeat(("die",), ("die",), 1.0, 10.0, [t], [np.ones((50, 1))],
                     [np.full((50, 1), 0.01)], [np.full((50, 1), 30.0)])
    assert refine_laws(step, [_Run({"T_chamber": t})], mh, {}, SearchSettings(),
                       lambda _m: None) == ([], None)


def test_the_report_matches_the_added_law_by_its_expression():
    added = {"kind": "expression", "where": ["die"], "expression": "c * exp(k * die)"}
    other = {"kind": "expression", "where": ["die"], "expression": "c * die^n"}
    assert is_added({**added}, added) and not is_added(other, added)
    assert is_added({"kind": "boundary", "where": ["T_chamber", "die"]},
                    {"kind": "boundary", "where": ["T_chamber", "die"]})
