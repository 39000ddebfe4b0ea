"""The missing-physics loop on generated buildings (issue 31, item 3).

One run each, 15-min samples, process noise on every node, a one-node start model
(`buildings.py`: an exact stochastic simulator independent of thermojax). Under the
Kalman likelihood the loop must recover three or more states of the four-state truth
(a heater with its own mass, an envelope, a sensor with its own lag, solar gain on the
envelope) and add nothing when the truth is the start model. Every refit must reach at
least its nested model and every held-out fold must be either counted or set aside with
a reason: the held-out checks of `_selection` on the field's usual case, one log.
"""

from __future__ import annotations

import json

import pytest

from thermojax.cli import main

from . import buildings as b
from .test_investigate import _check_report_keys

DAYS = 10  # 960 samples: scaled down from the 30-day default to keep the suite fast


def _investigate(name, tmp_path, max_steps):
    files = b.write_building_case(name, tmp_path / "data", seed=0, days=DAYS)
    out = tmp_path / "out"
    assert main(["investigate", "--likelihood", "kalman", "--model", str(files["model"]),
                 "--data", str(files["data"][0]), "--out", str(out),
                 "--max-steps", str(max_steps)]) == 0
    return files, json.loads((out / "report.json").read_text())


def _states_added(report) -> int:
    """Thermal states the loop added: extra nodes and sensor lags."""
    return sum(1 for s in report["steps"][1:]
               if s["added"]["kind"] in ("extra_node", "sensor_lag"))


@pytest.mark.slow
def test_the_loop_recovers_a_four_state_building_from_one_node(tmp_path):
    files, report = _investigate("building_4state", tmp_path, max_steps=2)
    _check_report_keys(report)
    added = [(s["added"]["kind"], s["added"]["where"]) for s in report["steps"][1:]]
    assert 1 + _states_added(report) >= 3, added  # Ti plus two more states, one per step
    for prev, step in zip(report["steps"], report["steps"][1:]):
        assert step["nll"] < prev["nll"] - 5.0, added  # every addition is a real gain
    for step in report["steps"]:
        for c in step["candidates"]:
            for vote in c.get("holdout_folds", []):
                assert vote["vote"] in ("for", "against", "inconclusive")
                assert vote["vote"] != "inconclusive" or vote["why"]


@pytest.mark.slow
def test_the_loop_adds_nothing_to_a_building_that_is_its_model(tmp_path):
    files, report = _investigate("building_null", tmp_path, max_steps=2)
    _check_report_keys(report)
    assert len(report["steps"]) == 1, [s["added"] for s in report["steps"][1:]]
