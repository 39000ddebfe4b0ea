"""Is a heat input held as its data move? A check of the hold a model file left out.

A heat input's `hold` defaults to `"foh"` (piecewise linear between samples), right for
a continuously varying power. Switched heaters, PRBS power and power averaged over each
sample period are piecewise constant (`"zoh"`), and a file written without knowing the
difference fits them worse: a one-room model of a building log whose heater power is
logged as 5-minute averages reaches a Kalman −log L 176 higher under `"foh"` than under
`"zoh"`, and every later step of an investigation inherits the wrong inputs.

Where a file leaves a heat input's `hold` out, the same model is fitted again with
`"zoh"` on that column; a gain above `GAIN` in log L (the same parameters: a likelihood
ratio above e¹⁰) is said, with what to write. `fit` leaves the model as written (the
hold is the user's to state); `investigate`, whose every later step would inherit the
worse inputs, goes on from the better hold and says so (`better_holds`).
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable

import numpy as np

from ..model._spec import ModelSpec

#: log L the other hold must gain to be said (the same model, no parameter added).
GAIN = 10.0


def unwritten_foh_columns(spec: ModelSpec) -> list[str]:
    """Heat-input columns held `"foh"` only because the file did not say."""
    return sorted({h.input for h in spec.heat_inputs
                   if h.hold == "foh" and not h.hold_written})


def with_hold(spec: ModelSpec, column: str, hold: str) -> ModelSpec:
    """`spec` with every heat input of `column` held `hold` (as if written)."""
    return dataclasses.replace(spec, heat_inputs=tuple(
        dataclasses.replace(h, hold=hold, hold_written=True) if h.input == column else h
        for h in spec.heat_inputs))


@dataclasses.dataclass(frozen=True)
class HoldFinding:
    """A heat-input column the file left at `"foh"` whose data fit `gain` (log L) better
    held `"zoh"`; `text`: the words for the user."""

    column: str
    gain: float
    text: str


def better_holds(spec: ModelSpec, nll: float, refit: Callable[[ModelSpec], float],
                 say=lambda _msg: None) -> list[HoldFinding]:
    """Each heat input whose data fit clearly better held `"zoh"` than the `"foh"` the
    file defaulted to.

    **Arguments:**

    - `spec`: the model as the file gave it.
    - `nll`: −log L of its fit.
    - `refit`: `refit(spec) -> −log L` of the same fit (likelihood, runs) of another spec.
    - `say`: progress lines.
    """
    found = []
    for column in unwritten_foh_columns(spec):
        say(f"checking the hold of {column}: the file does not give one (\"foh\" taken); "
            "fitting it piecewise constant (\"zoh\")")
        with warnings.catch_warnings():  # the check's own fit: its remarks are not the user's
            warnings.simplefilter("ignore")
            other = refit(with_hold(spec, column, "zoh"))
        gain = nll - other
        if np.isfinite(gain) and gain > GAIN:
            found.append(HoldFinding(column, float(gain), (
                f"{column} is held \"foh\" (piecewise linear between samples) because the "
                "model file gives no `hold` for it, but the same model fits the data better "
                f"by {gain:.1f} in log L with hold = \"zoh\" (piecewise constant: switched "
                "power, or power averaged over each sample period). If that is how the "
                f"column is logged, write hold = \"zoh\" on its [[heat_inputs]] entry; "
                "to keep \"foh\" and silence this, write hold = \"foh\".")))
    return found


def hold_findings(spec: ModelSpec, nll: float, refit: Callable[[ModelSpec], float],
                  say=lambda _msg: None) -> list[str]:
    """The words of `better_holds` (same arguments), one per column."""
    return [f.text for f in better_holds(spec, nll, refit, say)]
