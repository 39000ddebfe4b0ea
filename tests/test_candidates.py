"""The candidate machinery: multiple testing, boundary p-values, places, diagnose, resume."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import stats

from thermojax import parse_model
from thermojax.investigation._candidates import (benjamini_hochberg, column_role,
                                   enumerate_places, refit_p_value)
from thermojax.cli import main
from thermojax.model.effects import lower_effects

from hidden import generator as g


def test_benjamini_hochberg_textbook_example():
    # Benjamini & Hochberg (1995), section 3.2: 15 p-values, q = 0.05 rejects the 4 smallest
    p = [0.0001, 0.0004, 0.0019, 0.0095, 0.0201, 0.0278, 0.0298, 0.0344, 0.0459, 0.3240,
         0.4262, 0.5719, 0.6528, 0.7590, 1.0000]
    rejected = benjamini_hochberg(p[::-1], 0.05)[::-1]
    assert rejected.tolist() == [True] * 4 + [False] * 11
    assert benjamini_hochberg([], 0.05).size == 0


def test_boundary_p_values_are_the_chi_bar_square_mixture():
    # one positive parameter: ½χ²₀ + ½χ²₁, so half the χ²₁ tail
    assert refit_p_value("radiation", 3.84, 1) == pytest.approx(0.5 * stats.chi2.sf(3.84, 1))
    # a signed parameter: the plain χ²₁ tail
    assert refit_p_value("sensor_offset", 3.84, 1) == pytest.approx(stats.chi2.sf(3.84, 1))
    # three parameters, the first on its boundary: ½χ²₂ + ½χ²₃
    assert refit_p_value("extra_node", 10.0, 3) == pytest.approx(
        0.5 * stats.chi2.sf(10.0, 2) + 0.5 * stats.chi2.sf(10.0, 3))
    # Monte Carlo: the mixture's 5 % point for a boundary parameter is χ²₁'s 10 % point
    rng = np.random.default_rng(0)
    z = rng.standard_normal(200_000)
    lr = np.maximum(z, 0) ** 2  # LR of a positive mean estimated from one N(0,1) draw
    p = np.array([refit_p_value("radiation", x, 1) for x in lr[:20_000]])
    assert abs(np.mean(p < 0.05) - 0.05) < 0.005


def test_column_guesses():
    assert column_role("T_mount", np.zeros(3)) == "temperature"
    assert column_role("P_aux", np.zeros(3)) == "power"
    assert column_role("air_speed", np.zeros(3)) == "other"


def test_places_cover_every_kind_and_unused_columns():
    spec = parse_model(g.dump_toml(g.load_case("heat_source")["believed"]))
    lowered = lower_effects(spec).spec
    places = enumerate_places(spec, lowered, {"P_aux": "power", "T_mount": "temperature"})
    kinds = {k for k, _ in places}
    assert kinds == {"extra_node", "radiation", "conductance_temperature",
                     "capacitance_temperature", "heat_source", "boundary", "conductance_input",
                     "sensor_lag", "sensor_offset", "sensor_gain"}  # no bias: no viscoelastic
    assert ("heat_source", ("P_aux", "pcb")) in places
    assert ("boundary", ("T_mount", "housing")) in places
    assert ("boundary", ("T_chamber", "die")) in places  # a second path from a used column
    assert not any(k == "heat_source" and w[0] == "T_mount" for k, w in places)
    # an effect the model has is not proposed again
    spec2 = parse_model(g.dump_toml(g.load_case("heat_source")["believed"]) +
                        '\n[[effects]]\nkind = "sensor_offset"\nwhere = ["T_die"]\noffset = 0.0\n')
    places2 = enumerate_places(spec2, lower_effects(spec2).spec, {})
    assert ("sensor_offset", ("T_die",)) not in places2


def test_a_used_heat_input_may_be_routed_to_another_node():
    # Bacher & Madsen's last step: solar radiation that already heats the interior heats
    # the envelope (a node an extra_node effect made) too. Never proposed where it heats.
    from helpers import ROOM_WITH_ENVELOPE

    spec = parse_model(ROOM_WITH_ENVELOPE)

    places = enumerate_places(spec, lower_effects(spec).spec, {})
    assert ("heat_source", ("Ps", "Te")) in places
    assert ("heat_source", ("Ps", "Ti")) not in places
    # the paths the envelope's mass made are its own parameters: not split again
    assert ("extra_node", ("Ti", "Te")) not in places and ("extra_node", ("Te", "Ta")) not in \
        places and ("extra_node", ("Te",)) in places
    assert not any(k == "heat_source" and w[0] == "Ta" for k, w in places)  # a temperature


def _write(case, folder, horizon):
    return g.write_case(case, folder, seed=0, horizon_s=horizon)


@pytest.mark.slow
def test_diagnose_cli_ranks_the_hidden_offset_first(tmp_path):
    files = _write("sensor_offset", tmp_path / "data", 1200.0)
    argv = ["diagnose", "--model", str(files["model"]), "--out", str(tmp_path / "d")]
    for p in files["data"]:
        argv += ["--data", str(p)]
    assert main(argv) == 0
    report = json.loads((tmp_path / "d" / "report.json").read_text())
    first = report["candidates"][0]
    assert (first["kind"], first["where"]) == ("sensor_offset", ["T_die"]) and first["supported"]
    assert report["whiteness_p"]["T_die"] < 1e-6
    assert report["diagnostics"]["findings"]
    assert (tmp_path / "d" / "report.md").is_file()


@pytest.mark.slow
def test_investigate_resumes_from_its_checkpoint(tmp_path, capsys):
    files = _write("sensor_offset", tmp_path / "data", 1200.0)
    out = tmp_path / "inv"
    argv = ["investigate", "--model", str(files["model"]), "--out", str(out)]
    for p in files["data"]:
        argv += ["--data", str(p)]
    assert main(argv) == 0
    first = json.loads((out / "report.json").read_text())
    assert [s["added"] and s["added"]["kind"] for s in first["steps"]] == [None,
                                                                           "sensor_offset"]
    capsys.readouterr()
    # started again with the same inputs: resumes after step 1, no candidate refitted again
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "resuming after step 1" in printed
    again = json.loads((out / "report.json").read_text())
    assert [s["added"] and s["added"]["kind"] for s in again["steps"]] == [None,
                                                                           "sensor_offset"]
    assert again["steps"][0]["candidates"] == first["steps"][0]["candidates"]
    # a data file edited in place (same path, same times, one value changed): refused,
    # naming the file, never resumed on the old steps
    data = files["data"][0]
    lines = data.read_text().splitlines()
    row = lines[-1].split(",")
    row[-1] = repr(float(row[-1]) + 0.5)
    data.write_text("\n".join(lines[:-1] + [",".join(row)]) + "\n")
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "other inputs" in err and f"the data of {data}" in err and "--restart" in err
    # --restart starts afresh: nothing of the earlier run is left beside the new report
    (out / "step7_fit.png").write_bytes(b"from a longer earlier run")
    assert main(argv + ["--restart"]) == 0
    assert not (out / "step7_fit.png").exists()
    assert json.loads((out / "checkpoint.json").read_text())["inputs"]["runs"][0][
        "path"] == str(data)


@pytest.mark.slow
def test_investigate_under_the_kalman_likelihood(tmp_path):
    """The loop runs on the Kalman likelihood too (innovations for whiteness; refits
    with the exact-Hessian Newton solver). Scaled down: short runs, one step, one refit
    (the offset ranks first by its score)."""
    import thermojax

    files = _write("sensor_offset", tmp_path / "data", 900.0)
    spec = thermojax.load_model(files["model"])
    runs = [thermojax.read_telemetry(p) for p in files["data"]]
    report = thermojax.investigate(spec, runs, likelihood="kalman", refits=1, max_steps=1,
                                   holdout_check=False)
    assert report["likelihood"] == "kalman"
    added = report["steps"][1]["added"]
    assert (added["kind"], added["where"]) == ("sensor_offset", ["T_die"])
    assert abs(added["parameters"]["offset"] - 0.15) < 0.01
    assert report["steps"][1]["rmse"]["T_die"] < 1.5 * 0.01


def test_heat_responses_hold_the_heat_as_told_against_scipy():
    """`heat_responses` of a two-node network to a switching heat, zero- and first-order
    hold, against `scipy.signal.lsim` (`interp` False / True) from the same steady state."""
    from scipy import signal

    from thermojax.investigation._candidates import heat_responses

    cap = np.array([200.0, 50.0])  # J/K
    G01, G0a = 2.0, 1.5  # W/K: node 0 - node 1, node 0 - ambient
    A = np.array([[-(G01 + G0a), G01], [G01, -G01]]) / cap[:, None]
    C = np.array([[0.0, 1.0]])
    ts = np.arange(200) * 20.0  # s; the fast time constant is about 20 s
    rng = np.random.default_rng(3)
    W = np.zeros((1, ts.size, 2))
    W[0, :, 0] = 5.0 * rng.integers(0, 2, ts.size)  # W into node 0, switching
    W[0, :, 1] = np.linspace(0.0, 1.0, ts.size)
    got = heat_responses(A, C, cap, ts[None], [W, W], ["zoh", "foh"])
    system = signal.StateSpace(A, np.diag(1.0 / cap), C, np.zeros((1, 2)))
    x0 = np.linalg.solve(A, -np.diag(1.0 / cap) @ W[0, 0])
    for k, interp in enumerate((False, True)):
        _, y, _ = signal.lsim(system, W[0], ts, X0=x0, interp=interp)
        np.testing.assert_allclose(got[k, 0, :, 0], y, rtol=1e-9, atol=1e-9 * np.abs(y).max())
    assert np.abs(got[0] - got[1]).max() > 0.1  # the two holds differ here


@pytest.mark.slow
def test_a_law_on_a_zero_order_hold_input_is_scored_as_its_refit_integrates_it():
    """A learned law `c·P^p·exp(k(T − 25))` at the node a zero-order-hold power `P` already
    heats: at p = 1, k = 0 it is the model's own gain on `P`, so its score is zero. The
    data were made with `P` held to first order (PRBS1's solar input behaves so), which
    the model cannot follow; scored with `P` held to first order instead of as the model
    holds it (before this was fixed), the law would take that misfit for an effect its
    refit, integrated as the model holds `P`, cannot reach."""
    import dataclasses

    import thermojax as tj
    from thermojax.discovery._library import LIBRARY, LearnedLaw
    from thermojax.fitting._fit import output_error_at
    from thermojax.investigation._candidates import score_candidates

    model = """
name = "one_node"
[[nodes]]
name = "T"
capacitance = 600.0
initial = 25.0
[[boundaries]]
node = "T"
input = "Ta"
conductance = 10.0
hold = "zoh"
[[heat_inputs]]
node = "T"
input = "P"
gain = 1.0
hold = "HOLD"
[[sensors]]
node = "T"
column = "yT"
noise = 0.01
"""
    believed, truth = (parse_model(model.replace("HOLD", h)) for h in ("zoh", "foh"))
    rng = np.random.default_rng(0)
    ts = np.arange(300) * 30.0  # s, the node's time constant 60 s
    P = 20.0 * rng.integers(0, 2, ts.size)
    Ta = 25.0 + np.zeros(ts.size)
    u = np.stack([Ta, P], 1)  # the input order of both specs: Ta, P
    assert list(truth.input_columns) == ["Ta", "P"]
    data = tj.Dataset.from_experiments([tj.Experiment(ts, u, np.zeros((ts.size, 1)))])
    y = np.asarray(tj.simulate_dataset(tj.ThermalModel.from_spec(truth), data))[0]
    y = y + 0.01 * rng.standard_normal(y.shape)
    experiments = [tj.Experiment(ts, u, y)]
    result = tj.fit(believed, experiments)
    assert result.rmse["yT"] > 5 * 0.01  # the hold's misfit is far above the noise
    data, weights, r, J, states = output_error_at(result, experiments)
    term = next(t for t in LIBRARY if t.places == "input" and t.shape == ("p", "k"))
    law = LearnedLaw(dataclasses.replace(term, trials=((1.0, 0.0),)), column="P")
    columns = {"P": P[None], "Ta": Ta[None]}
    [cand] = score_candidates(result, data, [(law, ("T",))], columns, np.asarray(weights),
                              np.asarray(r), np.asarray(J), states=states)
    assert cand.score < 1e-6 * float(np.sum(np.asarray(r) ** 2)), cand.score
    # the same direction held to first order: a large, spurious score
    class FirstOrder(LearnedLaw):
        def heat_hold(self, ctx, where):
            return "foh"

    foh = FirstOrder(law.term, column="P")
    [wrong] = score_candidates(result, data, [(foh, ("T",))], columns, np.asarray(weights),
                               np.asarray(r), np.asarray(J), states=states)
    assert wrong.score > 100.0, wrong.score
