"""The selection rule: when a candidate effect is supported (`diagnose` and `investigate`).

Stated once (`significance_rule`) and applied by both commands:

1. **Significance.** Its likelihood-ratio p-value (after refitting; one-sided for an
   effect on the boundary of its parameter space, Davies' bound for a time constant
   absent under the null) passes Benjamini-Hochberg at false-discovery rate `fdr`
   over every candidate of the step: forward selection by likelihood-ratio tests, the
   field's practice on one log (Bacher & Madsen 2011, CTSM-R).
2. **Size.** It lowers the BIC by at least `MIN_BIC_DROP` (Kass & Raftery: "very
   strong"). While the residuals are not white, the statistics of 1 and 2 are divided
   by the residuals' long-run variance ratio (Newey-West).
3. **Held-out check** (`holdout_verdict`): refitted without each fold in turn (each
   run with three runs or more, else contiguous blocks), the model with the effect
   and without it predict the fold. A fold is *inconclusive* when a fit failed, did
   not converge after a second try, or its held-out gain is dominated by a few samples
   (the largest 1 % of per-sample differences carry more than half of their absolute
   sum: a boundary run or a held-out block started from a wrong state, not the
   effect). Inconclusive folds do not vote. The conclusive folds vote: the candidate
   is rejected when more of them predict worse with the effect than better, or when
   their summed gain is not positive. With fewer than two conclusive folds the check
   is inconclusive and 1-2 decide alone (the report says so).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

from ._candidates import Candidate, benjamini_hochberg

TIE_LR = float(stats.chi2.ppf(0.95, 1))  # 3.84
MIN_BIC_DROP = 10.0  # Kass & Raftery (1995): a Bayes factor above 150, "very strong"
DOMINATED_SHARE = 0.5  # the top 1 % of held-out samples carrying more than this is a break
DOMINATING_FRACTION = 0.01
MIN_CONCLUSIVE = 2  # conclusive folds the held-out check needs to decide anything


def significance_rule(fdr: float, n_blocks: int) -> str:
    """The rule above in words, for the reports."""
    return (
        f"forward selection by likelihood-ratio tests: Benjamini-Hochberg at false-discovery "
        f"rate {fdr} over all candidates of a step (likelihood-ratio p-values after "
        "refitting; one-sided boundary tests for positive effects; Davies' bound over the "
        "time constant for extra_node and viscoelastic, which do not exist under the null) "
        f"and a BIC drop of at least {MIN_BIC_DROP:g} (Kass-Raftery 'very strong'); while "
        "residuals are not white the statistics are divided by their long-run variance "
        "ratio (Newey-West). Then a held-out check (leave one run out with three runs or "
        f"more, else {n_blocks} contiguous blocks): a fold whose fit failed, did not "
        "converge, or whose held-out gain is dominated by a few samples (the top 1 % carry "
        "over half of it) is inconclusive and does not vote; the candidate is rejected when "
        "more conclusive folds predict worse with it than better, or their summed gain is "
        f"not positive; with fewer than {MIN_CONCLUSIVE} conclusive folds the check is "
        "inconclusive and the likelihood-ratio test decides. A candidate whose fitted "
        "parameters leave their physical range (a sensor gain beyond ±20 %, an offset beyond "
        "10 °C, a capacitance or conductance factor falling below 2 % of its reference value "
        "or crossing zero within the data's temperatures) is not supported, and a sensor artifact (gain, offset, lag) "
        f"steps aside for a supported physical effect within {MIN_BIC_DROP:g} of its deflated "
        "Δ BIC")


def deflated_delta_bic(c: Candidate, deflation: float | None = None) -> float:
    """Δ BIC with the likelihood ratio divided by a long-run variance ratio: the
    candidate's own (`lr_deflation`) unless `deflation` is given."""
    if c.delta_bic is None or not np.isfinite(c.score):
        return float("nan")
    d = max(c.lr_deflation if deflation is None else deflation, 1.0)
    return float(c.delta_bic + c.score * (1.0 - 1.0 / d))


def judge(cands: list[Candidate], fdr: float, separation_advice) -> None:
    """Mark the candidates that pass 1 and 2 (Benjamini-Hochberg at `fdr`, refitted,
    deflated Δ BIC ≤ −`MIN_BIC_DROP`, not a duplicate) and the near-ties among the
    refitted ones, in place. `separation_advice(kinds)`: what would tell kinds apart."""
    ok = benjamini_hochberg([c.p_value for c in cands], fdr)
    for c, passed in zip(cands, ok):
        dbic = deflated_delta_bic(c)
        c.supported = bool(passed and c.method == "refit" and dbic <= -MIN_BIC_DROP
                           and not c.duplicate)
        if c.duplicate:
            c.add_note(c.duplicate, first=True)
        elif passed and c.method == "refit" and not c.supported:
            c.note = c.note or (f"Δ BIC {dbic:.1f} (deflated by {c.lr_deflation:.2f} for "
                                f"autocorrelated residuals) is not a drop of {MIN_BIC_DROP:g}")
        if passed and c.method == "score":
            c.note = c.note or "significant by its score; not refitted (not among the best)"
    refitted = [c for c in cands if c.method == "refit" and np.isfinite(c.score)]
    for c in refitted:
        c.tied_with = [d.key for d in refitted if d is not c and abs(d.score - c.score) < TIE_LR
                       and (c.supported or d.supported)]
        if c.tied_with:
            tie = (f"near-tie: likelihood ratios within {TIE_LR:.2f} (the 95 % point of "
                   "χ²₁) of " + ", ".join(f"{k} {list(w)}" for k, w in c.tied_with) +
                   ", so the data cannot tell them apart; " +
                   separation_advice({c.kind, *(k for k, _ in c.tied_with)}))
            c.add_note(tie, first=True)


def prefer_vocabulary(cands: list[Candidate]) -> None:
    """A learned law (`expression` candidate) stays supported only if its Δ BIC is at
    least `MIN_BIC_DROP` below that of every supported kind of the vocabulary, both
    statistics deflated by the larger of their long-run variance ratios (a law's extra
    exponent or rate can absorb part of another missing effect while the residuals are
    not white: on a generated heat source beside a missing mass, a power law of the
    column gained 37 in likelihood ratio over the heat source, 2 parameters more, with
    the mass still absent). Where a named kind explains the data as well, the simpler,
    named form is kept."""
    dbic = deflated_delta_bic
    kinds = [c for c in cands if c.supported and c.learned is None]
    for c in cands:
        if c.learned is None or not c.supported:
            continue
        for k in kinds:
            d = max(c.lr_deflation, k.lr_deflation, 1.0)
            if dbic(c, d) > dbic(k, d) - MIN_BIC_DROP:
                c.supported = False
                c.add_note(f"{k.kind} {list(k.where)} explains as much (deflated Δ BIC "
                           f"{dbic(k, d):.1f} against {dbic(c, d):.1f}, deflation {d:.2f}): "
                           "the named kind is kept", first=True)
                break


def prefer_simpler_laws(cands: list[Candidate]) -> None:
    """Among learned laws (the library's and the symbolic search's), one stays supported
    only if its deflated Δ BIC is at least `MIN_BIC_DROP` below that of every supported
    law with fewer parameters: a second term or a free exponent that fits a little of the
    noise is not a better law (the rule `prefer_vocabulary` states between a law and a
    kind, here between laws)."""
    dbic = deflated_delta_bic
    laws = [c for c in cands if c.learned is not None and c.supported]
    for c in laws:
        for k in laws:
            if k is c or not k.supported or \
                    len(k.learned.term.shape) >= len(c.learned.term.shape):
                continue
            d = max(c.lr_deflation, k.lr_deflation, 1.0)
            if dbic(c, d) > dbic(k, d) - MIN_BIC_DROP:
                c.supported = False
                c.add_note(f"the simpler law {k.expression} explains as much (deflated "
                           f"Δ BIC {dbic(k, d):.1f} against {dbic(c, d):.1f}): it is kept",
                           first=True)
                break


@dataclass
class FoldVote:
    """One held-out fold: its gain (−log L of the held-out samples without the effect
    minus with it; positive favours the effect) and why it cannot vote ("" if it can)."""

    fold: tuple
    gain: float
    inconclusive: str = ""

    def as_json(self) -> dict:
        return {"fold": [self.fold[0], None if self.fold[1] is None else list(self.fold[1])],
                "gain": self.gain if np.isfinite(self.gain) else None,
                "vote": ("inconclusive" if self.inconclusive else
                         "for" if self.gain > 0 else "against"),
                **({"why": self.inconclusive} if self.inconclusive else {})}


def fold_vote(fold: tuple, without: np.ndarray | Exception, with_effect: np.ndarray | Exception
              ) -> FoldVote:
    """The vote of one fold from its held-out per-sample −log L terms under the fit
    without the effect and with it (or the exception a fit raised)."""
    for got in (without, with_effect):
        if isinstance(got, Exception):
            return FoldVote(fold, float("nan"),
                            f"a held-out fit failed ({type(got).__name__}: {got})"[:200])
    d = np.asarray(without, float) - np.asarray(with_effect, float)
    if d.size == 0 or not np.all(np.isfinite(d)):
        return FoldVote(fold, float("nan"), "a held-out term is not finite")
    gain = float(d.sum())
    k = max(1, math.ceil(DOMINATING_FRACTION * d.size))
    mag = np.abs(d)
    total = float(mag.sum())
    top = float(np.sort(mag)[::-1][:k].sum())
    if total > 0 and top > DOMINATED_SHARE * total:
        return FoldVote(fold, gain, f"{top / total:.0%} of its held-out gain comes from "
                                    f"{k} of {d.size} samples")
    return FoldVote(fold, gain)


def holdout_verdict(votes: list[FoldVote]) -> tuple[bool | None, float, str]:
    """`(passes, summed gain of the conclusive folds, reason)`: `passes` is None when
    fewer than `MIN_CONCLUSIVE` folds are conclusive (the check cannot decide)."""
    voting = [v for v in votes if not v.inconclusive]
    skipped = len(votes) - len(voting)
    aside = f" ({skipped} inconclusive fold{'s' * (skipped != 1)} set aside)" if skipped else ""
    if len(voting) < MIN_CONCLUSIVE:
        return None, float("nan"), (f"held-out check inconclusive: {len(voting)} of "
                                    f"{len(votes)} folds could vote{aside}")
    g = np.array([v.gain for v in voting])
    total = float(g.sum())
    wins, losses = int(np.sum(g > 0)), int(np.sum(g <= 0))
    if not wins > losses:
        return False, total, (f"predicts held-out data better in {wins} of {len(voting)} "
                              f"conclusive folds{aside}")
    if not total > 0:
        return False, total, f"summed held-out gain {total:.1f} is not positive{aside}"
    return True, total, (f"better in {wins} of {len(voting)} conclusive folds, summed "
                         f"held-out gain {total:.1f}{aside}")


def held_out_advice(cands: list[Candidate], likelihood: str) -> str | None:
    """What to try when, under output error, held-out *blocks* (one or two runs) rejected
    candidates that the likelihood-ratio test supports (on PRBS1's building log the
    first block, started from a state its fit cannot see, outweighed three better
    blocks); None otherwise (a held-out *run* is evidence, and the Kalman likelihood's
    held-out terms are one-step predictions)."""
    rejected = [c for c in cands if c.holdout_votes
                and c.holdout_votes[0].fold[1] is not None  # blocks, not runs
                and holdout_verdict(c.holdout_votes)[0] is False]
    if likelihood != "output_error" or not rejected:
        return None
    names = ", ".join(f"{c.kind} {list(c.where)}" for c in rejected[:3])
    return (f"{names} pass{'es' * (len(rejected) == 1)} the likelihood-ratio test but "
            "held-out blocks of the run reject "
            f"{'it' if len(rejected) == 1 else 'them'}. Under output error a held-out block "
            "is predicted by a free run that nothing corrects (the first one from a start "
            "state its fit cannot see), so where residuals are far from white (disturbances "
            "no column records, as in a building) the blocks judge the start and the "
            "disturbances more than the effect. On one log the field's practice is forward "
            "selection on the Kalman likelihood: rerun with `--likelihood kalman` (its "
            "held-out terms are one-step predictions), or give three or more runs (one "
            "held out at a time).")
