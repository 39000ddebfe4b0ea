"""The evidence of a step at a glance: per candidate, what the significance rule saw
(the likelihood-ratio statistic and Δ BIC against its threshold, whether it was
refitted, how the held-out folds voted) and what came of it (added, supported but not
added and why, or not supported). The rule itself is stated once, at the top of the
report; this table and its figure refer to it.

Reads `report.json` dicts (docs/formats.md §5) only; NumPy and matplotlib.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .._plots import WIDTH_IN, new_figure, save_figure
from ._selection import MIN_BIC_DROP

TOP = 8  # candidates shown


def _where(where) -> str:
    return "–".join(str(w) for w in where) if isinstance(where, (list, tuple)) else str(where)


def label(c: dict) -> str:
    w = _where(c.get("where") or [])
    return f"{c.get('kind', '?')} ({w})" if w else str(c.get("kind", "?"))


def is_added(c: dict, added: dict | None) -> bool:
    """Whether the candidate `c` (a report.json entry) is the effect `added` of the next
    step: same kind and place, and for a learned law the same expression (a step may
    score several laws at one node, and a refined law replaces another there)."""
    return bool(added) and c.get("kind") == added.get("kind") and \
        _where(c.get("where") or []) == _where(added.get("where") or []) and \
        (c.get("expression") is None or added.get("expression") is None or
         c.get("expression") == added.get("expression"))


def votes(c: dict) -> tuple[int, int, int]:
    """`(for, against, inconclusive)` among its held-out folds."""
    v = [f.get("vote") for f in c.get("holdout_folds") or []]
    return v.count("for"), v.count("against"), v.count("inconclusive")


def _held_out_rejects(c: dict) -> bool:
    """The held-out rule (`_selection.holdout_verdict`) from the folds in the report:
    rejected when the conclusive folds vote more against than for, or their summed gain
    is not positive (two conclusive folds at least)."""
    folds = [f for f in c.get("holdout_folds") or [] if f.get("vote") != "inconclusive"]
    if len(folds) < 2:
        return False
    n_for = sum(f.get("vote") == "for" for f in folds)
    gain = sum(f.get("gain") or 0.0 for f in folds)
    return len(folds) - n_for > n_for or not gain > 0


def outcome(c: dict, added: dict | None, added_rank: int | None, rank: int) -> str:
    """What came of candidate `c` (ranked `rank`) at a step whose next step `added` the
    candidate ranked `added_rank` (None: nothing added)."""
    if is_added(c, added):
        return "added"
    # the loop marks a candidate the held-out folds reject as not supported, and says
    # so in its note: told apart from one the test itself did not support
    if "held-out check against it" in str(c.get("note") or "") or _held_out_rejects(c):
        return "passed the test; rejected by the held-out folds"
    if not c.get("supported"):
        return ("not supported (score test only: not refitted)"
                if c.get("method") == "score" else "not supported")
    if added is not None and added_rank is not None and rank > added_rank:
        return "supported; not added (one effect per step: the added one ranks first)"
    if added is not None:
        return "supported; not added (the added one was preferred)"
    return "supported; not added"


def _num(x, fmt=".4g") -> str:
    if x is None or isinstance(x, bool) or not isinstance(x, (int, float)) \
            or not math.isfinite(x):
        return "–"
    return f"{x:{fmt}}"


def _p(x) -> str:
    if x is None or not isinstance(x, (int, float)) or not math.isfinite(x):
        return "–"
    return "< 1e-300" if x < 1e-300 else f"{x:.2g}"


def evidence_rows(step: dict, next_step: dict | None) -> list[dict]:
    """The shown candidates of `step` (the added one always among them) with their
    `outcome`, best first."""
    cands = list(step.get("candidates") or [])
    added = (next_step or {}).get("added")
    added_rank = next((k for k, c in enumerate(cands) if is_added(c, added)), None)
    shown = cands[:TOP]
    if added_rank is not None and added_rank >= TOP:
        shown.append(cands[added_rank])
    return [{**c, "rank": cands.index(c) + 1,
             "outcome": outcome(c, added, added_rank, cands.index(c))} for c in shown]


def evidence_table(step: dict, next_step: dict | None) -> list[str]:
    """Markdown lines: the evidence table of one step (empty without candidates)."""
    rows = evidence_rows(step, next_step)
    if not rows:
        return []
    md = [f"| # | candidate | refitted | likelihood ratio | Δ BIC (rule: ≤ −{MIN_BIC_DROP:g}) "
          "| p-value | held-out folds for / against / inconclusive | outcome |",
          "|---:|---|---|---:|---:|---:|---|---|"]
    for r in rows:
        f, a, n = votes(r)
        folds = f"{f} / {a} / {n}" if f + a + n else "not checked"
        out = f"**{r['outcome']}**" if r["outcome"] == "added" else r["outcome"]
        md.append("| " + " | ".join(str(v).replace("|", "\\|") for v in (
            r["rank"], label(r), "yes" if r.get("method") == "refit" else "no (score test)",
            _num(r.get("likelihood_ratio")), _num(r.get("delta_bic"), "+.4g"),
            _p(r.get("p_value")), folds, out)) + " |")
    return md


def _folds(c: dict) -> str:
    f, a, n = votes(c)
    if not f + a + n:
        return "(no held-out check)"
    return f"(held-out folds: {f} for, {a} against" + (f", {n} inconclusive)" if n else ")")


_COLOURS = {"added": "tab:green", "not supported": "0.6"}


def evidence_figure(path, step: dict, next_step: dict | None, title: str = "") -> Path | None:
    """A bar per shown candidate: its Δ BIC (symmetric-log axis) against the rule's
    threshold −`MIN_BIC_DROP`, coloured by outcome, its held-out votes under its
    name. None (nothing written) when no candidate has a Δ BIC."""
    rows = [r for r in evidence_rows(step, next_step)
            if isinstance(r.get("delta_bic"), (int, float)) and math.isfinite(r["delta_bic"])]
    if not rows:
        return None
    fig = new_figure(figsize=(WIDTH_IN, 2.2 + 0.6 * max(len(rows), 3)))
    ax = fig.subplots()
    y = np.arange(len(rows))[::-1]
    seen = set()
    for yi, r in zip(y, rows):
        key = "not supported" if r["outcome"].startswith("not supported") else (
            r["outcome"] if r["outcome"] in _COLOURS else
            "rejected by the held-out folds" if "held-out" in r["outcome"]
            else "supported, not added")
        colour = _COLOURS.get(key, "tab:red" if "held-out" in r["outcome"] else "tab:orange")
        ax.barh(yi, r["delta_bic"], color=colour, height=0.6,
                hatch=None if r.get("method") == "refit" else "//",
                label=key if key not in seen else None)
        seen.add(key)
    ax.axvline(-MIN_BIC_DROP, color="k", ls="--", lw=1.0,
               label=f"threshold: Δ BIC ≤ −{MIN_BIC_DROP:g}")
    ax.axvline(0, color="k", lw=0.5)
    ax.set_xscale("symlog", linthresh=MIN_BIC_DROP)
    lo = min(r["delta_bic"] for r in rows)
    hi = max(r["delta_bic"] for r in rows)
    ax.set_xlim(min(lo * 1.5, -10 * MIN_BIC_DROP), max(hi * 3, MIN_BIC_DROP))
    ax.set_yticks(y)
    ax.set_yticklabels([f"{r['rank']}. {label(r)}\n{_folds(r)}" for r in rows])
    ax.set_xlabel("Δ BIC = BIC after − BIC before (symmetric log scale; left is stronger)")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=9)
    hatched = any(r.get("method") != "refit" for r in rows)
    fig.suptitle((f"{title}\n" if title else "") + "evidence per candidate"
                 + (" (hatched: score test only, not refitted)" if hatched else ""))
    return save_figure(fig, path)
