"""The missing-physics loop (`thermojax investigate`, docs/formats.md §5).

Fit the model; if its residuals are not white, score every candidate effect
(`_candidates`), refit the best few, and add the best one the evidence supports;
repeat until the residuals are white, no candidate is supported, or `max_steps`.

A candidate is *supported* when, all at once:

1. its p-value passes the Benjamini-Hochberg procedure at false-discovery rate
   `fdr` over every candidate of the step (score-test p-values, replaced by the
   likelihood-ratio p-values of the refitted ones; one-sided where the effect is
   absent on a boundary of its parameter space);
2. it lowers the BIC (`delta_bic < 0`);
3. it predicts better out of sample: refitted with each run left out in turn, the
   extended model predicts the left-out runs better than the current model does
   (held-out −log L at the current noise stds; checked for the chosen candidate).

Candidates whose likelihood ratios differ by less than the 95 % point of χ²₁ (3.84)
are reported as tied (`tied_with`): the data cannot tell them apart.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import stats

from ..fitting._bias import bias_parameters, bias_to_spec, fit_bias, viscoelastic_candidate
from ._candidates import (Candidate, benjamini_hochberg, column_hold, column_role,
                          enumerate_places, new_effect, refit_p_value, score_candidates)
from ..measurements._data import Experiment
from ..fitting._fit import FitResult, fit, output_error_at, standardized_innovations
from .._json import json_safe
from .._memory import release_compiled_if_crowded
from ..model._model_file import dump_model, save_model
from ..model._parameters_by_name import spec_parameters, with_spec_parameters
from .._residual_analysis import ljung_box
from ..model._spec import ModelSpec
from ..measurements._telemetry import Telemetry

TIE_LR = float(stats.chi2.ppf(0.95, 1))  # 3.84


@dataclass
class Step:
    """One fitted model of the loop and its evidence."""

    spec: ModelSpec
    result: FitResult
    biases: dict  # column -> BiasFit
    record: dict  # the step's report.json entry
    traces: list[dict] = field(repr=False, default_factory=list)


# ---------------------------------------------------------------------------
# Evaluating one model


def _experiments(spec: ModelSpec, runs: list[Telemetry]) -> list[Experiment]:
    return [Experiment.from_telemetry(spec, t, name=t.path or f"run{i}")
            for i, t in enumerate(runs)]


def _bias_runs(result, runs, bias):
    from ._candidates import _states_jit

    data = result.problem.data
    x = np.asarray(_states_jit(result.model, data, result.state.run_initial))
    return [(np.asarray(t.ts), x[r, :len(t.ts)], t.column(bias.column)) for r, t in
            enumerate(runs)]


def evaluate(spec: ModelSpec, runs: list[Telemetry], likelihood: str, progress=None,
             holdout: int | None = None) -> Step:
    """Fit `spec` to the runs, its bias channels too, and measure the fit (docs/formats.md §5 keys)."""
    result = fit(spec, _experiments(spec, runs), likelihood=likelihood, progress=progress,
                 holdout=holdout)
    lowered = result.lowered_spec
    biases = {}
    for b in spec.biases:
        biases[b.column] = fit_bias(b, list(spec.effects), _bias_runs(result, runs, b),
                                    list(lowered.node_names))
    spec_out = result.spec
    effects = list(spec_out.effects)
    new_biases = []
    for b in spec_out.biases:
        nb, effects = bias_to_spec(b, effects, biases[b.column])
        new_biases.append(nb)
    spec_out = spec_out.replace(biases=tuple(new_biases), effects=tuple(effects))
    nll = result.nll + sum(f.nll for f in biases.values())
    n_params = result.n_params + sum(f.n_params for f in biases.values())
    n = result.n_samples + sum(int(sum(np.isfinite(r).sum() for r in f.residuals))
                               for f in biases.values())
    rmse = dict(result.rmse)
    rmse.update({c: float(f.rmse) for c, f in biases.items()})
    # whiteness: free-run residuals (output error) or standardized innovations (Kalman)
    cols = list(spec.sensor_columns)
    if likelihood == "kalman":
        seq = standardized_innovations(result)
    else:
        exps = _experiments(spec, runs)
        seq = [e.outputs - p for e, p in zip(exps, result.predictions)]
    tests = {c: ljung_box([s[:, j] for s in seq]) for j, c in enumerate(cols)}
    tests.update({c: ljung_box(f.residuals) for c, f in biases.items()})
    white = {c: p for c, (_, p, _) in tests.items()}
    lags = {c: lag for c, (_, _, lag) in tests.items()}
    params = dict(result.parameters)
    for f in biases.values():
        params.update(bias_parameters(f))
    record = {
        "added": None, "n_params": int(n_params), "rmse": rmse,
        "nll": float(nll), "aic": float(2 * n_params + 2 * nll),
        "bic": float(n_params * math.log(n) + 2 * nll),
        "whiteness_p": white, "whiteness_lags": lags, "candidates": [],
        "fit_percent": dict(result.fit_percent), "n_samples": int(n),
        "parameters": params, "converged": bool(result.converged),
    }
    step = Step(spec_out, result, biases, record)
    step.traces = _traces(spec, runs, result, biases)
    return step


def _traces(spec, runs, result, biases) -> list[dict]:
    """Measured and modelled columns per run, for plots (`_diagnostics.RunTrace`)."""
    out = []
    cols = list(spec.sensor_columns)
    inputs = list(spec.input_columns)
    for r, t in enumerate(runs):
        meas = [t.column(c) for c in cols] + [t.column(c) for c in biases]
        pred = [result.predictions[r][:, j] for j in range(len(cols))] + \
               [biases[c].predictions[r] for c in biases]
        out.append({"name": t.path or f"run{r}", "ts": np.asarray(t.ts),
                    "measured": np.stack(meas, 1), "predicted": np.stack(pred, 1),
                    "inputs": np.stack([t.column(c) for c in inputs], 1) if inputs
                    else np.zeros((len(t.ts), 0))})
    return out


# ---------------------------------------------------------------------------
# One step of diagnosis


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


def _viscoelastic_candidates(step: Step, runs: list[Telemetry], places) -> list[Candidate]:
    """Every `viscoelastic` place of `places`, refitted directly on its bias channel
    (linear least squares and a τ search: cheap)."""
    spec, result = step.spec, step.result
    node_names = list(result.lowered_spec.node_names)
    out = []
    for kind, where in places:
        if kind != "viscoelastic":
            continue
        bias = next(b for b in spec.biases if b.column == where[1])
        bias_fit, lr = viscoelastic_candidate(bias, list(spec.effects),
                                              _bias_runs(result, runs, bias), node_names,
                                              where[0])
        name = f"viscoelastic.{where[0]}"
        k = float(dict(zip(bias_fit.names, bias_fit.coefficients))[f"{name}.k"])
        out.append(Candidate(kind, tuple(where), float(lr), refit_p_value(kind, lr, 2),
                             method="refit",
                             delta_bic=-lr + 2 * math.log(step.record["n_samples"]),
                             parameters={"time_constant": bias_fit.time_constants[name][0],
                                         "k": k}))
    return out


def _refit(c: Candidate, step: Step, runs, likelihood, holds, initial, say) -> bool:
    """Refit the model of `step` with candidate `c` added; on success `c` holds the
    likelihood ratio, its p-value, Δ BIC, the extended step and the fitted parameters.

    The refit starts from the fitted model plus the effect's first guess and, with
    `initial`, also from the user's values; the better likelihood is kept."""
    spec, lowered = step.spec, step.result.lowered_spec
    effect = new_effect(spec, lowered, c.kind, c.where, holds)
    say(f"refitting with {c.kind} {list(c.where)} (score {c.score:.1f})")
    extended = spec.replace(effects=spec.effects + (effect,))
    starts = [extended]
    if initial is not None:
        starts.append(with_spec_parameters(extended, spec_parameters(initial)))
    ext = None
    for start in starts:
        try:
            got = evaluate(start, runs, likelihood)
        except Exception as err:  # one candidate's failure must not end the loop
            c.note = f"refit failed: {type(err).__name__}: {err}"[:300]
            continue
        if ext is None or got.record["nll"] < ext.record["nll"]:
            ext = got
    if ext is None:
        return False
    lr = 2 * (step.record["nll"] - ext.record["nll"])
    n_new = ext.record["n_params"] - step.record["n_params"]
    c.score, c.method = float(lr), "refit"
    c.p_value = refit_p_value(c.kind, lr, max(n_new, 1))
    c.delta_bic = ext.record["bic"] - step.record["bic"]
    c.result = ext
    added = next(e for e in ext.spec.effects if (e.kind, tuple(e.where)) == c.key)
    c.parameters = {k: p.value for k, p in added.parameters.items()}
    return True


def _judge(cands: list[Candidate], fdr: float) -> None:
    """Mark the supported candidates (Benjamini-Hochberg at `fdr`, refitted, Δ BIC < 0)
    and the near-ties among the refitted ones, in place."""
    ok = benjamini_hochberg([c.p_value for c in cands], fdr)
    for c, passed in zip(cands, ok):
        c.supported = bool(passed and c.method == "refit" and c.delta_bic is not None
                           and c.delta_bic < 0)
        if passed and c.method == "score":
            c.note = c.note or "significant by its score; not refitted (not among the best)"
    refitted = [c for c in cands if c.method == "refit"]
    for c in refitted:
        c.tied_with = [d.key for d in refitted if d is not c and abs(d.score - c.score) < TIE_LR
                       and (c.supported or d.supported)]
        if c.tied_with:
            c.note = (f"near-tie: likelihood ratios within {TIE_LR:.2f} (the 95 % point of "
                      "χ²₁) of " + ", ".join(f"{k} {list(w)}" for k, w in c.tied_with) +
                      ", so the data cannot tell them apart; " +
                      separation_advice({c.kind, *(k for k, _ in c.tied_with)}))


def diagnose_step(step: Step, runs: list[Telemetry], likelihood: str, *, refits: int = 3,
                  fdr: float = 0.05, say=print, white_p: float | None = None,
                  initial: ModelSpec | None = None) -> list[Candidate]:
    """Rank every candidate effect for the model of `step` (which it leaves unchanged).

    Thermal candidates are score-tested, the best `refits` of them refitted (see
    `_refit`: with `initial`, the model as the user wrote it, a refit also starts from
    the user's values, since a fit without the effect may have bent the other
    parameters to mimic it); viscoelastic ones are always refitted. With `white_p`,
    thermal candidates are only scored, not refitted, when every sensor's residuals
    are already white at that level (the misfit is in a bias channel).

    **Returns:** the candidates, refitted first, then by decreasing score."""
    spec, result = step.spec, step.result
    if white_p is not None and all(
            (step.record["whiteness_p"].get(c) or 0.0) > white_p for c in spec.sensor_columns):
        refits = 0
    unused = unused_columns(spec, runs)
    lowered = result.lowered_spec
    places = enumerate_places(spec, lowered, unused)
    thermal = [(k, w) for k, w in places if k != "viscoelastic"]
    data, weights, r, J = output_error_at(result, _experiments(lowered, runs))
    columns = _padded_columns(runs, set(unused) | set(spec.input_columns), data.ts.shape[1])
    say(f"scoring {len(places)} candidate effects")
    cands = score_candidates(result, data, thermal, columns, weights, r, J)
    cands += _viscoelastic_candidates(step, runs, places)
    cands.sort(key=lambda c: -c.score)
    holds = {c: column_hold(columns[c]) for c in unused}
    done = 0
    for c in list(cands):  # refit the best few thermal candidates
        if done >= refits:
            break
        if c.method == "refit" or c.score <= 0:
            continue
        done += _refit(c, step, runs, likelihood, holds, initial, say)
    cands.sort(key=lambda c: (c.method != "refit", -c.score))
    _judge(cands, fdr)
    return cands


SEPARATION = {
    frozenset(("sensor_lag", "extra_node")):
        "a lag acts on the reading alone, a mass also delays the heat reaching the rest of "
        "the network: a second sensor on (or beyond) that node, or a known power step into "
        "it, would separate them",
    frozenset(("radiation", "conductance_temperature")):
        "both strengthen the path as it warms; radiation grows with T³ in kelvin, a linear "
        "temperature coefficient with T̄ − 25 °C: runs over a wider temperature range "
        "(or in vacuum) would separate them",
}


def separation_advice(kinds) -> str:
    kinds = frozenset(kinds)
    for pair, text in SEPARATION.items():
        if pair <= kinds or (len(kinds) == 1 and kinds <= pair):
            return text
    return ("the data cannot tell these apart: excite the system differently (a power step "
            "in the node concerned, a faster ramp, a wider temperature range) or add a sensor "
            "near the candidates' places")


def _holdout_gain(spec_base, spec_ext, runs, likelihood, sigma, say) -> float:
    """Σ over runs of the held-out −log L improvement (current noise stds) when each run
    in turn is left out of both fits."""
    if len(runs) < 2:
        return float("nan")
    experiments = {id(s): _experiments(s, runs) for s in (spec_base, spec_ext)}
    gain = 0.0
    for r in range(len(runs)):
        ssr = []
        for s in (spec_base, spec_ext):
            res = fit(s, experiments[id(s)], likelihood="output_error", holdout=r)
            e = (experiments[id(spec_base)][r].outputs - res.predictions[r]) / sigma[None, :]
            ssr.append(float(np.nansum(e ** 2)))
        gain += 0.5 * (ssr[0] - ssr[1])
        say(f"held-out run {r}: −log L change {-0.5 * (ssr[0] - ssr[1]):.1f}")
    return gain


# ---------------------------------------------------------------------------
# The loop


def _choose(cands: list[Candidate], current: Step, runs, likelihood, holdout_check: bool,
            say) -> Candidate | None:
    """The first supported candidate that (unless viscoelastic, or without
    `holdout_check`) also predicts held-out runs better; the others it tries are marked
    unsupported."""
    for c in cands:
        if not c.supported:
            continue
        if holdout_check and c.kind != "viscoelastic":
            sigma = np.array([current.record["parameters"].get(
                f"sensors.{s}.noise", {"value": 0.01})["value"]
                for s in current.spec.sensor_columns])
            c.holdout_gain = _holdout_gain(current.spec, c.result.spec, runs, likelihood,
                                           sigma, say)
            if not c.holdout_gain > 0:
                c.supported = False
                c.note = "does not predict held-out runs better (leave one run out)"
                continue
        return c
    return None


def _extend(current: Step, chosen: Candidate, runs, likelihood) -> Step:
    """The next step: the model of `current` with `chosen` added (its refit, or a new
    evaluation for a viscoelastic effect), its record's `added` filled in."""
    if chosen.kind == "viscoelastic":
        from ..model._spec import Effect, Parameter

        eff = Effect("viscoelastic", chosen.where, {
            k: Parameter(v) for k, v in chosen.parameters.items()})
        nxt = evaluate(current.spec.replace(effects=current.spec.effects + (eff,)), runs,
                       likelihood)
    else:
        nxt = chosen.result
    added = next(e for e in nxt.spec.effects if (e.kind, tuple(e.where)) == chosen.key)
    nxt.record["added"] = {"kind": added.kind, "where": list(added.where),
                           "parameters": {k: p.value for k, p in added.parameters.items()},
                           **({"name": added.name} if added.name else {})}
    return nxt


def _unexplained(record: dict, white_p: float) -> str:
    bad = [c for c, p in record["whiteness_p"].items() if p is None or p <= white_p]
    return (f"the residuals of {', '.join(bad)} stay non-white: part of the error "
            "is not explained by any effect of the vocabulary with the data "
            "columns given (an unrecorded input, or physics outside the "
            "vocabulary).")


def investigate(spec: ModelSpec, runs: list[Telemetry], *, likelihood: str = "output_error",
                max_steps: int = 4, refits: int = 3, fdr: float = 0.05,
                white_p: float = 0.01, out: Path | None = None, progress=None,
                resume: bool = True, holdout_check: bool = True) -> dict:
    """Run the loop; returns the `report.json` dict (docs/formats.md §5). With `out`, writes the
    report, every step's model, `model_final.toml`, the Markdown report and its plots,
    and a checkpoint after each finished step, from which a rerun resumes."""
    say = progress or (lambda _m: None)
    t0 = time.perf_counter()
    out = Path(out) if out is not None else None
    fingerprint = _fingerprint(spec, runs, likelihood)
    records: list[dict] = []
    start_spec = spec
    if out is not None and resume:
        records, start_spec = _load_checkpoint(out, fingerprint, spec)
        if records:
            say(f"resuming after step {len(records) - 1} from {out / 'checkpoint.json'}")
    current = evaluate(start_spec, runs, likelihood, progress=None)
    if records:
        current.record["added"] = records[-1]["added"]
        records[-1] = {**current.record, "candidates": [], "wall_time_s":
                       records[-1].get("wall_time_s")}
    else:
        records.append(current.record)
    steps_traces = [None] * (len(records) - 1) + [current.traces]
    stopped = "max_steps"
    while True:
        i = len(records) - 1
        rec = records[-1]
        say(f"step {i}: −log L {rec['nll']:.1f}, RMSE " +
            ", ".join(f"{c} {v:.4g}" for c, v in rec["rmse"].items()))
        if all(p is not None and p > white_p for p in rec["whiteness_p"].values()):
            stopped = "residuals_white"
            break
        if i >= max_steps:
            stopped = "max_steps"
            break
        t_step = time.perf_counter()
        cands = diagnose_step(current, runs, likelihood, refits=refits, fdr=fdr, say=say,
                              white_p=white_p, initial=spec)
        chosen = _choose(cands, current, runs, likelihood, holdout_check, say)
        rec["candidates"] = [c.as_json() for c in cands]
        rec["wall_time_s"] = time.perf_counter() - t_step
        if chosen is not None and chosen.tied_with:
            rec["separation"] = separation_advice({chosen.kind, *(k for k, _ in
                                                                   chosen.tied_with)})
        if chosen is None:
            stopped = "no_supported_candidate"
            break
        current = _extend(current, chosen, runs, likelihood)
        say(f"added {chosen.kind} {list(chosen.where)}")
        records.append(current.record)
        steps_traces.append(current.traces)
        if out is not None:
            _save_checkpoint(out, fingerprint, records, current.spec)
        release_compiled_if_crowded()  # rejected candidates' programs are not reused
    report = {
        "schema": 1, "thermojax_version": _version(), "likelihood": likelihood,
        "steps": records, "stopped_because": stopped, "final_model": "model_final.toml",
        "unexplained": (None if stopped == "residuals_white"
                        else _unexplained(records[-1], white_p)),
        "significance_rule": (
            f"Benjamini-Hochberg at false-discovery rate {fdr} over all candidates of a "
            "step (one-sided boundary tests for positive effects), Δ BIC < 0 after "
            "refitting, and a better prediction of held-out runs (leave one run out)"),
        "whiteness_test": (f"Ljung-Box, lags min(20, N/5), runs pooled by summing per-run "
                           f"autocovariances; white when p > {white_p} for every column"),
        "wall_time_s": time.perf_counter() - t0,
    }
    report["noise"] = _noise(current)
    if out is not None:
        _write_outputs(out, report, current, steps_traces, runs)
    return json_safe(report)


def _noise(step: Step) -> dict:
    out = {}
    for c in step.spec.sensor_columns:
        p = step.record["parameters"].get(f"sensors.{c}.noise")
        if p is not None:
            out[c] = p["value"]
    for c, f in step.biases.items():
        out[c] = float(f.sigma)
    return out


def _version() -> str:
    from .. import __version__

    return __version__


def _fingerprint(spec, runs, likelihood) -> str:
    h = hashlib.sha256(dump_model(spec).encode())
    h.update(likelihood.encode())
    for t in runs:
        h.update(str(t.path).encode())
        h.update(np.ascontiguousarray(t.ts).tobytes())
    return h.hexdigest()


def _save_checkpoint(out: Path, fingerprint: str, records, spec) -> None:
    out.mkdir(parents=True, exist_ok=True)
    i = len(records) - 1
    save_model(spec, out / f"step{i}_model.toml",
               header=f"thermojax investigate: model after step {i}")
    tmp = out / "checkpoint.json.tmp"
    tmp.write_text(json.dumps(json_safe({"fingerprint": fingerprint, "steps": records,
                                          "model": f"step{i}_model.toml"})))
    tmp.replace(out / "checkpoint.json")


def _load_checkpoint(out: Path, fingerprint: str, spec):
    from ..model._model_file import load_model

    path = out / "checkpoint.json"
    if not path.exists():
        return [], spec
    try:
        doc = json.loads(path.read_text())
        if doc.get("fingerprint") != fingerprint:
            return [], spec
        return doc["steps"], load_model(out / doc["model"])
    except (OSError, ValueError, KeyError):
        return [], spec


def _write_outputs(out: Path, report: dict, final: Step, traces, runs) -> None:
    from ._investigation_report import write_investigation_report

    out.mkdir(parents=True, exist_ok=True)
    save_model(final.spec, out / "model_final.toml",
               header="thermojax investigate: the final model")
    (out / "report.json").write_text(json.dumps(json_safe(report), indent=2,
                                                allow_nan=False))
    cols = list(final.spec.sensor_columns) + [b.column for b in final.spec.biases]
    inputs = list(final.spec.input_columns)
    boundary = list(final.spec.boundary_columns)
    for step_traces in traces:  # every step's plots against the final model's inputs
        for r, tr in enumerate(step_traces or []):
            tr["inputs"] = np.stack([runs[r].column(c) for c in inputs], 1) if inputs \
                else np.zeros((len(tr["ts"]), 0))
    write_investigation_report(out, json_safe(report), [t or [] for t in traces], cols,
                               inputs, boundary)
