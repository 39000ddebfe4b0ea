"""What the loop says to expect of a step's time (docs/cli.md, `investigate`).

Twice a step: before it starts, from the last step's wall time and how much dearer a fit
of the structure it chose was (`refit_cost_ratio`, `expected_step_seconds`); and once
its candidates are scored, when the refits first in line include nonlinear models of a
model that is linear so far (`refit_forecast`): their fits are extended Kalman filters or
simulations in substeps, several times a linear fit's, and the step's time jumps
there (PRBS1: the first step refitting three nonlinear candidates took 49 s after 15 s;
the generated nonlinear building's 418 s after 148 s).
"""

from __future__ import annotations

from dataclasses import dataclass

from ._candidates import Candidate
from ..model.effects import KINDS

# A measured cost ratio above this changes what the loop says to expect.
DEARER = 1.2
# A refit of a nonlinear model against a linear one's, where the loop has not measured
# one yet: on PRBS1, 3.7x (three nonlinear candidates' refits 33 s after three linear
# ones' 9 s) and 3.6x to 4.8x for one fit of the four-state model with and without a
# temperature-dependent conductance (36-48 s against 10 s, 16 substeps).
NONLINEAR_REFIT_COST = 4.0


def refit_cost_ratio(chosen: Candidate, cands: list[Candidate]) -> float:
    """Seconds per fit of `chosen`'s refit over those of every refitted candidate of its
    step (1 where not measured): how much dearer a fit of the structure the next step
    extends is than the average fit of the step that chose it (a nonlinear effect's
    refit, an extended Kalman filter in substeps, against linear ones)."""
    timed = _timed(cands)
    if not any(chosen is c for c in timed):
        return 1.0
    mean = sum(c.refit_seconds for c in timed) / sum(c.refit_fits for c in timed)
    own = chosen.refit_seconds / chosen.refit_fits
    return own / mean if mean > 0 else 1.0


def expected_step_seconds(last: dict, cost_ratio: float) -> float:
    """The next step's wall time (s) from the last step's record: its fitting phases (the
    refits and held-out folds, `phase_times_s`) scaled by `cost_ratio` where that is
    above 1, the rest as they were."""
    phases = last.get("phase_times_s") or {}
    fitting = phases.get("refits", 0.0) + phases.get("held-out folds", 0.0)
    return last["wall_time_s"] + max(cost_ratio - 1.0, 0.0) * fitting


def is_nonlinear(c: Candidate) -> bool:
    """Whether candidate `c` makes a model nonlinear: a nonlinear kind or a learned law."""
    return c.learned is not None or KINDS[c.kind].nonlinear


@dataclass(frozen=True)
class RefitCosts:
    """What a step's refits cost (`measured`): the refits phase's wall time (s), the
    seconds of fitting per candidate of linear models and of nonlinear ones (summed over
    each candidate's starts; None where none was refitted) and the fitting seconds
    summed over every refitted candidate (the fits run side by side: the wall time is
    less)."""

    wall: float
    linear: float | None
    nonlinear: float | None
    fitting: float

    @classmethod
    def measured(cls, cands: list[Candidate], refits_wall: float,
                 model_nonlinear: bool) -> RefitCosts | None:
        """The costs of the refitted `cands` of a step whose refits phase took
        `refits_wall` s, on a model nonlinear or not; None where nothing was timed."""
        timed = _timed(cands)
        if not timed or refits_wall <= 0:
            return None
        lin = [c.refit_seconds for c in timed if not (model_nonlinear or is_nonlinear(c))]
        nonlin = [c.refit_seconds for c in timed if model_nonlinear or is_nonlinear(c)]
        return cls(refits_wall, sum(lin) / len(lin) if lin else None,
                   sum(nonlin) / len(nonlin) if nonlin else None,
                   sum(c.refit_seconds for c in timed))


def refit_forecast(last: RefitCosts | None, first: list[Candidate],
                   model_nonlinear: bool) -> str | None:
    """What to say of a step's refits once scored, from the last step's costs `last`
    and the candidates `first` in line to be refitted, on a model nonlinear or not:
    where the model is linear, some of `first` are nonlinear and their expected refits
    (the last step's seconds per linear candidate, a nonlinear one's as measured or
    `NONLINEAR_REFIT_COST` times that, at the last step's ratio of wall time to fitting
    time) are over `DEARER` times the last step's refits, the expected time; else None
    (the time expected before the step holds)."""
    nonlinear = [c for c in first if is_nonlinear(c)]
    if model_nonlinear or last is None or last.linear is None or not nonlinear:
        return None
    measured = last.nonlinear is not None
    per_nonlinear = last.nonlinear if measured else NONLINEAR_REFIT_COST * last.linear
    fitting = (len(first) - len(nonlinear)) * last.linear + len(nonlinear) * per_nonlinear
    expect = fitting * last.wall / last.fitting
    if expect <= DEARER * last.wall:
        return None
    how = "as measured" if measured else "as such fits usually are"
    return (f"{len(nonlinear)} of the {len(first)} refits first in line are of nonlinear "
            f"models (an extended filter or simulation in substeps, "
            f"{per_nonlinear / last.linear:.1f}× a linear refit {how}): expect the refits "
            f"to take about {duration_text(expect)} or more (the last step's "
            f"{duration_text(last.wall)})")


def duration_text(seconds: float) -> str:
    """`"40 s"`, `"7 min"`, `"1.5 h"`."""
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _timed(cands: list[Candidate]) -> list[Candidate]:
    return [c for c in cands if c.refit_seconds is not None and c.refit_fits > 0]
