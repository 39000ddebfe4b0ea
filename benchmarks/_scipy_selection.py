"""The SciPy peer of the loop: a forward selection scripted as a CTSM-R user scripts it,
on the NumPy filter of `_numpy_kalman.py` (`loop_scaling.py`). Nothing here imports
thermojax.

From a model TOML (read with `tomllib`), each step fits every extension of the current
model by `fit_lbfgsb` (L-BFGS-B, finite-difference gradients; restarted where it stops
until a restart gains under 0.01), warm-started at the
current model's fitted values, and keeps the one of largest likelihood ratio if its
p-value (χ², the parameters added) is under 0.01. The extensions are the hand-written
ones of a building study: a mass that takes a heat input from a node (a heater's
medium), a mass that takes a boundary from a node (an envelope), a dead-end mass on a
node, and a lag on a sensor. Each new node starts at a time constant of an hour (a
sensor's at one sample period) with its parent's process noise.
"""

from __future__ import annotations

import copy
import time

import numpy as np
import scipy.stats

import _numpy_kalman as numpy_kalman  # beside this script

P_VALUE = 0.01
TAU_S = 3600.0
# −log L: L-BFGS-B is started again where it stopped until a run gains less (from a
# model file's values its first run can stop at a ridge: on the linear building's 2,000
# samples at −515.6, where the second reaches thermojax's optimum, −1541.89)
RESTART_GAIN = 0.01


def _value(e):
    return e["value"] if isinstance(e, dict) else e


def _node(toml, name):
    return next(n for n in toml["nodes"] if n["name"] == name)


def _new_node(toml, name, parent, capacitance, conductance):
    """A node `name` of `capacitance` with `parent`'s process noise, linked to it."""
    toml["nodes"].append({"name": name, "capacitance": capacitance,
                          "process_noise": _value(parent.get("process_noise", 0.0))})
    toml.setdefault("links", []).append({"between": [parent["name"], name],
                                         "conductance": conductance})


def extensions(toml: dict, dt: float) -> list[tuple[str, dict]]:
    """`(label, extended TOML)` for every hand-written extension of `toml`."""
    out = []
    names = {n["name"] for n in toml["nodes"]}
    for k, h in enumerate(toml.get("heat_inputs", [])):
        name = f"m_{h['input']}"
        if name in names:
            continue
        t = copy.deepcopy(toml)
        parent = _node(t, h["node"])
        c = _value(parent["capacitance"]) / 4
        _new_node(t, name, parent, c, c / TAU_S)
        t["heat_inputs"][k]["node"] = name
        out.append((f"mass taking {h['input']} from {h['node']}", t))
    for k, b in enumerate(toml.get("boundaries", [])):
        name = f"m_{b['input']}"
        if name in names:
            continue
        t = copy.deepcopy(toml)
        parent = _node(t, b["node"])
        g = _value(b["conductance"])
        _new_node(t, name, parent, 10 * _value(parent["capacitance"]), 2 * g)
        t["boundaries"][k] = {**b, "node": name, "conductance": 2 * g}
        out.append((f"mass taking {b['input']} from {b['node']}", t))
    for n in toml["nodes"]:
        name = f"m_{n['name']}"
        if name in names or n["name"].startswith("lag_"):
            continue
        t = copy.deepcopy(toml)
        _new_node(t, name, _node(t, n["name"]), _value(n["capacitance"]),
                  _value(n["capacitance"]) / TAU_S)
        out.append((f"dead-end mass on {n['name']}", t))
    for k, s in enumerate(toml["sensors"]):
        name = f"lag_{s['column']}"
        if name in names:
            continue
        t = copy.deepcopy(toml)
        c = _value(_node(t, s["node"])["capacitance"]) / 100
        _new_node(t, name, _node(t, s["node"]), c, c / dt)
        t["sensors"][k]["node"] = name
        out.append((f"lag on {s['column']}", t))
    return out


def with_values(toml: dict, net: numpy_kalman.Network, v: np.ndarray) -> dict:
    """`toml` with its free values replaced by the physical values `v` (`net.full`)."""
    t = copy.deepcopy(toml)
    entries = ([(n, "capacitance") for n in t["nodes"]]
               + [(k, "conductance") for k in t.get("links", [])]
               + [(b, "conductance") for b in t.get("boundaries", [])]
               + [(h, "gain") for h in t.get("heat_inputs", [])]
               + [(s, "noise") for s in t["sensors"]]
               + [(n, "process_noise") for n in t["nodes"]]
               + [(t["nodes"][i], "initial") for i in net.initial])
    for (owner, key), value, free in zip(entries, v, net.free):
        if free:
            owner[key] = float(value)
    return t


def forward_selection(toml: dict, U, Y, dt: float, budget: float, say=print) -> dict:
    """The selection from `toml` on inputs `U` (T, inputs in the TOML's order) and readings
    `Y` (T, sensors), stopped after `budget` s (a fit running then stops there).

    **Returns:** `{"steps": [(label, −log L, seconds)], "fits": n, "wall": s,
    "stopped": why}`: the start and every extension kept."""
    t0 = time.perf_counter()
    left = lambda: budget - (time.perf_counter() - t0)  # noqa: E731

    def fitted(model):  # L-BFGS-B restarted where it stopped until it gains < RESTART_GAIN
        got, runs = {"nll": np.inf, "nit": 0, "model": model, "runs": 0}, 0
        while left() > 0:
            net = numpy_kalman.Network(model)
            again = numpy_kalman.fit_lbfgsb(net, U, Y, dt, budget=left(), target=-np.inf)
            runs += 1
            model = with_values(model, net, net.full(np.asarray(again["x"])))
            gain = got["nll"] - again["nll"]
            got = {**again, "model": model, "runs": runs, "nit": again["nit"] + got["nit"]}
            if gain < RESTART_GAIN:
                break
        got["success"] = left() > 0
        return got

    start = fitted(toml)
    fits = 1
    steps = [("start", start["nll"], time.perf_counter() - t0)]
    say(f"  SciPy peer: start −log L {start['nll']:.1f} ({time.perf_counter() - t0:.0f} s, "
        f"{start['nit']} iterations in {start['runs']} L-BFGS-B runs)")
    current, stopped = start, "budget" if not start["success"] else ""
    while not stopped:
        best = None
        n_params = int(numpy_kalman.Network(current["model"]).free.sum())
        for label, model in extensions(current["model"], dt):
            if left() <= 0:
                stopped = "budget"
                break
            got = fitted(model)
            fits += 1
            say(f"    {label}: −log L {got['nll']:.1f}" + ("" if got["success"] else
                                                          " (stopped at the budget)"))
            if not got["success"]:
                stopped = "budget"
                break
            got["label"] = label
            got["added"] = int(numpy_kalman.Network(model).free.sum()) - n_params
            if best is None or got["nll"] < best["nll"]:
                best = got
        if stopped:
            break
        if best is None:
            stopped = "no extension left"
            break
        lr = 2 * (current["nll"] - best["nll"])
        p = float(scipy.stats.chi2.sf(max(lr, 0.0), best["added"]))
        if p >= P_VALUE:
            stopped = f"no extension supported (best {best['label']}, p {p:.2g})"
            break
        current = best
        steps.append((best["label"], best["nll"], time.perf_counter() - t0))
        say(f"  SciPy peer: + {best['label']}: −log L {best['nll']:.1f} "
            f"(at {steps[-1][2]:.0f} s)")
    return {"steps": steps, "fits": fits, "wall": time.perf_counter() - t0,
            "stopped": stopped}

