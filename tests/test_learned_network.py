"""A heat network trained inside the model and distilled into the library
(`thermojax.discovery.learn_network_heat`, issue 33 item 2), on generated data whose
law is known: a fan dissipating c · air_speed^p · exp(k (T_pcb − 25)) W in the
unmeasured pcb of chain3 (c = 0.03, p = 2, k = 0.015)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import thermojax as tj
from thermojax import Experiment, parse_model
from thermojax.discovery import learn_network_heat
from thermojax.model.effects import lower_effects

from helpers import CONFIGS
from hidden import generator as g

CHAIN3 = CONFIGS.parent / "tests" / "hidden" / "models" / "chain3.toml"


def _experiments(spec, runs):
    low = lower_effects(spec).spec
    return [Experiment(ts, np.stack([c[k] for k in low.input_columns], 1),
                       np.stack([c[k] for k in low.sensor_columns], 1)) for ts, c in runs]


@pytest.mark.slow
def test_the_network_finds_the_fan_law_and_its_refit_recovers_the_truth():
    runs = g.generate_case("law_quadratic_input", seed=0, horizon_s=1500.0)
    spec = parse_model(CHAIN3.read_text())
    believed = tj.fit(spec, _experiments(spec, runs))
    law = learn_network_heat(believed, runs, "pcb", trajectory_steps=5)
    for c in spec.sensor_columns:  # the network explains most of the error
        assert law.rmse_after[c] < 0.5 * law.rmse_before[c], (law.rmse_before, law.rmse_after)
    best = law.distilled[0]
    assert best.law.term.name == "power of a column growing exponentially with temperature"
    assert best.where == ("pcb",) and best.law.column == "air_speed", best
    assert best.r2 > 0.5 and best.r2 > law.distilled[1].r2 + 0.2, law.distilled[:3]
    # the proposal, refitted with its coefficient and shape free, is the truth
    extended = dataclasses.replace(spec, effects=(*spec.effects, best.effect()))
    refit = tj.fit(extended, _experiments(extended, runs))
    assert refit.converged
    assert all(r < 1.5 * 0.01 for r in refit.rmse.values()), refit.rmse
    for name, truth in (("c", 0.03), ("p", 2.0), ("k", 0.015)):
        p = refit.parameters[f"effects.expression.pcb.{name}"]
        assert p["std"] > 0 and abs(p["value"] - truth) < 3 * p["std"], (name, p)


def test_a_node_without_missing_heat_is_refused_with_the_reason():
    """Data from the believed model itself: no heat is missing anywhere."""
    runs = g.generate_case("law_quadratic_input", seed=1, horizon_s=900.0, model="believed",
                           runs=[0])
    spec = parse_model(CHAIN3.read_text())
    fitted = tj.fit(spec, _experiments(spec, runs))
    with pytest.raises(ValueError, match="no missing heat at node 'pcb'"):
        learn_network_heat(fitted, runs, "pcb")
    with pytest.raises(ValueError, match="not in the model"):
        learn_network_heat(fitted, runs, "fan")
    ts, cols = runs[0]
    with pytest.raises(ValueError, match=r"run 0 lacks the model's column\(s\) \['P_die'\]"):
        learn_network_heat(fitted, [(ts, {k: v for k, v in cols.items() if k != "P_die"})],
                           "pcb")
