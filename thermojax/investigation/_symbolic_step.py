"""The symbolic search in a step of the loop (docs/formats.md §3a, docs/extensions.md):
on the missing heat at the node that carries the most, a search over expression trees
(`discovery.symbolic_search`) whose best laws become `expression` candidates beside the
kinds of the vocabulary and the library's laws: score-tested, refitted through the
dynamics and judged by the same rule (`_diagnose_step`). The step's record gets the
front (`symbolic_search`: each law's complexity, fit and, where refitted, its evidence).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ._network_candidate import MIN_HEAT_STDS
from ..discovery import column_scales, heat_variables, learned_law, symbolic_search
from ..model.effects._base import conduction_paths


@dataclass(frozen=True)
class SearchSettings:
    """The search's budget in a step: at most `evaluations` laws fitted and `seconds`
    (None: no limit), its random choices from `random_state`, and at most `refits` of its laws
    refitted through the dynamics."""

    evaluations: int = 1500
    seconds: float | None = 60.0
    random_state: int = 0
    refits: int = 2


def _shape_text(text: str, params) -> str:
    """`text` with every parameter name replaced by `θ`: two laws of one form compare
    equal whatever their parameters are called."""
    for name in sorted(params, key=len, reverse=True):
        text = re.sub(rf"\b{re.escape(name)}\b", "θ", text)
    return text


def search_laws(step, runs, mh, roles: dict[str, str], settings: SearchSettings, say
                ) -> tuple[list[tuple], dict]:
    """Search laws of the missing heat `mh` at its largest carrier.

    **Arguments:** the fitted `step`, its `runs`, the `MissingHeat` `mh`, `roles` the
    recorded columns a law may read (name -> role; the temperatures among them are not
    read), `settings`.

    **Returns:** `(laws, entry)`: the laws to score as `(LearnedLaw, where)` (the best
    of each complexity, `SymbolicFront.leaders`: the fit to the missing heat of a model
    that has bent its parameters is no final judge, the score test through the
    dynamics ranks them), and the step record's `symbolic_search` entry (the node, those
    laws with `on_front` for the Pareto front's, the search's counts; or why no search
    ran)."""
    per_node = mh.summary()["per_node"]
    node = max(per_node, key=lambda n: per_node[n]["rms_W"])
    rms, std = per_node[node]["rms_W"], per_node[node]["median_std_W"]
    if rms < MIN_HEAT_STDS * std:
        return [], {"node": node, "verdict": (
            f"the missing heat at {node} (RMS {rms:.3g} W) is below {MIN_HEAT_STDS:g} times "
            f"its median std ({std:.3g} W): nothing for a search to fit")}
    spec = step.result.lowered_spec
    nodes = list(mh.nodes)
    paths = conduction_paths(spec)
    # its conduction neighbours, and every boundary temperature (a path the model lacks)
    linked = [b for a, b in paths if a == node] + [a for a, b in paths if b == node]
    near = linked + list(spec.boundary_columns)
    near = [b for b in dict.fromkeys(near) if b in nodes or b in runs[0].names]
    cols = {}
    for c in [b for b in near if b not in nodes] + [c for c, r in roles.items()
                                                     if r != "temperature"]:
        cols[c] = [np.asarray(t.column(c), float)[:len(ts)] for t, ts in zip(runs, mh.ts)]
    scales = column_scales({c: np.concatenate(v) for c, v in cols.items() if c not in near})
    variables = heat_variables(mh.temperatures, nodes, node, near, cols, scales)
    at = nodes.index(node)
    target = np.concatenate([h[:, at] for h in mh.heat])
    target_std = np.concatenate([h[:, at] for h in mh.heat_std])
    # the model's own conductances and capacitance at the node, refitted with any law:
    # their heat (linear in the differences, in dT/dt) is fitted beside every law and
    # reported by none
    rate = np.concatenate([np.gradient(x[:, at], ts) if len(ts) > 1 else np.zeros(len(ts))
                           for x, ts in zip(mh.temperatures, mh.ts)])
    nuisance = np.stack([rate] + [v.values for v in variables
                                  if v.kind == "difference" and v.far in linked], 1)
    say(f"symbolic search at {node} over {', '.join(v.name for v in variables)}")
    front = symbolic_search(variables, target, target_std, nuisance=nuisance,
                            evaluations=settings.evaluations, seconds=settings.seconds,
                            random_state=settings.random_state, say=say,
                            taken=(*spec.node_names, *runs[0].names))
    entry = {"node": node, **front.as_json(),
             "front": [{**law.as_json(), "on_front": law in front.front}
                       for law in front.leaders]}
    return [learned_law(law, node) for law in front.leaders], entry


def new_laws(laws, cands) -> list[tuple]:
    """The `laws` whose form and place no candidate of `cands` (the library's laws
    scored) already has."""
    have = {(tuple(c.where), _shape_text(c.expression, (c.learned.term.shape + ("c",))))
            for c in cands if c.learned is not None}
    out = []
    for law, where in laws:
        key = (tuple(where), _shape_text(law.text(where), law.term.shape + ("c",)))
        if key not in have:
            out.append((law, where))
            have.add(key)
    return out


def mark_proposed(entry: dict, refitted) -> None:
    """Each law of `entry`'s front says whether it was refitted (`proposed`)."""
    texts = [(c.expression, c.learned.term.shape + ("c",)) for c in refitted]
    for row in entry.get("front", []):
        row["proposed"] = any(_shape_text(t, p) == _shape_text(row["expression"],
                                                               tuple(row["parameters"]))
                              for t, p in texts)
    entry["proposed"] = [row["expression"] for row in entry.get("front", [])
                         if row["proposed"]]


def record_evidence(entry: dict, cands) -> None:
    """Each proposed law of the front `entry` gets the evidence of its candidate in
    `cands`: its score test, likelihood ratio, Δ BIC, held-out gain and verdict."""
    by_text = {c.expression: c for c in cands if c.learned is not None}
    for row in entry.get("front", []):
        c = by_text.get(_candidate_text(row, entry["node"], cands))
        if c is None:
            continue
        row["evidence"] = {"score_test": _finite(c.score_test), "method": c.method,
                           "likelihood_ratio": _finite(c.likelihood_ratio),
                           "delta_bic": _finite(c.delta_bic),
                           "holdout_gain": _finite(c.holdout_gain),
                           "supported": bool(c.supported), "note": c.note}


def _candidate_text(row, node, cands):
    for c in cands:
        if c.learned is not None and c.where[0] == node and _same(c, row):
            return c.expression
    return None


def _same(c, row) -> bool:
    """Whether candidate `c` is the front's law `row` (same form at its place)."""
    names = tuple(row["parameters"])
    return _shape_text(c.expression, c.learned.term.shape + ("c",)) == \
        _shape_text(row["expression"], names)


def _finite(x):
    return None if x is None or not np.isfinite(x) else float(x)
