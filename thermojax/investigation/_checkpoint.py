"""The loop's checkpoint: what an investigation depends on, by content (`_inputs`),
saved after each finished step (`_save_checkpoint`) and resumed from only for the same
inputs (`_load_checkpoint`, which otherwise says what changed); a fresh start clears
what an earlier run left (`_clear_earlier_run`). Beside it, each finished step's traces
and missing heat (`_save_step_series`, `_load_step_series`): a resumed report draws the
steps before the interruption as an uninterrupted one does."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from .._errors import InputError
from .._json import json_safe
from ..measurements._telemetry import Telemetry
from ..model._model_file import dump_model, save_model


def _inputs(spec, runs, likelihood) -> dict:
    """What an investigation's result depends on, by content: the model file's text, the
    likelihood, and per run the SHA-256 of its times and every column's name and values
    (a data file edited in place changes it; the same data moved elsewhere does not)."""
    def digest(t: Telemetry) -> str:
        h = hashlib.sha256(np.ascontiguousarray(t.ts, dtype=np.float64).tobytes())
        for name, values in t.channels.items():
            h.update(name.encode() + b"\0")
            h.update(np.ascontiguousarray(values, dtype=np.float64).tobytes())
        return h.hexdigest()

    return {"model": hashlib.sha256(dump_model(spec).encode()).hexdigest(),
            "likelihood": likelihood,
            "runs": [{"path": str(t.path), "sha256": digest(t)} for t in runs]}


def _fingerprint(inputs: dict) -> str:
    return hashlib.sha256(json.dumps(inputs, sort_keys=True).encode()).hexdigest()


def _what_changed(old: dict, new: dict) -> str:
    """The differences between two `_inputs`, in words."""
    if not old:
        return "the checkpoint was written by an earlier thermojax version"
    out = []
    if old.get("model") != new["model"]:
        out.append("the model")
    if old.get("likelihood") != new["likelihood"]:
        out.append(f"the likelihood ({old.get('likelihood')} → {new['likelihood']})")
    before, after = old.get("runs", []), new["runs"]
    if len(before) != len(after):
        out.append(f"the number of data files ({len(before)} → {len(after)})")
    else:
        out += [f"the data of {b['path']}" + (f" (now {a['path']})" if a["path"] != b["path"]
                                              else "")
                for b, a in zip(before, after) if b["sha256"] != a["sha256"]]
    return ", ".join(out) or "the inputs"


def _save_checkpoint(out: Path, inputs: dict, records, spec) -> None:
    out.mkdir(parents=True, exist_ok=True)
    i = len(records) - 1
    save_model(spec, out / f"step{i}_model.toml",
               header=f"thermojax investigate: model after step {i}")
    tmp = out / "checkpoint.json.tmp"
    tmp.write_text(json.dumps(json_safe({"fingerprint": _fingerprint(inputs), "inputs": inputs,
                                          "steps": records, "model": f"step{i}_model.toml"})))
    tmp.replace(out / "checkpoint.json")


def _load_checkpoint(out: Path, inputs: dict, spec):
    """`(records, model)` to resume from `out`'s checkpoint, `([], spec)` when there is none.
    A checkpoint of other inputs is refused (`InputError`, saying what changed): resuming
    would mix steps of two investigations."""
    from ..model._model_file import load_model

    path = out / "checkpoint.json"
    if not path.exists():
        return [], spec
    try:
        doc = json.loads(path.read_text())
        stored = doc.get("fingerprint")
    except (OSError, ValueError) as err:
        raise InputError(f"its checkpoint cannot be read ({err}); pass --restart to start "
                         "afresh (the finished steps there are discarded).",
                         file=str(path)) from None
    if stored != _fingerprint(inputs):
        raise InputError(
            f"holds an investigation of other inputs: {_what_changed(doc.get('inputs'), inputs)} "
            "changed since its steps were made. Resuming would mix the two; pass --restart to "
            "start afresh from the given model (its finished steps are discarded), or choose "
            "another --out.", file=str(out))
    try:
        return doc["steps"], load_model(out / doc["model"])
    except (OSError, ValueError, KeyError) as err:
        raise InputError(f"its checkpoint names a model that cannot be read ({err}); pass "
                         "--restart to start afresh.", file=str(path)) from None


def _atomic_npz(path: Path, arrays: dict) -> None:
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez(f, **arrays)
    tmp.replace(path)


def _save_step_series(out: Path, i: int, traces: list[dict] | None, heat) -> None:
    """Step `i`'s plot traces (`Step.traces`) and its `discovery.MissingHeat` (or None) as
    `step<i>_traces.npz` and `step<i>_heat.npz` in `out`."""
    if traces:
        _atomic_npz(out / f"step{i}_traces.npz", {
            f"{r}.{k}": np.asarray(v) for r, tr in enumerate(traces) for k, v in tr.items()})
    if heat is not None:
        arrays = {"nodes": np.asarray(heat.nodes, dtype=str),
                  "carriers": np.asarray(heat.carriers, dtype=str),
                  "intensity": np.float64(heat.intensity),
                  "log_likelihood_gain": np.float64(heat.log_likelihood_gain)}
        for r in range(len(heat.ts)):
            for k in ("ts", "heat", "heat_std", "temperatures"):
                arrays[f"{r}.{k}"] = np.asarray(getattr(heat, k)[r])
        _atomic_npz(out / f"step{i}_heat.npz", arrays)


def _runs_of(z) -> list[dict]:
    runs: list[dict] = []
    for key in z.files:
        r, _, name = key.partition(".")
        if r.isdigit():
            while len(runs) <= int(r):
                runs.append({})
            runs[int(r)][name] = z[key]
    return runs


def _load_step_series(out: Path | None, n: int) -> tuple[list, list]:
    """`(traces, heat)` per step `0 .. n-1` saved in `out` by `_save_step_series` (None
    where a step has none or its file cannot be read: its figures are then left out)."""
    from ..discovery import MissingHeat

    traces, heat = [None] * n, [None] * n
    for i in range(n if out is not None else 0):
        try:
            with np.load(out / f"step{i}_traces.npz", allow_pickle=False) as z:
                traces[i] = [{**tr, "name": str(tr["name"])} for tr in _runs_of(z)]
        except (OSError, ValueError, KeyError):
            pass
        try:
            with np.load(out / f"step{i}_heat.npz", allow_pickle=False) as z:
                runs = _runs_of(z)
                heat[i] = MissingHeat(
                    tuple(map(str, z["nodes"])), tuple(map(str, z["carriers"])),
                    float(z["intensity"]), float(z["log_likelihood_gain"]),
                    *([run[k] for run in runs] for k in ("ts", "heat", "heat_std",
                                                         "temperatures")))
        except (OSError, ValueError, KeyError):
            pass
    return traces, heat


STALE = ("checkpoint.json", "step*_*", "report.json", "report.md", "model_final.toml")


def _clear_earlier_run(out: Path) -> None:
    """Remove what an earlier investigation left in `out` (its steps, checkpoint, report),
    so a fresh start leaves nothing of it beside the new report."""
    for pattern in STALE:
        for f in out.glob(pattern):
            if f.is_file():
                f.unlink()
