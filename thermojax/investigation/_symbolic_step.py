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
from types import SimpleNamespace

import numpy as np

from ._network_candidate import MIN_HEAT_STDS
from ..discovery import column_scales, heat_variables, learned_law, symbolic_search
from ..model._expression import evaluate_numpy, names, parse, resolve
from ..model.effects._base import conduction_paths


#: A refining search's laws refitted: the simplest within this share of the lowest cost
#: (`SymbolicFront.best`), the knee and the next such laws.
REFINE_ADEQUATE = 0.3


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
    node = _carrier(mh)
    rms, std = _heat_size(mh, node)
    if rms < MIN_HEAT_STDS * std:
        return [], {"node": node, "verdict": (
            f"the missing heat at {node} (RMS {rms:.3g} W) is below {MIN_HEAT_STDS:g} times "
            f"its median std ({std:.3g} W): nothing for a search to fit")}
    variables, target, target_std, nuisance, taken = _search_inputs(step, runs, mh, node,
                                                                   roles)
    say(f"symbolic search at {node} over {', '.join(v.name for v in variables)}")
    front = symbolic_search(variables, target, target_std, nuisance=nuisance,
                            evaluations=settings.evaluations, seconds=settings.seconds,
                            random_state=settings.random_state, say=say, taken=taken)
    entry = {"node": node, **front.as_json(),
             "front": [{**law.as_json(), "on_front": law in front.front}
                       for law in front.leaders]}
    return [learned_law(law, node) for law in front.leaders], entry


def refine_laws(step, runs, mh, roles: dict[str, str], settings: SearchSettings, say
                ) -> tuple[list[tuple], dict | None]:
    """Search again around the laws the model already holds at a node (docs/extensions.md,
    "refining a law").

    A law added at an earlier step that leaves structured missing heat at its node is
    an approximation of the truth's law; the next law added beside it would only explain
    the approximation's error away. Here the search's target is the heat those laws
    carry into the node (at their fitted values, on the smoothed temperatures) plus the
    missing heat, over the same variables and the columns the laws read: its best laws
    (`SymbolicFront.best`) are candidates that replace those laws, refitted through the
    dynamics and judged beside every other candidate.

    **Returns:** `(laws, entry)`: `(LearnedLaw, where, replaces, found)` per law, where
    `replaces` are the indices in `step.spec.effects` of the laws it would replace and
    `found` its `FoundLaw`; the record's `refinement` entry (the laws replaced, the
    front), or `([], None)` where the model holds no law. The node is the law-holding
    node that carries the most missing heat (any law-holding node where none carries
    any)."""
    at_nodes = [e.where[0] for e in step.spec.effects if e.kind == "expression" and e.where]
    if not at_nodes:
        return [], None
    # the carrier of the most missing heat where it holds a law; else the law's node,
    # whose law may have taken heat that belongs to another form (a node beside it then
    # carries what the law's form cannot)
    per_node = mh.summary()["per_node"]
    node = max(dict.fromkeys(at_nodes), key=lambda n: per_node.get(n, {}).get("rms_W", 0.0))
    held = [(i, e) for i, e in enumerate(step.spec.effects)
            if e.kind == "expression" and e.where and e.where[0] == node]
    read = {n: "law" for _, e in held for n in names(parse(e.expression))
            if n not in mh.nodes and n not in e.parameters and n in runs[0].names}
    variables, target, target_std, nuisance, taken = _search_inputs(
        step, runs, mh, node, {**roles, **read})
    carried = sum(_law_heat(e, mh, runs) for _, e in held)
    texts = [e.expression for _, e in held]
    say(f"refining the law(s) at {node} ({'; '.join(texts)}): a search over the heat they "
        "carry plus the missing heat")
    front = symbolic_search(variables, target + carried, target_std, nuisance=nuisance,
                            evaluations=settings.evaluations, seconds=settings.seconds,
                            random_state=settings.random_state, say=say, taken=taken)
    # the target is a reconstruction: fits within `REFINE_ADEQUATE` of the best are
    # told apart by the dynamics, not by it (on a sum of an Arrhenius law and a fan's
    # losses the truth's form was 18 % above the front's lowest cost)
    picked = front.best(settings.refits + 1, adequate=REFINE_ADEQUATE)
    entry = {"node": node, "replaces": texts, **front.as_json(),
             "front": [{**law.as_json(), "picked": law in picked} for law in front.front]}
    replaces = tuple(i for i, _ in held)
    return [(*learned_law(law, node), replaces, law) for law in picked], entry


def search_at_file_values(step, runs, initial, roles: dict[str, str],
                          settings: SearchSettings, say) -> tuple[list[tuple], dict | None]:
    """Search laws of the missing heat of the step's structure at the file's values.

    A fitted model has bent its parameters to mimic what it lacks, and its missing heat
    is what is left of the law after that: on a chamber-to-board law `h ΔT / (1 + s
    |ΔT|)` at an unmeasured board, the fitted model's missing heat there correlated
    -0.24 to 0.76 with the law, the file's values' 0.97 to 0.997 (slope 0.98). So the
    search also runs on the missing heat of `initial`'s values (the laws the loop added
    at their fitted values), with the node's linear paths fitted beside every law but
    not its capacitance heat: at the file's values a law's own heat follows the ramps
    as `dT/dt` does, and fitted beside it `dT/dt` took the law away (R² 0.001 for the
    truth's path, 0.99 without). Its best laws (`SymbolicFront.best` within
    `REFINE_ADEQUATE`) are refitted from the file's values whatever their score test
    at the bent model says.

    **Returns:** `(laws, entry)`: `(LearnedLaw, where, found)` per law, and the record's
    `at_file_values` entry (`node`, the front with `picked`), or `([], None)` where the
    missing heat there is too small or no reconstruction ran."""
    from ..discovery import missing_heat
    from ..fitting._fit import fit
    from ..model._parameters_by_name import spec_parameters, with_spec_parameters
    from ._step import _experiments

    spec = with_spec_parameters(step.spec, spec_parameters(initial))
    at_file = fit(spec, _experiments(spec, runs), max_steps=1, restart_plateaus=False,
                  polish=False, restart_unconverged=False)
    mh = missing_heat(at_file)
    if not mh.carriers:
        return [], None
    node = _carrier(mh)
    rms, std = _heat_size(mh, node)
    if rms < MIN_HEAT_STDS * std:
        return [], None
    at = SimpleNamespace(spec=at_file.spec, result=at_file)
    variables, target, target_std, nuisance, taken = _search_inputs(at, runs, mh, node,
                                                                   roles)
    say(f"symbolic search at {node} on the missing heat at the file's values")
    front = symbolic_search(variables, target, target_std, nuisance=nuisance[:, 1:],
                            evaluations=settings.evaluations, seconds=settings.seconds,
                            random_state=settings.random_state, say=say, taken=taken)
    picked = front.best(settings.refits, adequate=REFINE_ADEQUATE)
    entry = {"node": node, **front.as_json(),
             "front": [{**law.as_json(), "picked": law in picked} for law in front.front]}
    return [(*learned_law(law, node), law) for law in picked], entry


def _carrier(mh) -> str:
    """The node of `mh` whose missing heat has the largest RMS."""
    per_node = mh.summary()["per_node"]
    return max(per_node, key=lambda n: per_node[n]["rms_W"])


def _heat_size(mh, node) -> tuple[float, float]:
    """`(RMS, median std)` of the missing heat at `node`, W."""
    row = mh.summary()["per_node"][node]
    return row["rms_W"], row["median_std_W"]


def _search_inputs(step, runs, mh, node: str, roles: dict[str, str]) -> tuple:
    """`(variables, target, target_std, nuisance, taken)` of a search at `node`: the
    grammar's variables (the node's temperature, its differences to its conduction
    neighbours and to every boundary temperature, the columns of `roles` that are not
    temperatures), the missing heat there and its std (W, runs joined), the nuisance
    heats every law is fitted beside, and the names a parameter must not take."""
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
    return variables, target, target_std, nuisance, (*spec.node_names, *runs[0].names)


def _law_heat(effect, mh, runs) -> np.ndarray:
    """The heat (W) the `expression` effect carries into its node `where[0]` at its
    values, on the smoothed temperatures of `mh` and the runs' columns (runs joined)."""
    tree = parse(effect.expression)
    params = tuple(effect.parameters)
    cols = tuple(n for n in names(tree) if n not in mh.nodes and n not in params)
    program = resolve(tree, tuple(mh.nodes), cols, params)
    values = [effect.parameters[k].value for k in params]
    out = []
    for T, t, ts in zip(mh.temperatures, runs, mh.ts):
        u = np.stack([np.asarray(t.column(c), float)[:len(ts)] for c in cols], 1) if cols \
            else np.zeros((len(ts), 0))
        out.append(np.broadcast_to(evaluate_numpy(program, T, u, values), (len(ts),)))
    return np.concatenate(out)


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
    """Each proposed law of the front `entry` (and of the fronts of its searches at the
    file's values and around the held laws) gets
    the evidence of its candidate in `cands`: its score test, likelihood ratio, Δ BIC,
    held-out gain and verdict."""
    fronts = [(entry, False)]
    if "front" in entry.get("at_file_values", {}):
        fronts.append((entry["at_file_values"], False))
    if "front" in entry.get("refinement", {}):
        fronts.append((entry["refinement"], True))
    for front, refines in fronts:
        for row in front.get("front", []):
            c = _candidate(row, front["node"], cands, refines)
            if c is None:
                continue
            row["evidence"] = {"score_test": _finite(c.score_test), "method": c.method,
                               "likelihood_ratio": _finite(c.likelihood_ratio),
                               "delta_bic": _finite(c.delta_bic),
                               "holdout_gain": _finite(c.holdout_gain),
                               "supported": bool(c.supported), "note": c.note}


def _candidate(row, node, cands, refines: bool):
    """The candidate of `cands` that is the front's law `row` at `node`: one that
    replaces the held laws (`refines`) or one that is added beside them."""
    return next((c for c in cands if c.learned is not None and c.where[0] == node
                 and bool(c.replaces) == refines and _same(c, row)), None)


def _same(c, row) -> bool:
    """Whether candidate `c` is the front's law `row` (same form at its place)."""
    names = tuple(row["parameters"])
    return _shape_text(c.expression, c.learned.term.shape + ("c",)) == \
        _shape_text(row["expression"], names)


def _finite(x):
    return None if x is None or not np.isfinite(x) else float(x)
