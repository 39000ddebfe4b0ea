"""Plateaus: fits that stop where the data cannot see a node.

A node whose own time constant `C / ΣG` is far below the sample period follows its
neighbours at once; one far beyond the longest run never moves. Either way its
capacitance and conductances change nothing the data can show, so the gradient along
them vanishes and a Gauss-Newton fit stops there, "converged", with them unidentifiable,
however far the point is from the data's optimum (a start 100× off in C and G does
this). After such a fit, `fit` restarts those nodes at a time constant the data can see
(the geometric mean of the sample period and the run's length, by scaling the node's
capacitance) and keeps the restart when it fits clearly better (`GAIN`, −log L). When
it does not, the node is genuinely beyond the data (a negligible mass) and the first fit
stands, with that said.
"""

from __future__ import annotations

import dataclasses
import math

from ..model._network import local_time_constants
from ..model._spec import ModelSpec, Parameter

FAST = 0.1  # a node faster than this many sample periods is invisible
SLOW = 10.0  # and one slower than this many run lengths
GAIN = 2.0  # −log L a restart must gain to replace the first fit


@dataclasses.dataclass(frozen=True)
class Invisible:
    """A node the data cannot see at the fitted values: its time constant `tau` (s)
    against the data's `sample_period` and `duration` (s)."""

    node: str
    tau: float
    sample_period: float
    duration: float

    def describe(self) -> str:
        where = (f"far below the {self.sample_period:g} s sample period"
                 if self.tau < self.sample_period else f"far beyond the {self.duration:g} s run")
        return f"the time constant C/ΣG of node '{self.node}' ({self.tau:.3g} s) is {where}"


def invisible_nodes(spec: ModelSpec, unidentifiable: set[str], sample_period: float,
                    duration: float) -> list[Invisible]:
    """Nodes of the fitted `spec` outside the data's time scales whose free capacitance is
    unidentifiable together with the rest of their parameters (`unidentifiable`: dotted
    names), the fastest first."""
    out = []
    for name, tau in local_time_constants(spec).items():
        node = next(n for n in spec.nodes if n.name == name)
        if node.capacitance.fixed or f"nodes.{name}.capacitance" not in unidentifiable:
            continue
        if FAST * sample_period <= tau <= SLOW * duration:
            continue
        out.append(Invisible(name, float(tau), sample_period, duration))
    return sorted(out, key=lambda v: v.tau)


def visible_start(spec: ModelSpec, invisible: list[Invisible]) -> ModelSpec:
    """`spec` with each invisible node's capacitance scaled so that its time constant is
    `sqrt(sample_period · duration)`."""
    moved = {v.node: math.sqrt(v.sample_period * v.duration) / v.tau for v in invisible}
    return spec.replace(nodes=tuple(
        dataclasses.replace(n, capacitance=Parameter(n.capacitance.value * moved[n.name],
                                                     False))
        if n.name in moved else n for n in spec.nodes))


def plateau_note(invisible: list[Invisible], gain: float | None,
                 restarted: bool = True) -> str:
    """What the message says: a restart that helped (`gain`, −log L), one that did not
    (None), or none tried (`restarted` False: a long log, where it would cost another
    fit of the whole log)."""
    what = "; ".join(v.describe() for v in invisible)
    if not restarted:
        return (f"; {what}: the data cannot see the node's parameters (not refitted from a "
                "time constant they could see, which on a log this long costs another fit "
                "of the whole log; fix them from design, or fit a shorter stretch to try)")
    if gain is not None:
        return (f"; restarted from a plateau where {what}, so that the data could not move "
                f"the node's parameters: −log L fell by {gain:.4g}. A start this far from the "
                "data can hide other optima: `--starts N` (multi-start) tries more")
    return (f"; {what}: the data cannot see the node's parameters (a restart where they "
            "could did not fit better)")
