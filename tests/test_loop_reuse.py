"""Work the missing-physics loop does once, not twice (issue 10, item 3): held-out fits
of a model are kept for the next step, and estimated noise stds are profiled out inside
the solve, so where they start does not matter (no re-weighting passes to redo)."""

from __future__ import annotations

from hidden import generator as g


def _one_run(case, tmp_path, horizon_s):
    from thermojax import load_model
    from thermojax.measurements import read_telemetry

    files = g.write_case(case, tmp_path / "data", seed=0, horizon_s=horizon_s)
    return load_model(files["model"]), [read_telemetry(files["data"][0])]


def test_held_out_fits_are_made_once_per_model_and_fold(tmp_path, monkeypatch):
    from thermojax import parse_model
    from thermojax.investigation import _held_out

    calls = []
    monkeypatch.setattr(_held_out, "_fit_without",
                        lambda spec, exps, fold, starts, lk: calls.append((spec, fold, lk))
                        or len(calls))
    text = (g.HERE / "models" / "chain3.toml").read_text()
    a, a_again = parse_model(text), parse_model(text)  # equal, distinct objects
    b = parse_model(text.replace("noise = 0.01", "noise = 0.02", 1))
    fits = _held_out.HeldOutFits()
    assert fits(a, [], (0, None), "output_error") == 1
    assert fits(a_again, [], (0, None), "output_error") == 1  # kept
    assert fits(a, [], (1, None), "output_error") == 2  # another fold
    assert fits(b, [], (0, None), "output_error") == 3  # another model
    assert fits(a, [], (0, None), "kalman") == 4  # another likelihood
    assert len(calls) == 4


def test_the_noise_start_does_not_move_the_optimum(tmp_path):
    # Estimated noise stds are held at their ML values inside the solve: the stds a fit
    # starts from do not change the optimum it reaches, nor the stds it ends with.
    from thermojax.investigation._step import evaluate
    from thermojax.model._parameters_by_name import with_spec_parameters
    from thermojax.model._spec import Parameter

    spec, runs = _one_run("one_run", tmp_path, 900.0)
    got = {}
    for std in (0.5, 0.0105):  # either side of the ML stds (0.11 °C here)
        start = with_spec_parameters(spec, {f"sensors.{c}.noise": Parameter(std)
                                            for c in spec.sensor_columns})
        got[std] = evaluate(start, runs, "output_error").record
    a, b = got[0.5], got[0.0105]
    assert abs(a["nll"] - b["nll"]) < 1e-3
    for name, p in a["parameters"].items():
        if p.get("free"):
            q = b["parameters"][name]
            assert abs(p["value"] - q["value"]) <= 1e-3 * abs(p["value"]) + 0.05 * (
                p.get("std") or 0.0), name
    for c in spec.sensor_columns:  # and the stds themselves reach the same values
        sa = a["parameters"][f"sensors.{c}.noise"]["value"]
        sb = b["parameters"][f"sensors.{c}.noise"]["value"]
        assert abs(sa - sb) < 1e-4 * sa


def test_a_steps_scoring_inputs_computed_ahead_are_the_ones_taken(tmp_path, monkeypatch):
    """A candidate's score-test inputs, computed on a thread while its held-out folds
    are fitted (`score_ahead`), are those computed when its step is scored, to the last
    bit, and scoring the step takes them instead of computing them again."""
    import numpy as np

    from thermojax.investigation import _diagnose_step
    from thermojax.investigation._background import score_ahead
    from thermojax.investigation._step import evaluate

    spec, runs = _one_run("one_run", tmp_path, 900.0)
    step = evaluate(spec, runs, "kalman")
    score_ahead(step, runs, "kalman")
    ahead = step.scoring[1].result()
    again = _diagnose_step.scoring_inputs(step, runs, "kalman")
    for a, b in zip(ahead[1:5], again[1:5]):  # weights, r, J, states (None: linear)
        assert (a is None and b is None) or np.array_equal(a, b)
    monkeypatch.setattr(_diagnose_step, "scoring_inputs", lambda *a: (_ for _ in ()).throw(
        AssertionError("computed again")))
    cands = _diagnose_step.diagnose_step(step, runs, "kalman", refits=0, say=lambda m: None)
    assert cands and all(c.method == "score" for c in cands)
