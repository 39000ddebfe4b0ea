"""Work the investigation does side by side: candidate refits on threads, figures drawn
ahead. Each must give exactly what doing one thing at a time gives."""

from __future__ import annotations

import os
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest

import thermojax
from thermojax.investigation import _refits
from thermojax.investigation import _plots_ahead
from thermojax.investigation._candidates import Candidate
from thermojax.investigation._plots_ahead import PlotsAhead

from hidden import generator as g


def _cands(kinds):
    return [Candidate(k, (f"n{i}",), score=100.0 - i, p_value=0.0)
            for i, k in enumerate(kinds)]


def _one_at_a_time(cands, refits, succeeds):
    """The rule written out: in order, every scored candidate with a positive score,
    until `refits` succeeded or `2 refits` were tried."""
    tried, done = [], 0
    for c in cands:
        if done >= refits or len(tried) >= 2 * refits:
            break
        if c.method != "score" or not c.score > 0:
            continue
        tried.append(c.where)
        done += succeeds[c.where]
    return tried


def test_waves_try_the_candidates_one_at_a_time_would_try():
    rng = np.random.default_rng(0)
    for trial in range(200):
        n = int(rng.integers(0, 12))
        cands = _cands(rng.choice(["radiation", "sensor_offset", "extra_node"], n))
        for c in cands:  # some were not score-tested, or scored nothing
            if rng.random() < 0.15:
                c.method = "refit"
            elif rng.random() < 0.15:
                c.score = 0.0
        succeeds = {c.where: bool(rng.random() < 0.6) for c in cands}
        refits = int(rng.integers(0, 5))
        # a learned law refitted beside the kinds, whatever its rank; its outcome
        # does not count (and a law scored nothing, or refitted already, is not refitted)
        law = Candidate("expression", ("law",), score=float(rng.choice([0.0, 50.0])),
                        p_value=0.0)
        law.method = "refit" if rng.random() < 0.15 else "score"
        beside = [law] if rng.random() < 0.5 else []
        succeeds[law.where] = bool(rng.random() < 0.5)
        tried, waves = [], []

        def wave(batch):
            waves.append([c.where for c in batch])
            tried.extend(c.where for c in batch if c is not law)
            return [succeeds[c.where] for c in batch]

        _refits.refit_best(cands, refits, wave, beside=beside)
        assert tried == _one_at_a_time(cands, refits, succeeds), trial
        assert all(len(w) <= refits + (w[:1] == [law.where]) for w in waves)
        law_refitted = bool(beside) and law.method == "score" and law.score > 0
        assert [w for w in waves if law.where in w] == (waves[:1] if law_refitted else [])
        assert all(w.index(law.where) == 0 for w in waves if law.where in w)


@pytest.mark.parametrize("cpus", [1, 8])
def test_every_start_of_every_candidate_is_fitted_side_by_side(monkeypatch, cpus):
    """A wave's fits (each candidate's starts) all go to the threads, first starts
    before later ones, the later starts of the candidate with the most first; each
    candidate concludes from its own fits in start order, a failed fit passed on as its
    exception (the loop goes on)."""
    submitted, lock = [], threading.Lock()

    def fake_starts(c, step, new_columns, initial, runs=(), nested=False):
        n = {"radiation": 1, "capacitance_temperature": 3}.get(c.kind, 2)
        return [(None, f"start {k}", f"{c.where[0]}:{k}") for k in range(n)]

    def fake_evaluate(model, runs, likelihood, nested_nll, polish, restart_unconverged):
        assert nested_nll == -12.5  # every start knows the likelihood it can reach
        assert polish  # a kind's refit is polished (a learned law's is not)
        with lock:
            submitted.append(model)
        time.sleep(0.02)
        if model == "n2:1":
            raise FloatingPointError("went non-finite")
        return f"fit of {model}"

    concluded = {}

    def fake_refit(c, step, runs, new_columns, fits, say, white_p=0.01):
        concluded[c.where[0]] = fits
        return not any(isinstance(f, Exception) for _, _, f in fits)

    monkeypatch.setattr(_refits, "_refit_starts", fake_starts)
    monkeypatch.setattr(_refits, "evaluate", fake_evaluate)
    monkeypatch.setattr(_refits, "_refit", fake_refit)
    monkeypatch.setattr(_refits, "_needs_retry", lambda fits, step: False)
    monkeypatch.setattr(os, "cpu_count", lambda: cpus)
    cands = _cands(["radiation", "sensor_offset", "extra_node", "capacitance_temperature"])
    nested = SimpleNamespace(thermal_nll=-12.5)  # the step the candidates extend
    ok = _refits._refit_side_by_side(cands, nested, [], "output_error", set(), None,
                                 lambda m: None)
    assert ok == [True, True, False, True]
    assert sorted(submitted) == ["n0:0", "n1:0", "n1:1", "n2:0", "n2:1", "n3:0", "n3:1",
                                 "n3:2"]
    if cpus == 1:
        assert submitted == ["n0:0", "n1:0", "n2:0", "n3:0", "n3:1", "n3:2", "n1:1", "n2:1"]
    assert concluded["n3"] == [(None, f"start {k}", f"fit of n3:{k}") for k in range(3)]
    assert concluded["n1"] == [(None, "start 0", "fit of n1:0"),
                               (None, "start 1", "fit of n1:1")]
    assert concluded["n2"][0] == (None, "start 0", "fit of n2:0")
    assert isinstance(concluded["n2"][1][2], FloatingPointError)


def test_a_learned_laws_refit_is_not_polished_and_a_kinds_is(monkeypatch):
    """Every start of a learned law (its retry from the nested optimum too) is fitted
    without the Kalman polish; every start of a kind with it."""
    from thermojax.discovery import LIBRARY, LearnedLaw

    seen = []

    def fake_starts(c, step, new_columns, initial, runs=(), nested=False):
        return [(None, f"start {k}", f"{c.where[0]}:{k}:{nested}") for k in range(2)]

    def fake_evaluate(model, runs, likelihood, nested_nll, polish, restart_unconverged):
        seen.append((model, polish))
        return "fit"

    monkeypatch.setattr(_refits, "_refit_starts", fake_starts)
    monkeypatch.setattr(_refits, "evaluate", fake_evaluate)
    monkeypatch.setattr(_refits, "_refit", lambda c, step, runs, nc, fits, say, w=0.01: True)
    monkeypatch.setattr(_refits, "_needs_retry", lambda fits, step: True)  # retried too
    law = Candidate("expression", ("n1",), 99.0, 0.0, learned=LearnedLaw(LIBRARY[0], None))
    _refits._refit_side_by_side([_cands(["radiation"])[0], law], SimpleNamespace(thermal_nll=0.0),
                            [], "kalman", set(), None, lambda m: None)
    assert sorted(seen) == sorted((f"{n}:{k}:{nested}", n == "n0") for n in ("n0", "n1")
                                  for k in range(2) for nested in (False, True))


def test_only_a_holds_first_start_is_restarted_from_output_error(monkeypatch):
    """A refit's first start of each hold, when its Kalman fit does not converge, is
    fitted again from the output-error fit; its later starts (the user's values, the
    score's τ) are not: each is one more start. The nested retry is a first start."""
    seen = {}

    def fake_starts(c, step, new_columns, initial, runs=(), nested=False):
        if nested:
            return [("zoh", "nested", f"{c.where[0]}:nested")]
        return [(h, s, f"{c.where[0]}:{h}:{s}") for h in ("zoh", "foh")
                for s in ("fitted", "user", "tau")]

    def fake_evaluate(model, runs, likelihood, nested_nll, polish, restart_unconverged):
        seen[model] = restart_unconverged
        return "fit"

    monkeypatch.setattr(_refits, "_refit_starts", fake_starts)
    monkeypatch.setattr(_refits, "evaluate", fake_evaluate)
    monkeypatch.setattr(_refits, "_refit", lambda c, step, runs, nc, fits, say, w=0.01: True)
    monkeypatch.setattr(_refits, "_needs_retry", lambda fits, step: True)
    _refits._refit_side_by_side(_cands(["radiation"]), SimpleNamespace(thermal_nll=0.0), [],
                            "kalman", set(), None, lambda m: None)
    assert seen == {f"n0:{h}:{s}": s == "fitted" for h in ("zoh", "foh")
                    for s in ("fitted", "user", "tau")} | {"n0:nested": True}


@pytest.mark.slow
def test_refits_side_by_side_give_the_one_at_a_time_answer(tmp_path, monkeypatch):
    """A real step: four candidates of three kinds refitted, and the chosen one's
    held-out folds fitted, on one thread and on several give identical candidates, to
    the last bit."""
    files = g.write_case("sensor_offset", tmp_path / "data", seed=0, horizon_s=900.0)
    spec = thermojax.load_model(files["model"])
    runs = [thermojax.read_telemetry(p) for p in files["data"]]
    reports = []
    for cpus in (1, 4):
        monkeypatch.setattr(os, "cpu_count", lambda cpus=cpus: cpus)
        reports.append(thermojax.investigate(spec, runs, max_steps=1, refits=4))
    steps = [r["steps"][0]["candidates"] for r in reports]
    refitted = [c for c in steps[0] if c["method"] == "refit"]
    # the four best kinds, and the best learned law (refitted beside them)
    assert len([c for c in refitted if c["kind"] != "expression"]) == 4
    assert len([c for c in refitted if c["kind"] == "expression"]) <= 1
    assert steps[0] == steps[1]
    assert reports[0]["steps"][1]["parameters"] == reports[1]["steps"][1]["parameters"]


def _traces(n_runs=2, n=400):
    rng = np.random.default_rng(1)
    ts = np.arange(n) * 10.0
    out = []
    for r in range(n_runs):
        chamber = 20.0 + 0.01 * ts
        power = np.where(ts > ts[n // 2], 2.0, 0.0)
        pred = np.column_stack([chamber + 1.0])
        out.append({"name": f"run{r}", "ts": ts, "predicted": pred,
                    "measured": pred + 0.01 * rng.standard_normal((n, 1)),
                    "inputs": np.column_stack([chamber, power])})
    return out


def test_figures_drawn_ahead_are_reused_or_redrawn(tmp_path, monkeypatch):
    calls = []
    real = _plots_ahead.diagnostic_plots

    def counted(out_dir, prefix, columns, runs, input_names, *args, **kwargs):
        calls.append((prefix, tuple(input_names), threading.current_thread().name))
        return real(out_dir, prefix, columns, runs, input_names, *args, **kwargs)

    monkeypatch.setattr(_plots_ahead, "diagnostic_plots", counted)
    traces = _traces()
    plots = PlotsAhead()
    try:
        plots.ahead(tmp_path, "step0", ["T_die"], traces, ["T_chamber", "P_die"],
                    ["T_chamber"], title="Step 0", time_scale=100.0)
        # the caller may change the traces afterwards: the queued job drew its own copy
        for tr in traces:
            tr["inputs"] = tr["inputs"][:, :1]
        # the same figures: the queued job's, not drawn again
        names = plots.draw(tmp_path, "step0", ["T_die"], traces, ["T_chamber", "P_die"],
                           ["T_chamber"], title="Step 0", time_scale=100.0)
        assert len(calls) == 1 and calls[0][2] != threading.current_thread().name
        assert set(names) == {"fit", "acf", "xcorr", "periodogram", "phases"}
        assert all((tmp_path / f).stat().st_size > 0 for f in names.values())
        # other inputs (the final model reads fewer columns): drawn again, after
        plots.draw(tmp_path, "step0", ["T_die"], traces, ["T_chamber"], ["T_chamber"],
                   title="Step 0", time_scale=100.0)
        assert [c[1] for c in calls] == [("T_chamber", "P_die"), ("T_chamber",)]
        # other traces with equal arguments: drawn again too
        plots.draw(tmp_path, "step0", ["T_die"], _traces(), ["T_chamber", "P_die"],
                   ["T_chamber"], title="Step 0", time_scale=100.0)
        assert len(calls) == 3
    finally:
        plots.close()


def test_figures_of_a_candidate_are_staged_until_drawn(tmp_path):
    """A candidate's figures (its step may never be taken) are drawn into a hidden
    folder: moved into place when the report asks for them, removed at close if not."""
    kept, dropped = _traces(), _traces()
    plots = PlotsAhead()
    try:
        for prefix, traces in (("step1", kept), ("step2", dropped)):
            plots.ahead(tmp_path, prefix, ["T_die"], traces, ["T_chamber", "P_die"],
                        ["T_chamber"], staged=True, title="Step 1", time_scale=100.0)
        plots.ahead(tmp_path, "step1", ["T_die"], kept, ["T_chamber", "P_die"],
                    ["T_chamber"], title="Step 1", time_scale=100.0)  # queued already
        assert len(plots._jobs) == 2
        names = plots.draw(tmp_path, "step1", ["T_die"], kept, ["T_chamber", "P_die"],
                           ["T_chamber"], title="Step 1", time_scale=100.0)
        assert sorted(p.name for p in tmp_path.glob("*.png")) == sorted(names.values())
    finally:
        plots.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(names.values())
