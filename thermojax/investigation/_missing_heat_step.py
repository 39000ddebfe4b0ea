"""A step's missing heat: reconstructed where the residuals are not white
(`record_missing_heat`), searched at the file's values (`_file_values_step`) and offered
to the heat network (`_network_step`) when no candidate was supported, and described
where nothing explained it (`record_unexplained`, `_unexplained`)."""

from __future__ import annotations

from pathlib import Path

from ._candidates import Candidate
from ._diagnose_step import at_file_values, unused_columns
from ._held_out import _choose
from ._physical_range import data_span, reject_unphysical
from ._refits import _refit_side_by_side
from ._selection import judge, prefer_simpler_laws, prefer_vocabulary
from ._separation import separation_advice
from ._step import Step


def record_missing_heat(step: Step, out: Path | None, i: int, white_p: float, say):
    """When a column of `step` is not white, reconstruct the missing heat
    (`discovery.missing_heat`), write it as `step<i>_missing_heat.csv` in `out` and put
    its summary in the step's record (`missing_heat`). A failure is a note, not the end
    of the loop.

    **Returns:** the `MissingHeat`, or None (white, or the reconstruction failed)."""
    from ..discovery import missing_heat, write_missing_heat

    rec = step.record
    if all(p is not None and p > white_p for p in rec["whiteness_p"].values()):
        return None
    say(f"step {i}: reconstructing the missing heat")
    try:
        mh = missing_heat(step.result, say=say)
        name = f"step{i}_missing_heat.csv"
        if out is not None:
            write_missing_heat(mh, Path(out) / name)
        rec["missing_heat"] = mh.summary(name if out is not None else None)
        return mh
    except Exception as err:  # the reconstruction could not run: say why
        rec["missing_heat"] = {"file": None,
                               "note": f"could not reconstruct: {type(err).__name__}: {err}"[:300]}
        say(rec["missing_heat"]["note"])
        return None


def _file_values_step(current: Step, runs, cands: list[Candidate], likelihood, fdr,
                      white_p, initial, search, holdout_check, say, held_out
                      ) -> Candidate | None:
    """When no candidate was supported: the laws of the search on the missing heat of
    the step's structure at the file's values (`_diagnose_step.at_file_values`; the
    fitted model's missing heat is what its bent parameters left of a law), refitted
    and judged beside the step's candidates (whose own verdicts stand), and, if
    supported, held-out checked like any other.

    **Returns:** the chosen candidate, or None."""
    new = at_file_values(current, runs, initial, search, say)
    if not new:
        return None
    _refit_side_by_side(new, current, runs, likelihood,
                        set(unused_columns(current.spec, runs)), initial, say, white_p)
    kept = [(c.supported, c.note, c.tied_with) for c in cands]
    judge(cands + new, fdr, separation_advice)
    prefer_vocabulary(cands + new)
    prefer_simpler_laws(new)
    reject_unphysical(new, data_span(current.spec, runs))
    for c, (supported, note, tied) in zip(cands, kept):
        c.supported, c.note, c.tied_with = supported, note, tied
    cands += new
    new.sort(key=lambda c: (c.method != "refit", -c.score))
    return _choose(new, current, runs, likelihood, holdout_check, say, held_out)


def _network_step(current: Step, runs, mh, cands: list[Candidate], likelihood, fdr,
                  white_p, initial, holdout_check, say, held_out) -> Candidate | None:
    """When no candidate was supported: the heat network's proposal
    (`_network_candidate`), refitted and judged beside the step's candidates (the
    family of Benjamini-Hochberg holds them all; their own verdicts stand) and, if
    supported, held-out checked like any other. Its account goes into the step's
    record (`network`); a network that cannot run is a note, not the end of the loop.

    **Returns:** the chosen candidate, or None."""
    from ._network_candidate import network_candidate

    try:
        cand, current.record["network"] = network_candidate(current, runs, mh, say)
    except Exception as err:
        current.record["network"] = {
            "verdict": f"the heat network could not run: {type(err).__name__}: {err}"[:300]}
        say(current.record["network"]["verdict"])
        return None
    if cand is None:
        return None
    _refit_side_by_side([cand], current, runs, likelihood,
                        set(unused_columns(current.spec, runs)), initial, say, white_p)
    cand.add_note(f"proposed by the heat network at {current.record['network']['node']}",
                  first=True)  # after the refit, which writes its own note
    kept = [(c.supported, c.note, c.tied_with) for c in cands]
    judge(cands + [cand], fdr, separation_advice)
    prefer_vocabulary(cands + [cand])
    reject_unphysical([cand], data_span(current.spec, runs))
    for c, (supported, note, tied) in zip(cands, kept):
        c.supported, c.note, c.tied_with = supported, note, tied
    cands.append(cand)
    return _choose([cand], current, runs, likelihood, holdout_check, say, held_out)


def record_unexplained(step: Step, mh, say) -> None:
    """The step's `unexplained` list (spec §3a) when no candidate, of the vocabulary or
    the library, explained its non-white residuals: the missing heat described."""
    from ..discovery import unexplained

    if mh is None:
        return
    step.record["unexplained"] = unexplained(mh, step.record["missing_heat"]["file"])
    net = step.record.get("network") or {}
    for u in step.record["unexplained"]:
        if u["where"] == [net.get("node")] and "verdict" in net:
            u["network"] = net["verdict"]  # what the heat network made of it
        say(f"unexplained at {u['where'][0]}: {u['what']}")


def _unexplained(record: dict, white_p: float) -> str:
    bad = [c for c, p in record["whiteness_p"].items() if p is None or p <= white_p]
    return (f"the residuals of {', '.join(bad)} stay non-white: part of the error "
            "is not explained by any effect of the vocabulary with the data "
            "columns given (an unrecorded input, or physics outside the "
            "vocabulary).")
