"""Work the investigation does side by side: candidate refits on threads, figures drawn
ahead. Each must give exactly what doing one thing at a time gives."""

from __future__ import annotations

import os
import threading
import time

import jax
import numpy as np
import pytest

import thermojax
from thermojax import parse_model
from thermojax.investigation import _investigate as inv
from thermojax.investigation import _plots_ahead
from thermojax.investigation._candidates import Candidate, enumerate_places, new_effect
from thermojax.investigation._plots_ahead import PlotsAhead
from thermojax.model._model import ThermalModel
from thermojax.model.effects import KINDS, lower_effects

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
        tried, waves = [], []

        def wave(batch):
            waves.append(len(batch))
            tried.extend(c.where for c in batch)
            return [succeeds[c.where] for c in batch]

        inv.refit_best(cands, refits, wave)
        assert tried == _one_at_a_time(cands, refits, succeeds), trial
        assert all(w <= refits for w in waves)


def test_one_structure_is_refitted_on_one_thread_in_order(monkeypatch):
    """Candidates of one model structure (an offset at any sensor) share state kept per
    structure: one thread takes them in order; other structures (a radiation at each
    place) run on other threads meanwhile."""
    seen = []
    lock = threading.Lock()

    def fake_refit(c, *args):
        with lock:
            seen.append((c.kind, c.where, threading.current_thread().name))
        time.sleep(0.05)
        return c.where != ("n2",)  # one failure, reported for its own candidate

    monkeypatch.setattr(inv, "_refit", fake_refit)
    monkeypatch.setattr(os, "cpu_count", lambda: 8)
    cands = _cands(["radiation", "sensor_offset", "radiation", "sensor_offset", "extra_node"])
    ok = inv._refit_side_by_side(cands, "args")
    assert ok == [True, True, False, True, True]
    offsets = [(w, t) for k, w, t in seen if k == "sensor_offset"]
    assert [w for w, _ in offsets] == [("n1",), ("n3",)]
    assert len({t for _, t in offsets}) == 1
    assert len({t for _, _, t in seen}) == 4  # four structures, four threads
    # one processor: no thread at all, the same answers
    seen.clear()
    monkeypatch.setattr(os, "cpu_count", lambda: 1)
    assert inv._refit_side_by_side(cands, "args") == ok
    assert {t for _, _, t in seen} == {threading.current_thread().name}


def test_place_is_data_says_which_kinds_share_a_structure():
    """The grouping above relies on `place_is_data`: a kind added at two places gives one
    model structure (pytree structure, static fields included) exactly when it says so."""
    spec = parse_model(g.dump_toml(g.load_case("heat_source")["believed"]))
    lowered = lower_effects(spec).spec
    places = enumerate_places(spec, lowered, {"P_aux": "power", "T_aux": "temperature"})
    checked = set()
    for kind, impl in KINDS.items():
        where = [w for k, w in places if k == kind][:2]
        if len(where) < 2:
            continue
        structures = []
        for w in where:
            ext = spec.replace(effects=spec.effects + (new_effect(spec, lowered, kind, w, {}),))
            structures.append(jax.tree.structure(ThermalModel.from_spec(
                lower_effects(ext).spec)))
        assert (structures[0] == structures[1]) == impl.place_is_data, kind
        checked.add(kind)
    assert checked == set(KINDS) - {"viscoelastic"}  # a bias term, not the thermal model


@pytest.mark.slow
def test_refits_side_by_side_give_the_one_at_a_time_answer(tmp_path, monkeypatch):
    """A real step: four candidates of three kinds refitted on one thread and on several
    give identical candidates, to the last bit."""
    files = g.write_case("sensor_offset", tmp_path / "data", seed=0, horizon_s=900.0)
    spec = thermojax.load_model(files["model"])
    runs = [thermojax.read_telemetry(p) for p in files["data"]]
    reports = []
    for cpus in (1, 4):
        monkeypatch.setattr(os, "cpu_count", lambda cpus=cpus: cpus)
        reports.append(thermojax.investigate(spec, runs, max_steps=1, refits=4,
                                             holdout_check=False))
    steps = [r["steps"][0]["candidates"] for r in reports]
    refitted = [c for c in steps[0] if c["method"] == "refit"]
    assert len(refitted) == 4
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
