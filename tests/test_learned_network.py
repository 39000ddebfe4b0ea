"""A heat network trained inside the model and distilled into the library
(`thermojax.discovery.learn_network_heat`, issue 33 item 2), on generated data whose
law is known: a fan dissipating c · air_speed^p · exp(k (T_pcb − 25)) W in the
unmeasured pcb of chain3 (c = 0.03, p = 2, k = 0.015). That form is one of the function
library's templates (`discovery.LIBRARY`), so the distillation matches a known form and
the refit recovers its parameters: a test of finding and refitting a form the library
holds, not of discovering one it lacks (a network whose heat matches no library term is
refused, `test_the_network_account_proposes_only_a_matched_law_that_explains_the_misfit`)."""

from __future__ import annotations

import numpy as np
import pytest

import thermojax as tj
from thermojax import Experiment, parse_model
from thermojax.discovery import learn_network_heat
from thermojax.model.effects import lower_effects

from helpers import CONFIGS, law_truths
from hidden import generator as g

CHAIN3 = CONFIGS.parent / "tests" / "hidden" / "models" / "chain3.toml"


def _experiments(spec, runs):
    low = lower_effects(spec).spec
    return [Experiment(ts, np.stack([c[k] for k in low.input_columns], 1),
                       np.stack([c[k] for k in low.sensor_columns], 1)) for ts, c in runs]


@pytest.mark.slow
def test_the_loop_asks_the_network_and_its_proposal_recovers_the_truth(monkeypatch):
    """The loop's network step (`investigate` calls it where nothing was supported):
    the network's distilled proposal, refitted, judged by the rule and held-out checked,
    is chosen, ends at the noise and holds the truth within three stds."""
    from thermojax.discovery import missing_heat
    from thermojax.investigation import _network_candidate
    from thermojax.investigation._held_out import HeldOutFits
    from thermojax.investigation._missing_heat_step import _network_step
    from thermojax.investigation._step import evaluate

    monkeypatch.setattr(_network_candidate, "TRAJECTORY_STEPS", 5)  # a scaled-down run
    runs = g.generate_case("law_quadratic_input", seed=0, horizon_s=1500.0)
    telemetry = [tj.Telemetry(ts, cols) for ts, cols in runs]
    spec = parse_model(CHAIN3.read_text())
    step = evaluate(spec, telemetry, "output_error")
    mh = missing_heat(step.result)
    assert "pcb" in mh.carriers
    cands = []
    chosen = _network_step(step, telemetry, mh, cands, "output_error", 0.05, 0.01, spec,
                           True, print, HeldOutFits())
    net = step.record["network"]
    assert net["node"] == "pcb" and net["explained_share"] > 0.5, net
    for c in spec.sensor_columns:  # the network explains most of the error
        assert net["rmse_after"][c] < 0.5 * net["rmse_before"][c], net
    assert net["distilled"]["law"] == "power of a column growing exponentially with temperature"
    assert chosen is not None and cands == [chosen] and chosen.supported, cands
    assert chosen.where == ("pcb",) and chosen.learned.column == "air_speed"
    assert chosen.method == "refit" and "heat network" in chosen.note
    refit = chosen.result.result
    assert refit.converged
    assert all(r < 1.5 * 0.01 for r in refit.rmse.values()), refit.rmse
    truths = law_truths(chosen.learned.text(chosen.where), {"c": 0.03, "p": 2.0, "k": 0.015})
    for name, truth in truths.items():
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


def _law(before, after, r2):
    """A `NetworkLaw` with the given RMSEs (°C per sensor) whose best distilled term,
    an exponential of the pcb's temperature, matches its heat with `r2`."""
    from thermojax.discovery import LIBRARY, Distilled, LearnedLaw, NetworkLaw

    term = next(t for t in LIBRARY if t.name == "exponential of a temperature")
    best = Distilled(LearnedLaw(term), ("pcb",), 0.1, (0.02,), r2)
    return NetworkLaw("pcb", before, before, after, [], [best], model=None)


def test_the_network_account_proposes_only_a_matched_law_that_explains_the_misfit():
    """The loop's rule on the network (`_network_candidate.account`): the mean over
    sensors of 1 − (after / before)² must reach one half, and the best library term must
    match the network's heat with R² ≥ 0.5; each refusal says what it means."""
    from thermojax.investigation._network_candidate import account

    before = {"T_a": 0.4, "T_b": 0.2}
    # (0.2/0.4)² = 0.25 and (0.1/0.2)² = 0.25: three quarters of the misfit removed
    ok = account("pcb", _law(before, {"T_a": 0.2, "T_b": 0.1}, 0.8))
    assert ok["proposed"] and ok["explained_share"] == pytest.approx(0.75)
    assert ok["distilled"]["expression"] == "c * exp(k * (pcb - 25))"
    assert "refitted as a candidate" in ok["verdict"]
    # 1 − 0.81 = 0.19 on each sensor: too little, whatever the match
    weak = account("pcb", _law(before, {"T_a": 0.36, "T_b": 0.18}, 0.9))
    assert not weak["proposed"] and weak["explained_share"] == pytest.approx(0.19)
    assert "no function of what was recorded" in weak["verdict"]
    unmatched = account("pcb", _law(before, {"T_a": 0.2, "T_b": 0.1}, 0.3))
    assert not unmatched["proposed"] and "matches no library term" in unmatched["verdict"]
    assert "extend `discovery.LIBRARY`" in unmatched["verdict"]
