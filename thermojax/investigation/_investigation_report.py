"""The human-readable side of `thermojax investigate`: `report.md` and its figures.

No JAX; the figures come from `_diagnostic_plots`. It reads the `report.json` dict of
docs/formats.md §5 and, per step, the run traces of the model fitted at that step, and tells the
story: what was found, why the loop stopped, how the error fell, and per step the
ranked candidates, the evidence for the effect added, and what the residual still
looks like.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from ._diagnostic_plots import diagnostic_plots, error_chart, settling_time
from ._diagnostics import diagnose_traces
from ._evidence import MIN_BIC_DROP, evidence_figure, evidence_rows, is_added, votes
from ._missing_heat_plots import missing_heat_section
from ._whiteness_verdict import stopping_sentence, white_threshold, whiteness_verdict
from .._plots import column_units

_TOP = 8  # candidates shown per step

_STOPPED = {
    "residuals_white": "the residuals became white (nothing systematic is left to explain)",
    "no_supported_candidate": "no candidate effect passed the significance rule",
    "max_steps": "the step limit was reached",
}


def _num(x, fmt: str = ".4g") -> str:
    """A number for a table cell; a dash for None or a non-number."""
    if isinstance(x, bool) or x is None:
        return "–"
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(v):
        return "–"
    if fmt == "p":
        return "< 1e-300" if v < 1e-300 else f"{v:.2g}"
    return f"{v:{fmt}}"


def _cell(x) -> str:
    return str(x).replace("|", "\\|").replace("\n", " ")


def _where(where) -> str:
    if where is None:
        return ""
    if isinstance(where, (list, tuple)):
        return "–".join(str(w) for w in where)
    return str(where)


def _effect(e) -> str:
    """`kind (a–b)` for an effect or candidate dict, or a `[kind, where]` pair."""
    if e is None:
        return "nothing"
    if isinstance(e, (list, tuple)):
        kind, where = (e[0], e[1]) if len(e) >= 2 else (e[0] if e else "?", None)
    else:
        kind, where = e.get("kind", "?"), e.get("where")
    w = _where(where)
    return f"{kind} ({w})" if w else str(kind)


def _sentence(text) -> str:
    text = str(text).strip()
    return text if text.endswith((".", "!", "?")) else text + "."


def _yes_no(x) -> str:
    return "–" if x is None else ("yes" if x else "no")


def _matching_candidate(previous: dict, added: dict) -> dict | None:
    """The candidate of the previous step that was added (spec: the first one; matched
    by kind and place when possible)."""
    cands = previous.get("candidates") or []
    return next((c for c in cands if is_added(c, added)), cands[0] if cands else None)


def _evidence(i: int, step: dict, previous: dict, report: dict, columns, units) -> str:
    """One paragraph: why the effect added at step `i` was added and what it bought."""
    added = step.get("added")
    if not added:
        return "Nothing was added at this step."
    c = _matching_candidate(previous, added) or {}
    parts = [f"**Added {_effect(added)}**"]
    ev = []
    if c.get("score_test") is not None:
        ev.append(f"score-test statistic {_num(c['score_test'])}")
    if c.get("likelihood_ratio") is not None:
        ev.append(f"likelihood-ratio statistic {_num(c['likelihood_ratio'])}")
    if c.get("score_test") is None and c.get("likelihood_ratio") is None \
            and c.get("score") is not None:
        ev.append(f"evidence score {_num(c['score'])}"
                  + (f" ({c['method']})" if c.get("method") else ""))
    if c.get("delta_bic") is not None:
        ev.append(f"Δ BIC {_num(c['delta_bic'], '+.4g')}")
    if c.get("p_value") is not None:
        pv = _num(c["p_value"], "p")
        ev.append(f"p {pv}" if pv.startswith("<") else f"p = {pv}")
    if c.get("supported") is not None:
        ev.append("supported" if c["supported"] else "not supported")
    if ev:
        parts.append(": " + ", ".join(ev))
    if report.get("significance_rule") and c.get("supported"):
        parts.append(" under the significance rule (stated at the top of this report)")
    parts.append(".")
    ties = c.get("tied_with") or []
    if ties:
        parts.append(" The data could not tell it apart from "
                     + ", ".join(_effect(t) for t in ties) + ".")
    if previous.get("separation"):
        parts.append(f" What would separate them: {_sentence(previous['separation'])}")
    if c.get("note"):
        parts.append(f" Note: {_sentence(c['note'])}")
    params = added.get("parameters") or {}
    if params:
        fitted = step.get("parameters") or {}
        parts.append(" Fitted: " + ", ".join(
            f"{k} = {_pm(v, _effect_std(fitted, added, k))}" for k, v in params.items()) + ".")
    before, after = previous.get("rmse") or {}, step.get("rmse") or {}
    changes = [f"{col} {_num(before.get(col))} → {_num(after.get(col))} {units[col]}"
               for col in columns if col in before or col in after]
    if changes:
        parts.append(" RMSE: " + "; ".join(changes) + ".")
    return "".join(parts)


def _pm(value, std) -> str:
    """`value ± std` (the std to 2 significant digits), or the value alone. A std of zero
    is no measure of certainty (a parameter held at its bound, or a direction the
    curvature could not resolve): it is said in words, never printed as "± 0"."""
    if isinstance(std, (int, float)) and math.isfinite(std) and std > 0:
        return f"{_num(value)} ± {_num(std, '.2g')}"
    if isinstance(std, (int, float)) and std == 0:
        return f"{_num(value)} (std undetermined: held at a bound or unresolved by the data)"
    return _num(value)


def _effect_std(parameters: dict, added: dict, name: str):
    """The std of the added effect's parameter `name` in a step's fitted `parameters`
    (dotted names `effects.<kind>.<...>.<name>`); None if absent."""
    kind, where = added.get("kind"), [str(w) for w in (added.get("where") or [])]
    label = added.get("name")
    for key, p in parameters.items():
        parts = key.split(".")
        if len(parts) < 3 or parts[0] != "effects" or parts[-1] != name:
            continue
        if (label and label in key) or (parts[1] == kind and all(w in key for w in where)):
            return (p or {}).get("std")
    return None


def _candidate_table(step: dict, next_step: dict | None = None) -> list[str]:
    """The step's candidates (`_evidence.evidence_rows`: the best `_TOP`, the added one
    always among them): both statistics, Δ BIC against the rule's threshold, whether
    refitted, the held-out folds' votes, and the outcome that tells the added one from
    the supported ones not added."""
    cands = step.get("candidates") or []
    lines = ["| # | candidate | score test | likelihood ratio | Δ BIC (rule: ≤ "
             f"−{MIN_BIC_DROP:g}) | p-value | supported | held-out folds for / against / "
             "inconclusive | outcome | tied with | method | note |",
             "|---|---|---:|---:|---:|---:|---|---|---|---|---|---|"]
    for c in evidence_rows(step, next_step):
        ties = ", ".join(_effect(t) for t in (c.get("tied_with") or [])) or "–"
        st, lr = c.get("score_test"), c.get("likelihood_ratio")
        if st is None and lr is None:  # a report from before the two were told apart
            st, lr = (None, c.get("score")) if c.get("method") == "refit" else (c.get("score"),
                                                                                None)
        f, a, n = votes(c)
        out = f"**{c['outcome']}**" if c["outcome"] == "added" else c["outcome"]
        lines.append("| " + " | ".join(_cell(v) for v in (
            c["rank"], _effect(c), _num(st), _num(lr), _num(c.get("delta_bic"), "+.4g"),
            _num(c.get("p_value"), "p"), _yes_no(c.get("supported")),
            f"{f} / {a} / {n}" if f + a + n else "not checked", out, ties,
            c.get("method") or "–", c.get("note") or "")) + " |")
    if len(cands) > _TOP:
        lines.append(f"\n({len(cands) - _TOP} more candidates not shown; all are in report.json.)")
    return lines


def step_plot_options(i: int, step: dict, prefix: str | None = None) -> dict:
    """The `diagnostic_plots` keywords of step `i` (its `report.json` entry `step`): the
    lag span's time scale from its parameters and the figures' title."""
    what = "the given model" if not step.get("added") else f"after adding {_effect(step['added'])}"
    return {"time_scale": settling_time(step.get("parameters") or {}),
            "title": f"Diagnosis of {what}" if prefix else f"Step {i}, {what}"}


def _diagnose_steps(out: Path, steps, step_traces, columns, input_names, boundary_inputs,
                    prefix: str | None = None, units: dict | None = None, plots_ahead=None,
                    white_p: float | None = None):
    """Per step: `diagnose_traces` and `diagnostic_plots` of its traces (None for both
    when the step has none). Plots are named `step<i>_*.png`, or `<prefix>_*.png` for a
    single step with `prefix`; with `plots_ahead` (a `PlotsAhead`) they come from it."""
    draw = plots_ahead.draw if plots_ahead is not None else diagnostic_plots
    diagnoses, plots = [], []
    for i in range(len(steps)):
        traces = step_traces[i] if i < len(step_traces) else None
        if traces:
            options = step_plot_options(i, steps[i], prefix)
            extra = {} if white_p is None else {"white_p": white_p}
            diagnoses.append(diagnose_traces(columns, traces, input_names, boundary_inputs,
                                             units=units, time_scale=options["time_scale"],
                                             **extra))
            plots.append(draw(out, prefix or f"step{i}", columns, traces, input_names,
                              boundary_inputs, units=units, **options))
        else:
            diagnoses.append(None)
            plots.append(None)
    return diagnoses, plots


def _default_units(steps: list[dict], columns) -> dict[str, str]:
    """column -> unit by `_plots.column_units`: a column is a bias channel when some
    step's `parameters` hold a `biases.<column>.*` entry."""
    names = {k for s in steps for k in (s.get("parameters") or {})}
    bias = [c for c in columns if any(k.startswith(f"biases.{c}.") for k in names)]
    return column_units([c for c in columns if c not in bias], bias)


def noise_sources(steps: list[dict], columns) -> dict[str, str]:
    """column -> "given" (fixed in the model file) or "estimated" (fitted with the model:
    then RMSE ≈ noise by construction), from the first step's `parameters`."""
    params = (steps[0].get("parameters") if steps else None) or {}
    out = {}
    for c in columns:
        p = params.get(f"sensors.{c}.noise")
        out[c] = "estimated" if p is None or p.get("free", True) else "given"
    return out


def _summary(report: dict, steps: list[dict], columns, noise: dict, units: dict,
             diagnosis: bool = False, verdict: dict | None = None) -> list[str]:
    """The `## Summary` section: what was added, why the loop stopped, RMSE against noise."""
    first, last = (steps[0] if steps else {}), (steps[-1] if steps else {})
    added = [(i, s["added"]) for i, s in enumerate(steps) if s.get("added")]
    md = ["## Summary", ""]
    if diagnosis:
        md.append("The given model was fitted and its residuals diagnosed; every candidate "
                  "effect was ranked without changing the model.")
    elif added:
        md.append(f"Starting from the given model, the investigation added {len(added)} "
                  f"effect{'s' if len(added) > 1 else ''}, in this order: "
                  + "; ".join(f"{_effect(a)} (step {i})" for i, a in added) + ".")
    else:
        md.append("The investigation added no effect to the given model.")
    for h in first.get("hold_changes") or []:
        md.append(f"The model file gives no hold for `{h['column']}`; held "
                  f"\"{h['hold']}\" (piecewise constant between samples) the given model "
                  f"fits its data better by {h['gain_log_l']:.1f} in log L than under the "
                  "default \"foh\", so the investigation went on from that hold and its "
                  "models write it.")
    stopped = report.get("stopped_because")
    if stopped and not diagnosis:
        md.append(stopping_sentence(stopped, verdict, _STOPPED))
    if report.get("likelihood"):
        md.append(f"Likelihood: `{report['likelihood']}`.")
    md.append("")
    if report.get("significance_rule"):  # stated here once; the steps refer to it
        md += [f"**Significance rule.** A candidate counts as supported when: "
               f"{_sentence(report['significance_rule'])} Every step below judges its "
               "candidates by this rule.", ""]
    sources = noise_sources(steps, columns)
    kalman = bool(verdict and verdict["kalman"])
    free = {r["column"]: r["free_run_p"] for r in (verdict or {}).get("rows", [])}
    head = ("| column | start RMSE | final RMSE | noise std | noise is | final / noise "
            "(given noise only) | " + ("final innovations whiteness p | final free-run "
                                       "whiteness p" if kalman else
                                       "final free-run whiteness p") + " | unit |")
    md += [head, "|---|---:|---:|---:|---|---:|---:|" + ("---:|" if kalman else "") + "---|"]
    for c in columns:
        r0, r1 = (first.get("rmse") or {}).get(c), (last.get("rmse") or {}).get(c)
        sd = noise.get(c)
        ratio = (r1 / sd) if isinstance(r1, (int, float)) and isinstance(sd, (int, float)) \
            and sd > 0 and sources[c] == "given" else None
        ps = [_num((last.get("whiteness_p") or {}).get(c), "p")]
        if kalman:
            ps.append(_num(free.get(c), "p"))
        md.append("| " + " | ".join(_cell(v) for v in (
            c, _num(r0), _num(r1), _num(sd),
            "given in the model" if sources[c] == "given" else "estimated",
            _num(ratio, ".3g"), *ps, units[c])) + " |")
    md.append("")
    if any(v == "estimated" for v in sources.values()) and kalman:
        md.append("An estimated noise std is the measurement noise the Kalman filter "
                  "assumes, not a floor the free run must reach; the free-run RMSE shows "
                  "what the model alone, driven by its inputs, leaves.")
    elif any(v == "estimated" for v in sources.values()):
        md.append("An estimated noise std is the fit's own residual scale, so RMSE ≈ noise "
                  "holds by construction: it is no yardstick of success; the whiteness p "
                  "is.")
    given = {c: v for c, v in noise.items() if sources.get(c) == "given"}
    if given:
        noise = given
        close = [c for c in columns if isinstance((last.get("rmse") or {}).get(c), (int, float))
                 and c in noise and noise[c] > 0 and last["rmse"][c] <= 1.2 * noise[c]]
        if close:
            md.append("The final model's error is within 20 % of the measurement noise for "
                      + ", ".join(close) + ".")
        far = [c for c in columns if c in noise and c not in close
               and isinstance((last.get("rmse") or {}).get(c), (int, float))]
        if far:
            md.append("Still above the noise: " + ", ".join(far) + ".")
    for i, s in enumerate(report.get("steps") or []):
        if (s.get("network") or {}).get("verdict"):  # nothing supported; heat missing
            md.append(f"Step {i} asked a heat network: {s['network']['verdict']}.")
    if "unexplained" in report:
        u = report.get("unexplained")
        md.append(f"Left unexplained: {u}" if u else "Nothing is flagged as left unexplained.")
    if report.get("advice"):
        md.append(f"Advice: {report['advice']}")
    if report.get("final_model"):
        md.append(f"Final model: [`{report['final_model']}`]({report['final_model']}).")
    md.append("")
    if diagnosis:
        return md
    return md + ["![free-run RMSE per step](error_by_step.png)", ""]


def _steps_table(steps: list[dict], columns, units: dict) -> list[str]:
    """The `## Steps` overview: one row per step (added effect, size, fit, RMSE, time)."""
    md = ["## Steps", ""]
    head = ["step", "added", "parameters", "−log L", "AIC", "BIC"] + [
        f"RMSE {c}, {units[c]}" for c in columns]
    timed = any("wall_time_s" in s for s in steps)
    if timed:
        head.append("wall time, s")
    md += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for i, s in enumerate(steps):
        row = [i, _effect(s.get("added")) if s.get("added") else "start", _num(s.get("n_params")),
               _num(s.get("nll")), _num(s.get("aic")), _num(s.get("bic"))]
        row += [_num((s.get("rmse") or {}).get(c)) for c in columns]
        if timed:
            row.append(_num(s.get("wall_time_s"), ".3g"))
        md.append("| " + " | ".join(_cell(v) for v in row) + " |")
    md.append("")
    return md


def _whiteness_table(verdict: dict) -> list[str]:
    """`### Residual whiteness` of one step: Ljung-Box p per column of the sequence the
    loop's rule reads (under the Kalman likelihood the innovations, and the free run
    beside them, each named), each judged at the loop's threshold, and the one verdict
    (`_whiteness_verdict`) built from these very numbers."""
    md = ["### Residual whiteness", ""]
    t = f"p > {verdict['white_p']:g}"
    if verdict["kalman"]:
        md += [f"| column | innovations p | innovations white ({t}) | free-run p | "
               f"free run white ({t}) | lags |", "|---|---:|---|---:|---|---:|"]
        for r in verdict["rows"]:
            md.append("| " + " | ".join(_cell(v) for v in (
                r["column"], _num(r["rule_p"], "p"), _yes_no(r["rule_white"]),
                _num(r["free_run_p"], "p"), _yes_no(r["free_run_white"]),
                _num(r["lags"], ".0f"))) + " |")
    else:
        md += [f"| column | free-run p | white ({t}) | lags |", "|---|---:|---|---:|"]
        for r in verdict["rows"]:
            md.append("| " + " | ".join(_cell(v) for v in (
                r["column"], _num(r["rule_p"], "p"), _yes_no(r["rule_white"]),
                _num(r["lags"], ".0f"))) + " |")
    md += ["", verdict["sentence"], ""]
    return md


def _whiteness_finding(f: str, columns) -> bool:
    """A `diagnose_traces` finding that only restates a column's Ljung-Box verdict (the
    step's whiteness table and verdict say it once)."""
    return any(f.startswith((f"{c}: residuals white", f"{c}: residuals not white"))
               for c in columns)


def _step_section(i: int, steps: list[dict], report: dict, columns, plots, diagnoses,
                  units: dict, verdict: dict | None = None, heat: list[str] = (),
                  evidence: str | None = None) -> list[str]:
    """`## Step i`: the evidence for its effect, its fit, residual and candidates."""
    s = steps[i]
    title = "the given model" if i == 0 and not s.get("added") \
        else f"added {_effect(s.get('added'))}"
    md = [f"## Step {i}: {title}" if report.get("stopped_because") != "diagnosis only"
          else "## The given model", ""]
    if i > 0:
        md += [_evidence(i, s, steps[i - 1], report, columns, units), ""]
    pl, dg = plots[i], diagnoses[i]
    if pl:
        if i > 0 and plots[i - 1]:
            md += ["Measured against model, before (previous step) and after this step:", "",
                   f"![before: step {i - 1}]({plots[i - 1]['fit']})",
                   f"![after: step {i}]({pl['fit']})", ""]
        else:
            md += ["Measured against model:", "", f"![step {i}]({pl['fit']})", ""]
    if verdict is not None:
        md += _whiteness_table(verdict)
    md.append("Lags as stated; runs pooled by summing per-run autocovariances, each run "
              "about its own mean (a lag never straddles two runs).")
    md.append("")
    if dg:
        shown = [f for f in dg["findings"] if not _whiteness_finding(f, columns)]
        if shown:
            md += ["What the free-run residual shows:", ""] + [f"- {f}" for f in shown] + [""]
    md += list(heat)
    if pl:
        md += [f"![residual autocorrelation]({pl['acf']})", "",
               f"![residual against inputs and their rates]({pl['xcorr']})", "",
               f"![cumulated periodogram]({pl['periodogram']})", "",
               f"![residual by chamber phase]({pl['phases']})", ""]
    else:
        md += ["(No run traces for this step: no plots.)", ""]
    cands = s.get("candidates") or []
    md += ["### Candidates", ""]
    if cands:
        md.append("Ranked by evidence (larger is stronger): the likelihood-ratio statistic "
                  "2 (−log L before − after) for refitted candidates, else the score-test "
                  "statistic (no refit), each in its own column; Δ BIC = BIC after − BIC "
                  "before. Supported means: passes the significance rule stated at the "
                  "top; the first supported candidate that the held-out folds do not "
                  "reject is added at the next step, and the outcome column says what "
                  "became of each.")
        md.append("")
        if evidence:
            md += [f"![evidence per candidate at step {i}]({evidence})", ""]
        md += _candidate_table(s, steps[i + 1] if i + 1 < len(steps) else None) + [""]
        if s.get("separation"):
            md += [f"What would separate the tied candidates: {_sentence(s['separation'])}", ""]
    else:
        md += ["No candidate was evaluated at this step.", ""]
    md += _front_table(s.get("symbolic_search"))
    return md


def _front_table(entry: dict | None) -> list[str]:
    """`### Laws searched`: the symbolic search's front at the step (simplest first),
    each law's complexity, fit to the missing heat and, where refitted, its evidence."""
    if not entry:
        return []
    md = ["### Laws searched", ""]
    if "front" not in entry:
        return md + [_sentence(entry.get("verdict", "no search")), ""]
    md += [f"A search over expression trees fitted {entry['evaluated']} laws to the missing "
           f"heat at {entry['node']} in {entry['seconds']:.1f} s ({entry['generations']} "
           f"generations, stopped: {entry['stopped']}). The front: the best fit at each "
           "complexity (tree nodes as written), each kept only where it fits better than "
           "every simpler law (on the front: yes; the others are the best of their "
           "complexity). Every law was score-tested through the dynamics, the best "
           "significant ones refitted and judged by the same rule as every candidate.",
           ""]
    md += _law_rows(entry["front"], (
        _COMPLEXITY, _LAW, ("R² on the missing heat", _r2),
        ("on the front", lambda row, ev, refit: _yes_no(row.get("on_front"))),
        ("score test", lambda row, ev, refit: _num(ev.get("score_test"))),
        _REFITTED, _RATIO, _DELTA_BIC,
        ("held-out gain", lambda row, ev, refit: _num(ev.get("holdout_gain"))), _SUPPORTED))
    return (md + [""] + _file_values_table(entry.get("at_file_values"))
            + _refinement_table(entry.get("refinement")))


def _refinement_table(entry: dict | None) -> list[str]:
    """`### Laws refined`: the front of the search around the laws the model held at the
    node (the heat they carry plus the missing heat), the refitted ones' evidence as
    replacements of those laws."""
    if not entry:
        return []
    if "front" not in entry:
        return ["### Laws refined", "", _sentence(entry.get("verdict", "no search")), ""]
    held = "; ".join(f"`{t}`" for t in entry["replaces"])
    return _picked_table(
        "### Laws refined", entry,
        f"The model held {held} at {entry['node']}. A search around it fitted "
        f"{entry['evaluated']} laws to the heat it carries plus the missing heat; the picked "
        "laws were refitted as replacements of it (likelihood ratio and Δ BIC against the "
        "model that holds it).")


def _file_values_table(entry: dict | None) -> list[str]:
    """`### Laws searched at the file's values`: where no candidate was supported, the
    front of the search on the missing heat of the structure at the model file's
    values, the refitted ones' evidence."""
    if not entry:
        return []
    if "front" not in entry:
        return ["### Laws searched at the file's values", "",
                _sentence(entry.get("verdict", "no search")), ""]
    return _picked_table(
        "### Laws searched at the file's values", entry,
        f"No candidate was supported. A search fitted {entry['evaluated']} laws to the "
        f"missing heat at {entry['node']} of this structure at the model file's values (the "
        "fitted model's parameters had moved to mimic what it lacks); the picked laws were "
        "refitted from the file's values and judged like every candidate.")


def _picked_table(title: str, entry: dict, text: str) -> list[str]:
    """`title`, `text` and the table of `entry`'s front (the picked laws' evidence)."""
    return [title, "", text, "", *_law_rows(entry["front"], (
        _COMPLEXITY, _LAW, ("R²", _r2), _REFITTED, _RATIO, _DELTA_BIC, _SUPPORTED)), ""]


def _r2(row, ev, refit) -> str:
    return _num(row["r2"], ".5f")


# The searched laws' tables' columns: (header, cell(row, its evidence, refitted or not)).
_COMPLEXITY = ("complexity", lambda row, ev, refit: str(row["complexity"]))
_LAW = ("law", lambda row, ev, refit: f"`{row['expression']}`")
_REFITTED = ("refitted", lambda row, ev, refit: _yes_no(refit))
_RATIO = ("likelihood ratio", lambda row, ev, refit: _num(ev.get("likelihood_ratio")))
_DELTA_BIC = ("Δ BIC", lambda row, ev, refit: _num(ev.get("delta_bic")))
_SUPPORTED = ("supported",
              lambda row, ev, refit: _yes_no(ev.get("supported")) if refit else "–")


def _law_rows(front: list[dict], columns) -> list[str]:
    """A Markdown table of the searched laws `front` (each with its `evidence`), one
    column per `(header, cell)` of `columns`."""
    md = ["| " + " | ".join(h for h, _ in columns) + " |", "|" + "---|" * len(columns)]
    for row in front:
        ev = row.get("evidence") or {}
        refit = ev.get("method") == "refit"
        md.append("| " + " | ".join(cell(row, ev, refit) for _, cell in columns) + " |")
    return md


def write_investigation_report(out_dir, report: dict, step_traces: list, columns: list[str],
                               input_names: list[str], boundary_inputs=(),
                               diagnosis: bool = False, units: dict | None = None,
                               plots_ahead=None, missing_heat: list | None = None,
                               nearest: dict | None = None,
                               input_units: dict | None = None) -> Path:
    """Write `report.md` (and its PNGs, plus `diagnostics.json`) into `out_dir`.

    **Arguments:**

    - `out_dir`: folder, created if needed.
    - `report`: the `investigate` `report.json` dict (docs/formats.md §5); optional keys used
      when present: `noise` (column -> std), `significance_rule`, `likelihood`,
      `unexplained`, `steps[*].wall_time_s`, `steps[*].separation`, and in candidates
      `p_value`, `supported`, `method`, `note`.
    - `step_traces`: `step_traces[i]` the run traces (see `_diagnostics`) of the
      model fitted at step `i`; a missing entry just leaves that step without plots.
    - `columns`, `input_names`, `boundary_inputs`: as `diagnose_traces` takes them.
    - `diagnosis`: the one-step report of `diagnose` (titled a diagnosis, plots
      `diagnose_*.png`, no error-per-step chart).
    - `units`: column -> unit (default `_plots.column_units`: °C, or for a bias column,
      one the steps' `parameters` name as `biases.<column>.*`, deg/h for `*_dph`, µg
      for `*_ug`).
    - `plots_ahead`: a `PlotsAhead` that may already have drawn the steps' figures
      (the investigation's, while it went on); the figures are drawn by it.
    - `missing_heat`: per step, its `discovery.MissingHeat` where at hand (else the
      step's `step<i>_missing_heat.csv` in `out_dir` is drawn, without an added law).
    - `nearest`: node -> the sensor columns nearest it
      (`_missing_heat_plots.nearest_sensors`), drawn under its missing heat.
    - `input_units`: input column -> unit for the missing-heat figure.

    **Returns:** the path of `report.md`.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    steps = list(report.get("steps") or [])
    units = {**_default_units(steps, columns), **(units or {})}
    noise = {k: v for k, v in (report.get("noise") or {}).items() if v is not None}
    white_p = white_threshold(report)
    diagnoses, plots = _diagnose_steps(out, steps, step_traces, columns, input_names,
                                       boundary_inputs, "diagnose" if diagnosis else None,
                                       units, plots_ahead, white_p)
    verdicts = [whiteness_verdict(s, d, report.get("likelihood"), white_p, columns, units)
                for s, d in zip(steps, diagnoses)]
    (out / "diagnostics.json").write_text(json.dumps(
        {"steps": diagnoses}, indent=1, allow_nan=False, ensure_ascii=False))
    sources = noise_sources(steps, columns)
    if not diagnosis:
        error_chart(out / "error_by_step.png", steps or [{}], columns, noise, units,
                    {c: sources.get(c) == "given" for c in noise},
                    kalman=report.get("likelihood") == "kalman")

    md = ["# Diagnosis report" if diagnosis else "# Investigation report", ""]
    md += _summary(report, steps, columns, noise, units, diagnosis,
                   verdicts[-1] if verdicts else None)
    if not diagnosis:
        md += _steps_table(steps, columns, units)
    for i in range(len(steps)):
        traces = step_traces[i] if i < len(step_traces) else None
        heat = missing_heat_section(
            out, i, steps, traces, columns, input_names, boundary_inputs,
            (missing_heat or [])[i] if i < len(missing_heat or []) else None, nearest,
            units, input_units, "diagnose" if diagnosis else None)
        evidence = None
        if not diagnosis and steps[i].get("candidates"):
            evidence = f"step{i}_evidence.png"
            if evidence_figure(out / evidence, steps[i], steps[i + 1] if i + 1 < len(steps)
                               else None, title=f"Step {i}") is None:
                evidence = None
        md += _step_section(i, steps, report, columns, plots, diagnoses, units, verdicts[i],
                            heat, evidence)
    path = out / "report.md"
    path.write_text("\n".join(md) + "\n", encoding="utf-8")
    return path
