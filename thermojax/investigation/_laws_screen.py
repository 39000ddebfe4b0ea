"""The learned laws' screening: the library's laws at the model's places
(`_learned_places`), and before the costliest refit of a step, whether a law is worth
it: not where a kind of the vocabulary outranks it (`_law_outranked`), nor where its
best shape is the kind it nests (`_law_adds_nothing`)."""

from __future__ import annotations

import numpy as np
from scipy import stats

from ._candidates import Candidate, helper_nodes
from ..discovery import learned_places
from ..model._spec import ModelSpec
from ..model.effects import KINDS


def _law_outranked(law: Candidate, cands: list[Candidate]) -> bool:
    """Whether a kind of the vocabulary has a larger score-test statistic than the learned
    `law`: a named kind then explains more at first order, and the law's refit (a
    nonlinear model: under the Kalman likelihood the costliest fit of an investigation)
    is skipped. Notes the reason on `law`."""
    kinds = [c for c in cands if c.learned is None and c.kind != "viscoelastic"
             and c.score_test is not None and np.isfinite(c.score_test)]
    best = max(kinds, key=lambda c: c.score_test, default=None)
    if best is None or best.score_test <= law.score_test:
        return False
    law.add_note(f"not refitted: its score, {law.score_test:.4g}, is below that of "
                 f"{best.kind} {list(best.where)} ({best.score_test:.4g}): a named kind "
                 "explains more")
    return True


def _law_adds_nothing(law: Candidate, cands: list[Candidate], fdr: float,
                      lowered: ModelSpec | None = None) -> bool:
    """Whether the learned `law`'s best score direction gains less over the kind of the
    vocabulary it nests than the χ²(1) critical value at `fdr` (the shape chosen from
    its grid is the one extra degree of freedom): its shape is then the nested kind's,
    and its refit, a nonlinear model (the costliest of a step), could only tie with the
    kind, which `prefer_vocabulary` keeps. Likewise when its best shape is the nested
    kind's and the model (`lowered`) already has that kind there: the score then finds
    nothing in the law's own shapes, only in a heat the model has (on PRBS1 the law
    `c·Ps^p·exp(k(Ti − 25))` at p = 1, k = 0 is the model's solar gain on Ti; it scored
    489 and 351 from the half-sample shift between how score tests and the model hold
    `Ps`, and its refits, 25 s of the loop, gained 56 and 46, both rejected).
    Notes the reason on `law`."""
    nested = law.learned.nested_kind(law.where)
    if (nested is not None and lowered is not None and law.learned.is_nested_shape(law.shape)
            and KINDS[nested[0]].held_by(lowered, nested[1])):
        shape = ", ".join(f"{n} = {v:g}" for n, v in zip(law.learned.term.shape, law.shape))
        law.add_note(f"not refitted: its best shape ({shape}) makes it {nested[0]} "
                     f"{list(nested[1])}, a heat the model already has: the score finds "
                     "nothing in the law's own shapes")
        return True
    kind = next((c for c in cands if c.learned is None and c.key == nested), None)
    if kind is None or kind.score_test is None:
        return False
    gain = law.score_test - kind.score_test
    critical = float(stats.chi2.isf(fdr, 1))
    if gain >= critical:
        return False
    law.add_note(f"not refitted: its score exceeds that of {kind.kind} {list(kind.where)}, "
                 f"the kind it nests, by {gain:.3g} (under {critical:.3g}, the χ²(1) "
                 f"critical value at {fdr:g}): its best shape is the kind's, which explains "
                 "as much")
    return True


def _learned_places(spec: ModelSpec, lowered: ModelSpec, unused: dict[str, str],
                    scales: dict[str, float]) -> list:
    """The library's laws at every place (`discovery.learned_places`): the unused columns
    and the model's own power columns as inputs (read in `scales`), except a law the
    model already holds."""
    roles = {**unused, **{h.input: "power" for h in spec.heat_inputs}}
    have = {(tuple(e.where), e.expression) for e in spec.effects if e.kind == "expression"}
    helpers = helper_nodes(spec, lowered)
    return [(law, where) for law, where in learned_places(lowered, roles, scales)
            if (tuple(where), law.text(where)) not in have and not helpers & set(where)]
