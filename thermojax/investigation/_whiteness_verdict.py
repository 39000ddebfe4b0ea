"""One verdict on whiteness per step, from the numbers the report's table shows.

The loop stops at `residuals_white` when every column of a step's `whiteness_p` is above
the threshold `white_p`: under the output-error likelihood those are the free-run
residuals' Ljung-Box p-values, under the Kalman likelihood the one-step innovations'.
Under the Kalman likelihood the free run is a second, different sequence: a model whose
innovations are white may still simulate badly from its inputs alone (its process noise
and state corrections carry it). The report names both, judges both at the same
threshold, and says which one the loop's rule reads; the stopping sentence is built
from the very same numbers (`whiteness_verdict`), so the text cannot contradict the
table.

No JAX; plain dicts (the `report.json` step entry and `diagnose_traces`' output).
"""

from __future__ import annotations

import math
import re

DEFAULT_WHITE_P = 0.01  # `investigate`'s default threshold


def white_threshold(report: dict) -> float:
    """The threshold the loop used: `report["white_p"]`, else the number after `p >` in
    its `whiteness_test` sentence, else `investigate`'s default (0.01)."""
    v = report.get("white_p")
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return float(v)
    m = re.search(r"p\s*>\s*([0-9.eE+-]+)", str(report.get("whiteness_test") or ""))
    if m:
        try:
            return float(m.group(1))
        except ValueError:
            pass
    return DEFAULT_WHITE_P


def _p(v) -> str:
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        return "–"
    return "p < 1e-300" if v < 1e-300 else f"p = {v:.2g}"


def _is_white(p, white_p: float) -> bool | None:
    if not isinstance(p, (int, float)) or isinstance(p, bool) or not math.isfinite(p):
        return None
    return p > white_p


def whiteness_verdict(step: dict, diagnosis: dict | None, likelihood: str | None,
                      white_p: float, columns, units: dict | None = None) -> dict:
    """The whiteness of one step, judged once.

    **Arguments:** `step`, a `report.json` step entry (its `whiteness_p`,
    `whiteness_lags`, `rmse`); `diagnosis`, `diagnose_traces` of its free-run traces (or
    None); `likelihood`; `white_p`, the loop's threshold; `columns` in report order;
    `units` column -> unit.

    **Returns:** a dict with `kalman` (bool), `rule` (the sequence the loop's rule reads:
    "innovations" or "free-run residuals"), `rows` (per column: `column`, `rule_p`,
    `rule_white`, `free_run_p`, `free_run_white`, `lags`), `white` (the loop's verdict:
    every `whiteness_p` above `white_p`, the very test that stops the loop),
    `free_run_white` (None when unknown), and `sentence`, the verdict in words.
    """
    units = units or {}
    kalman = likelihood == "kalman"
    wp = step.get("whiteness_p") or {}
    lags = step.get("whiteness_lags") or {}
    cols_dg = (diagnosis or {}).get("columns") or {}
    rows = []
    for c in list(columns) + [c for c in wp if c not in columns]:
        lb = (cols_dg.get(c) or {}).get("ljung_box") or {}
        rule_p = wp.get(c)
        free_p = lb.get("p") if kalman else (rule_p if c in wp else lb.get("p"))
        rows.append({"column": c, "rule_p": rule_p, "rule_white": _is_white(rule_p, white_p),
                     "free_run_p": free_p, "free_run_white": _is_white(free_p, white_p),
                     "lags": lags.get(c, lb.get("lags"))})
    # the loop's own test (`investigate`): every column it tested, None counts as not white
    white = all(p is not None and p > white_p for p in wp.values())
    free = [r["free_run_white"] for r in rows if r["free_run_white"] is not None]
    free_run_white = all(free) if free else None
    rule = "innovations" if kalman else "free-run residuals"
    return {"kalman": kalman, "rule": rule, "rows": rows, "white": white,
            "free_run_white": free_run_white, "white_p": white_p,
            "sentence": _sentence(rows, white, free_run_white, kalman, white_p, step, units)}


def _list(rows, key: str) -> str:
    return ", ".join(f"{r['column']} {_p(r[key])}" for r in rows)


def _sentence(rows, white, free_run_white, kalman, white_p, step, units) -> str:
    tested = [r for r in rows if r["rule_p"] is not None or r["column"] in
              (step.get("whiteness_p") or {})]
    fail = [r for r in tested if not r["rule_white"]]
    what = "one-step innovations" if kalman else "free-run residuals"
    head = (f"**Whiteness verdict: {'white' if white else 'not white'}.** The loop's rule "
            f"reads the {what} (Ljung-Box, white when p > {white_p:g} in every column"
            + ("; under the Kalman likelihood the innovations are the model's own "
               "prediction errors" if kalman else "") + "): ")
    if not tested:
        head += "no column was tested."
    elif white:
        head += f"every column passes ({_list(tested, 'rule_p')})."
    else:
        head += f"{_list(fail, 'rule_p')} {'fails' if len(fail) == 1 else 'fail'}."
    if not kalman:
        return head
    known = [r for r in rows if r["free_run_white"] is not None]
    if free_run_white is None:
        return head + " The free run (the model driven by its inputs alone) was not tested."
    rmse = step.get("rmse") or {}
    errs = ", ".join(f"{r['column']} {rmse[r['column']]:.3g} {units.get(r['column'], '°C')}"
                     for r in known if isinstance(rmse.get(r["column"]), (int, float)))
    if free_run_white:
        return head + (f" The free run (the model driven by its inputs alone) is white too "
                       f"({_list(known, 'free_run_p')}).")
    bad = [r for r in known if not r["free_run_white"]]
    return head + (
        f" The free run (the model driven by its inputs alone) is not white: "
        f"{_list(bad, 'free_run_p')}" + (f", free-run RMSE {errs}" if errs else "") + ". "
        + ("So the innovations are white only because the filter's corrections absorb "
           "what the model misses: the model alone does not reproduce the data, and its "
           "simulation errors are systematic." if white else
           "Both sequences still hold structure."))


def stopping_sentence(stopped: str | None, verdict: dict | None, descriptions: dict) -> str:
    """Why the loop stopped, in words that agree with the last step's `verdict`:
    `descriptions` maps a `stopped_because` value to its plain description."""
    if stopped != "residuals_white" or verdict is None:
        return f"It stopped because {descriptions.get(stopped, stopped)} (`{stopped}`)."
    p = verdict["white_p"]
    if not verdict["kalman"]:
        return (f"It stopped because the free-run residuals became white (Ljung-Box p > "
                f"{p:g} in every column; `residuals_white`): nothing systematic is left "
                "for the vocabulary to explain.")
    out = (f"It stopped because the one-step innovations became white (Ljung-Box p > {p:g} "
           f"in every column; `residuals_white`), the rule under the Kalman likelihood.")
    if verdict["free_run_white"] is False:
        out += (" The free run is not white (see the last step's whiteness verdict): the "
                "model explains the data only together with its filter's corrections, so "
                "its simulation from the inputs alone is not to be trusted as it is.")
    elif verdict["free_run_white"]:
        out += " The free run is white too."
    return out
