"""What a candidate's refit says beyond its likelihood: the p-value of its likelihood
ratio (`rule_p_value`: Davies' bound where the effect's time constant does not exist
under the null), whether its effect only duplicates structure the model already has
(`duplicate_reason`), and which unmeasured nodes had bent their parameters to mimic it
(`absorbing_nodes`)."""

from __future__ import annotations

import math

import numpy as np

from ._candidates import Candidate, refit_p_value
from ._diagnostics import davies_p_value, davies_variation
from ._step import Step
from ..measurements._telemetry import Telemetry
from ..model._spec import EFFECT_KINDS, ModelSpec


DAVIES_KINDS = ("extra_node", "viscoelastic")  # a time constant absent under the null
VISCOELASTIC_TAU_RANGE = (1.0, 1e5)  # s, the τ search of `viscoelastic_candidate`


def rule_p_value(kind: str, lr: float, n_new: int, runs: list[Telemetry]) -> float:
    """p-value of a (deflated) likelihood-ratio statistic: Davies' bound for the kinds
    whose time constant does not exist under the null, else `refit_p_value`."""
    if kind not in DAVIES_KINDS:
        return refit_p_value(kind, lr, max(n_new, 1))
    if kind == "viscoelastic":
        lo, hi = VISCOELASTIC_TAU_RANGE
    else:  # an extra node's local time constant: from the sample period to the record
        lo = sample_period(runs)
        hi = sum(float(t.ts[-1] - t.ts[0]) for t in runs)
    return davies_p_value(lr, max(n_new - 1, 1), davies_variation(math.log(max(hi / lo, 1.0))))


def added_effect(spec: ModelSpec, c: Candidate):
    """The effect candidate `c` added to `spec` (the last of its kind at its place: a
    learned law may join another expression there)."""
    return [e for e in spec.effects if (e.kind, tuple(e.where)) == c.key][-1]


FAST_FRACTION = 0.2  # a mass or lag faster than this share of a sample period is unseen
MIN_RELAXATION_SAMPLES = 3.0  # a viscoelastic τ under this many samples is white noise
AT_BOUND = 1e-6  # a positive parameter below this share of its first guess sits at zero


def sample_period(runs: list[Telemetry]) -> float:
    """The shortest of the runs' median sample periods (s)."""
    return min(float(np.median(np.diff(t.ts))) for t in runs)


def duplicate_reason(c: Candidate, first_guess: dict, period: float) -> str:
    """Why the refitted effect of `c` (its `parameters`) only duplicates structure the
    model already has, or "" when it does not: an added mass or sensor lag whose time
    constant is far below the sample `period` (s), a viscoelastic τ below a few samples,
    or a positive parameter at its bound (zero) relative to its `first_guess`."""
    p = c.parameters or {}
    if c.kind == "extra_node" and c.result is not None:
        lowered = c.result.result.lowered_spec
        new = added_effect(c.result.spec, c).name
        g = sum(k.conductance.value for k in lowered.links if new in k.between) + sum(
            b.conductance.value for b in lowered.boundaries if b.node == new)
        tau = p["capacitance"] / g if g > 0 else math.inf
        if tau < FAST_FRACTION * period:
            return (f"duplicate: the added mass's local time constant, {tau:.3g} s, is far "
                    f"below the sample period ({period:g} s), so it only splits an existing "
                    "conductance")
    if c.kind == "sensor_lag" and p.get("time_constant", math.inf) < FAST_FRACTION * period:
        return (f"duplicate: a lag of {p['time_constant']:.3g} s is far below the sample "
                f"period ({period:g} s)")
    if c.kind == "viscoelastic" and p.get("time_constant", math.inf) < \
            MIN_RELAXATION_SAMPLES * period:
        return (f"duplicate: a relaxation time of {p['time_constant']:.3g} s is below "
                f"{MIN_RELAXATION_SAMPLES:g} samples ({period:g} s each): it follows the "
                "temperature like the static terms")
    for name in EFFECT_KINDS[c.kind].positive:
        guess = first_guess.get(name)
        if name in p and guess and p[name] < AT_BOUND * guess:
            return f"duplicate: {name} went to its bound (zero): the effect is absent"
    return ""


ABSORB_STDS = 3.0  # a shift beyond this many stds (and `ABSORB_SHARE`) is mimicry
ABSORB_SHARE = 0.1


def absorbing_nodes(step: Step, extended: Step) -> dict[str, list[str]]:
    """Unmeasured nodes of `step` whose own parameters (capacitance, the conductances
    touching them) moved when the candidate's effect was added, by more than
    `ABSORB_STDS` of their std and `ABSORB_SHARE` of their value: node -> parameters.
    Without the effect those parameters were bent to mimic it, so the node and the
    effect partly stand in for each other."""
    spec = step.spec
    measured = {s.node for s in spec.sensors}
    before, after = step.record["parameters"], extended.record["parameters"]
    out: dict[str, list[str]] = {}
    for node in spec.node_names:
        if node in measured:
            continue
        for name, p in before.items():
            group, _, rest = name.partition(".")
            key = rest.rpartition(".")[0]
            touches = (group == "nodes" and key == node) or (
                group in ("links", "boundaries") and node in key.split("-"))
            q = after.get(name)
            if not touches or q is None or not p.get("free") or p.get("std") is None:
                continue
            shift = abs(q["value"] - p["value"])
            if shift > ABSORB_STDS * p["std"] and shift > ABSORB_SHARE * abs(p["value"]):
                out.setdefault(node, []).append(name)
    return out
