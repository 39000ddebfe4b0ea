"""One step of diagnosis (`diagnose_step`): every candidate effect for a fitted model,
score-tested from its fit (`scoring_inputs`; under the Kalman likelihood on the
innovations, `innovation_directions`), viscoelastic ones refitted on their bias channel,
the best thermal ones and a learned law refitted (`_refits`, `_laws_screen`), then
judged by the selection rule (`_selection`) and the physical range."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ._candidates import Candidate, column_role, enumerate_places, score_candidates
from ._laws_screen import _law_adds_nothing, _law_outranked, _learned_places
from ._phase_times import phase
from ._physical_range import data_span, prefer_physics, reject_unphysical
from ._refit_verdicts import duplicate_reason, rule_p_value, sample_period
from ._refits import _refit_side_by_side, refit_best, refittable
from ._selection import judge, prefer_simpler_laws, prefer_vocabulary
from ._separation import separation_advice
from ._step import Step, _bias_runs, _experiments
from ._symbolic_step import SearchSettings, mark_proposed, new_laws, refine_laws, \
    search_at_file_values, search_laws
from ..discovery import column_scales
from ..fitting._bias import viscoelastic_candidate
from ..fitting._fit import FitResult, output_error_at
from ..fitting._residual_analysis import ljung_box, long_run_variance_ratio
from ..measurements._telemetry import Telemetry
from ..model._spec import ModelSpec


def unused_columns(spec: ModelSpec, runs: list[Telemetry]) -> dict[str, str]:
    """Data columns every run holds that the model does not use, with a role guess."""
    used = set(spec.input_columns) | set(spec.sensor_columns) | {b.column for b in spec.biases}
    common = set(runs[0].names)
    for t in runs[1:]:
        common &= set(t.names)
    out = {}
    for c in runs[0].names:
        if c in common and c not in used and c != "time_s":
            values = np.concatenate([t.column(c) for t in runs])
            if np.all(np.isfinite(values)):
                out[c] = column_role(c, values)
    return out


def _padded_columns(runs: list[Telemetry], names, T: int) -> dict[str, np.ndarray]:
    """Data columns `names` as (runs, T) arrays on the padded time grid (each run's last
    value repeated)."""
    columns = {}
    for c in names:
        arr = np.zeros((len(runs), T))
        for i, t in enumerate(runs):
            v = t.column(c)
            arr[i, :len(v)] = v
            arr[i, len(v):] = v[-1]
        columns[c] = arr
    return columns


def _viscoelastic_candidates(step: Step, runs: list[Telemetry], places,
                             white_p: float = 0.01) -> list[Candidate]:
    """Every `viscoelastic` place of `places`, refitted directly on its bias channel
    (linear least squares and a τ search: cheap). A failed fit is reported, not raised."""
    spec, result = step.spec, step.result
    node_names = list(result.lowered_spec.node_names)
    n = step.record["n_samples"]
    out = []
    for kind, where in places:
        if kind != "viscoelastic":
            continue
        try:
            bias = next(b for b in spec.biases if b.column == where[1])
            bias_runs, rates = _bias_runs(result, runs, bias)
            bias_fit, lr = viscoelastic_candidate(bias, list(spec.effects), bias_runs,
                                                  node_names, where[0], node_rates=rates)
            name = f"viscoelastic.{where[0]}"
            k = float(dict(zip(bias_fit.names, bias_fit.coefficients))[f"{name}.k"])
            if not (np.isfinite(lr) and np.isfinite(k)):
                raise FloatingPointError(f"non-finite fit (LR {lr}, k {k})")
        except Exception as err:  # one candidate's failure must not end the loop
            out.append(Candidate(kind, tuple(where), float("nan"), 1.0, method="score",
                                 note=f"refit failed: {type(err).__name__}: {err}"[:300]))
            continue
        _, white, _ = ljung_box(bias_fit.residuals)
        d = long_run_variance_ratio(bias_fit.residuals) if not white > white_p else 1.0
        c = Candidate(kind, tuple(where), float(lr), rule_p_value(kind, lr / d, 2, runs),
                      method="refit", delta_bic=-lr + 2 * math.log(n), lr_deflation=d,
                      parameters={"time_constant": bias_fit.time_constants[name][0], "k": k})
        c.duplicate = duplicate_reason(c, {}, sample_period(runs))
        out.append(c)
    return out


# Directions whitened per call, in multiples: the residuals (1), the Jacobian (one per
# free parameter) and the candidates' directions (tens) share one program per model
# instead of compiling three (0.2 s each, in the single-threaded scoring of each step).
WHITEN_BLOCK = 32


def innovation_directions(result: FitResult, data):
    """`f(V)`: output-space directions `V` (runs, T, p, m), free-run °C, to the whitened
    innovations they cause in the fitted Kalman filter, (runs, T, p, m)
    (`fitting._likelihood.dataset_innovation_map`; linear in `V`, so its columns are
    padded with zeros to a multiple of `WHITEN_BLOCK` and cut off again)."""
    from ..fitting._likelihood import dataset_innovation_map

    def whiten(V):
        m = V.shape[-1]
        padded = np.zeros((*V.shape[:-1], -(-m // WHITEN_BLOCK) * WHITEN_BLOCK))
        padded[..., :m] = V
        return np.asarray(dataset_innovation_map(result.model, data,
                                                 jnp.asarray(padded)))[..., :m]
    return whiten


def diagnose_step(step: Step, runs: list[Telemetry], likelihood: str, *, refits: int = 3,
                  fdr: float = 0.05, say=print, white_p: float | None = None,
                  initial: ModelSpec | None = None, missing=None,
                  search: SearchSettings | None = None, forecast=None) -> list[Candidate]:
    """Rank every candidate effect for the model of `step` (which it leaves unchanged).

    Thermal candidates are score-tested, the best `refits` of them refitted (see
    `_refit`: with `initial`, the model as the user wrote it, a refit also starts from
    the user's values, since a fit without the effect may have bent the other
    parameters to mimic it); viscoelastic ones are always refitted. With `white_p`,
    thermal candidates are only scored, not refitted, when every sensor's residuals
    are already white at that level (the misfit is in a bias channel). `forecast(first)`,
    where given, is told the candidates first in line to be refitted before any is.

    **Returns:** the candidates, refitted first, then by decreasing score."""
    spec, result = step.spec, step.result
    if white_p is not None and all(
            (step.record["whiteness_p"].get(c) or 0.0) > white_p for c in spec.sensor_columns):
        refits = 0
    unused = unused_columns(spec, runs)
    lowered = result.lowered_spec
    places = enumerate_places(spec, lowered, unused)
    thermal = [(k, w) for k, w in places if k != "viscoelastic"]
    ahead = step.scoring
    with phase("score tests"):
        data, weights, r, J, states, whiten = (
            ahead[1].result() if ahead is not None and ahead[0] == likelihood
            else scoring_inputs(step, runs, likelihood))
        columns = _padded_columns(runs, set(unused) | set(spec.input_columns),
                                  data.ts.shape[1])
        laws = _learned_places(spec, lowered, unused, column_scales(columns))
        say(f"scoring {len(places)} candidate effects and {len(laws)} learned laws")
        try:
            cands = score_candidates(result, data, thermal + laws, columns, weights, r, J,
                                     deflation=step.deflation(white_p if white_p is not None
                                                              else 0.01), whiten=whiten,
                                     states=states)
        except Exception as err:  # scoring failure: no thermal candidate this step
            say(f"scoring failed: {type(err).__name__}: {err}")
            cands = []
    with phase("bias channels"):
        cands += _viscoelastic_candidates(step, runs, places,
                                          white_p if white_p is not None else 0.01)
    cands.sort(key=lambda c: -c.score if np.isfinite(c.score) else math.inf)

    def wave(w):
        with phase("refits"):
            return _refit_side_by_side(w, step, runs, likelihood, set(unused), initial, say,
                                       white_p if white_p is not None else 0.01)

    # The best learned law significant by its score is refitted too, beside the kinds
    # (never instead of them: a law may mimic a kind, and the kind is the simpler form),
    # unless a kind has the larger score or the law's shape is its nested kind's. Its
    # refit, a nonlinear model (the costliest), goes first in the kinds' first wave.
    best_law = [c for c in cands if c.learned is not None and c.p_value < fdr][:1]
    if not (refits and best_law and not _law_outranked(best_law[0], cands) and
            not _law_adds_nothing(best_law[0], cands, fdr, lowered)):
        best_law = []
    found = []
    if refits and search is not None and missing is not None:
        found = _searched(step, runs, missing, cands, (data, weights, r, J, states, whiten),
                          columns, search, fdr, say)
    kinds = [c for c in cands if c.learned is None]
    if forecast is not None and refits:
        forecast(best_law + found + refittable(kinds)[:refits])
    refit_best(kinds, refits, wave, beside=best_law + found)
    for c in found:
        c.add_note("proposed by the symbolic search", first=True)
    if best_law:
        # the kind the law reduces to (a column's heat_source), refitted too if it was
        # not: the law must beat the simpler form it nests (`prefer_vocabulary`)
        nested = best_law[0].learned.nested_kind(best_law[0].where)
        refit_best([c for c in cands if c.learned is None and c.key == nested], 1, wave)
    cands.sort(key=lambda c: (c.method != "refit",
                              -c.score if np.isfinite(c.score) else math.inf))
    judge(cands, fdr, separation_advice)
    prefer_vocabulary(cands)
    prefer_simpler_laws(cands)
    reject_unphysical(cands, data_span(spec, runs))
    prefer_physics(cands, separation_advice)
    return cands


def _searched(step: Step, runs, missing, cands: list[Candidate], scoring, columns,
              search: SearchSettings, fdr: float, say) -> list[Candidate]:
    """The symbolic search's laws (`_symbolic_step.search_laws`) on the step's missing
    heat, score-tested like the library's and added to `cands`; returns those to refit
    (the `search.refits` best by their score among the significant ones). The front goes into the
    step's record (`symbolic_search`); a search that cannot run is a note there."""
    from ._candidates import score_candidates

    mh = missing()
    if mh is None or not mh.carriers:
        return []
    data, weights, r, J, states, whiten = scoring
    roles = search_roles(step, runs)
    try:
        laws, entry = search_laws(step, runs, mh, roles, search, say)
        laws = new_laws(laws, cands)
        scored = score_candidates(step.result, data, laws, columns, weights, r, J,
                                  deflation=step.deflation(0.01), whiten=whiten,
                                  states=states) if laws else []
    except Exception as err:  # the search's failure must not end the loop
        step.record["symbolic_search"] = {
            "verdict": f"the symbolic search could not run: {type(err).__name__}: {err}"[:300]}
        say(step.record["symbolic_search"]["verdict"])
        return []
    cands += scored
    best = sorted((c for c in scored if c.p_value < fdr), key=lambda c: -c.score)
    mark_proposed(entry, best[:search.refits])
    step.record["symbolic_search"] = entry
    refined = _refined(step, runs, mh, roles, search, say)
    cands += refined
    return best[:search.refits] + refined


def search_roles(step: Step, runs) -> dict[str, str]:
    """The recorded columns a searched law may read (name -> role): the unused ones and
    the heat inputs' powers."""
    return {**unused_columns(step.spec, runs),
            **{h.input: "power" for h in step.spec.heat_inputs}}


def at_file_values(step: Step, runs, initial, search: SearchSettings, say
                   ) -> list[Candidate]:
    """Candidates from the search on the missing heat at the file's values
    (`_symbolic_step.search_at_file_values`): added beside the model's effects like the
    search's other laws, not score-tested at the bent model (whose parameters took part
    of the law), refitted from the file's values. The search's front goes into the
    step's `symbolic_search` entry (`at_file_values`)."""
    roles = search_roles(step, runs)
    try:
        laws, entry = search_at_file_values(step, runs, initial, roles, search, say)
    except Exception as err:  # the search's failure must not end the loop
        entry = {"verdict": "the search at the file's values could not run: "
                            f"{type(err).__name__}: {err}"[:300]}
        say(entry["verdict"])
        laws = []
    if entry is not None:
        step.record.setdefault("symbolic_search", {})["at_file_values"] = entry
    return [_law_candidate(law, where, found, "proposed by the search on the missing "
                           "heat at the file's values") for law, where, found in laws]


def _law_candidate(law, where, found, note: str, **replacing) -> Candidate:
    """A searched law `(LearnedLaw, where)` as a candidate refitted whatever its score
    (an infinite score until then), from the search's constants (`found`, a
    `FoundLaw`); `replacing`: `replaces` and `replaced` of a refined law."""
    c = Candidate("expression", tuple(where), math.inf, 1.0, score_test=math.nan,
                  learned=law, shape=law.term.trials[0] if law.term.trials else None,
                  estimate=float(found.parameters.get("c", math.nan)), **replacing)
    c.add_note(note)
    return c


def _refined(step: Step, runs, mh, roles, search: SearchSettings, say) -> list[Candidate]:
    """Candidates that replace the laws the model holds at a node by the best laws of a
    search around them (`_symbolic_step.refine_laws`): not score-tested (a replacement
    is not an extension of the fitted model), always refitted. The search's front goes
    into the step's `symbolic_search` entry (`refinement`)."""
    try:
        laws, entry = refine_laws(step, runs, mh, roles, search, say)
    except Exception as err:  # the search's failure must not end the loop
        entry = {"verdict": f"the refining search could not run: {type(err).__name__}: "
                            f"{err}"[:300]}
        say(entry["verdict"])
        laws = []
    if entry is not None:
        step.record.setdefault("symbolic_search", {})["refinement"] = entry
    out = []
    for law, where, replaces, found in laws:
        replaced = tuple(step.spec.effects[i].expression for i in replaces)
        out.append(_law_candidate(law, where, found,
                                  f"refines {'; '.join(replaced)} (replaces it)",
                                  replaces=tuple(replaces), replaced=replaced))
    return out


def scoring_inputs(step: Step, runs: list[Telemetry], likelihood: str) -> tuple:
    """`(data, weights, r, J, states, whiten)` the score tests of `step` start from: the
    output-error problem at its fit (`output_error_at`); under the Kalman likelihood the
    residuals `r` and Jacobian `J` whitened by the fitted filter, and `whiten` the map
    that does it (`innovation_directions`), else None."""
    result = step.result
    data, weights, r, J, states = output_error_at(
        result, _experiments(result.lowered_spec, runs))
    weights, r, J = np.array(weights), np.array(r), np.array(J)
    whiten = None
    if likelihood == "kalman":
        # Score on the innovations: residuals, the fitted parameters' directions and
        # every candidate's direction go through the fitted filter (`innovation_map`).
        whiten = innovation_directions(result, data)
        scale = np.where(weights > 0, 1.0 / np.where(weights > 0, weights, 1.0), 0.0)
        r = whiten((r.reshape(weights.shape) * scale)[..., None]).reshape(-1)
        J = whiten(J.reshape(*weights.shape, -1) * scale[..., None]).reshape(r.size, -1)
    return data, weights, r, J, states, whiten
