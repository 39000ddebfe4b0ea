"""Designing the run that tells two explanations apart, checked by running it.

The rivals are a sensor lag on the die's reading and an unmodelled mass in series between
the board and the die (`chain3`): on the calibration schedule (chamber ramps, steady power)
the mass, when true, is predicted to be mimicked by the lag. The designed profile is
simulated with the mass as the truth by an independent simulator (`chamber_truth`, the mass
a plain fourth node), both rivals are fitted by `fit`, and the log-likelihood-ratio
statistic of the run is compared with the one predicted before the run.
"""

import math
from pathlib import Path

import numpy as np
import pytest

import chamber_truth as truth
from helpers import run_cli

from thermojax.design._discrimination import DECISIVE, decisive_probability, discriminate
from thermojax.design._references import reference_profile
from thermojax.fitting import fit
from thermojax.measurements import Experiment
from thermojax.model import parse_model

ROOT = Path(__file__).resolve().parents[1]
BASE = (ROOT / "thermojax" / "data" / "chain3.toml").read_text()
LAG = BASE + '\n[[effects]]\nkind = "sensor_lag"\nwhere = ["T_die"]\ntime_constant = 8.0\n'
MASS = BASE + ('\n[[effects]]\nkind = "extra_node"\nwhere = ["pcb", "die"]\nname = "spreader"\n'
               'capacitance = 0.5\nconductance = 0.12\nconductance_b = 0.12\n')
SIGMA = 0.01


def _mass_truth():
    """The mass hypothesis as a plain four-node network, for the independent simulator."""
    import tomllib

    doc = tomllib.loads(BASE)
    doc["nodes"].append({"name": "spreader", "capacitance": 0.5})
    doc["links"] = [lk for lk in doc["links"] if set(lk["between"]) != {"pcb", "die"}]
    doc["links"] += [{"between": ["pcb", "spreader"], "conductance": 0.12},
                     {"between": ["spreader", "die"], "conductance": 0.12}]
    return truth.read_chamber_model(doc)


def _statistic(ts, T, P, seed):
    """`(RSS_lag − RSS_mass) / σ²` of a run simulated with the mass true, each rival fitted."""
    m = _mass_truth()
    U = np.stack([T, P], axis=1)
    z = truth.simulate(m, ts, U)
    rng = np.random.default_rng(seed)
    Y = np.stack([z[:, i] + rng.normal(0, SIGMA, ts.size) for i, _ in m.sensors.values()],
                 axis=1)
    rss = {}
    for name, text in (("lag", LAG), ("mass", MASS)):
        spec = parse_model(text)
        res = fit(spec, [Experiment(ts, U, Y, name=name)])
        rss[name] = float(np.sum((res.predictions[0] - Y) ** 2)) / SIGMA ** 2
    return rss["lag"] - rss["mass"]


def test_decisive_probability_is_the_normal_tail():
    # 2 log LR ~ N(λ, 4λ): at λ = DECISIVE half the runs decide
    assert decisive_probability(DECISIVE) == pytest.approx(0.5)
    assert decisive_probability(100.0) == pytest.approx(
        0.5 * math.erfc(-(100.0 - DECISIVE) / (2 * math.sqrt(100.0)) / math.sqrt(2)))
    assert decisive_probability(0.0) == 0.0


@pytest.mark.slow
def test_designed_run_decides_where_the_calibration_schedule_cannot(tmp_path):
    specs = [("lag", parse_model(LAG)), ("mass", parse_model(MASS))]
    d = discriminate(specs, 1800.0, dt=10.0, n_starts=1, rounds=2, max_steps=60,
                     references=("calibration",))
    assert not d.violations
    for pair, v in d.pairs.items():
        assert v["p_decisive"] > 0.999, (pair, v)
    near_tie = d.references["calibration"][("mass", "lag")]
    assert near_tie["p_decisive"] < 0.5, near_tie
    # Run both profiles with the mass true: the statistic each gives, against the prediction.
    designed = _statistic(d.ts, d.temperature, d.power, seed=5)
    lam = d.pairs[("mass", "lag")]["expected_2log_lr"]
    assert designed > DECISIVE
    # N(λ, 4λ): within four stds, and 5 % for refits that stop at slightly different optima
    assert abs(designed - lam) <= 4 * 2 * math.sqrt(lam) + 0.05 * lam, (designed, lam)
    rT, rP = reference_profile("calibration", d.schedule)
    default = _statistic(d.ts, rT, rP, seed=5)
    lam_ref = near_tie["expected_2log_lr"]
    # N(λ, 4λ): within four stds of the prediction
    assert abs(default - lam_ref) <= 4 * 2 * math.sqrt(lam_ref) + 1.0, (default, lam_ref)


def test_near_tie_advice_names_the_command():
    from thermojax.investigation._separation import separation_advice

    for kinds in ({"sensor_lag", "extra_node"}, {"radiation", "conductance_temperature"},
                  {"sensor_gain", "heat_source"}, {"boundary", "heat_source"}):
        assert "thermojax design --model M --rivals" in separation_advice(kinds)


def test_rivals_reading_other_sensors_are_refused(tmp_path, capsys):
    from helpers import assert_refused

    other = tmp_path / "other.toml"
    other.write_text(BASE.replace('column = "T_die"', 'column = "T_chip"'))
    rc, _, err = run_cli(capsys, "design", "--model", ROOT / "thermojax" / "data" / "chain3.toml",
                         "--duration", "600", "--dt", "10", "--rivals", other,
                         "--out", tmp_path / "d")
    assert_refused(rc, err, "other.toml", "same sensors")
    assert not (tmp_path / "d").exists()


def test_rivals_from_an_investigation_folder(tmp_path, capsys):
    """A folder as `investigate` writes it (report.json, step models), made by hand: the
    near-tie the loop named becomes the rivals."""
    import json

    from helpers import assert_refused
    from thermojax.design._from_investigation import rivals_from_investigation

    (tmp_path / "step0_model.toml").write_text(BASE)
    (tmp_path / "step1_model.toml").write_text(LAG)
    steps = [{"added": None, "candidates": [
        {"kind": "sensor_lag", "where": ["T_die"], "tied_with": [["extra_node", ["pcb", "die"]]]},
        {"kind": "sensor_offset", "where": ["T_die"], "tied_with": []}]},
        {"added": {"kind": "sensor_lag", "where": ["T_die"],
                   "parameters": {"time_constant": 8.0}}, "candidates": []}]
    (tmp_path / "report.json").write_text(json.dumps({"steps": steps}))
    specs = rivals_from_investigation(tmp_path)
    assert [n for n, _ in specs] == ["sensor_lag(T_die)", "extra_node(pcb-die)"]
    assert specs[0][1].effects[0].parameters["time_constant"].value == 8.0  # as fitted
    added = specs[1][1].effects[-1]
    assert added.kind == "extra_node" and added.where == ("pcb", "die")
    # no near-tie: refused, naming the file
    steps[0]["candidates"][0]["tied_with"] = []
    (tmp_path / "report.json").write_text(json.dumps({"steps": steps}))
    rc, _, err = run_cli(capsys, "design", "--from-investigation", tmp_path, "--duration", "600",
                         "--out", tmp_path / "d")
    assert_refused(rc, err, "report.json", "no near-tie")
