"""Effects with physical values only: the range check and the preference for physics.

Every effect kind declares where its parameters stay physical over the data
(`AbstractEffect.unphysical`): a sensor gain far from a calibration error, an offset
beyond any sensor's, a capacitance or conductance factor that falls below 2 % of its reference value or
crosses zero within the data's temperatures. A refitted candidate outside its range is
not supported, whatever its likelihood. A sensor artifact (gain, offset, lag) is not
chosen over a supported physical effect that the data support nearly as well (deflated
Δ BIC within `MIN_BIC_DROP`): a sensor error is the last explanation, not the first.

A refit is also judged as a whole model: an added node that its own heat inputs would
lift more than `MAX_RISE_K` over what it touches at the largest logged input is a lag
fitted with a vanishing capacitance and conductance, not a body (on a generated building
a heater's mass went from 1.1e6 J/K and 639 W/K to 112 J/K and 0.05 W/K, 10⁵ K over the
room at full power, when a later candidate was refitted beside it, and every fit after
needed four times the substeps).
"""

from __future__ import annotations

import numpy as np

from ..measurements._telemetry import Telemetry
from ..model._spec import ModelSpec
from ..model.effects import KINDS
from ..model.effects._base import DataSpan
from ._candidates import Candidate
from ._selection import MIN_BIC_DROP, deflated_delta_bic

SENSOR_ARTIFACTS = ("sensor_gain", "sensor_offset", "sensor_lag")


def data_span(spec: ModelSpec, runs: list[Telemetry]) -> DataSpan:
    """The temperatures (°C) the model's sensors and boundary inputs cover over every
    run, and every column's range."""
    columns = {}
    for t in runs:
        for name, v in t.channels.items():
            v = v[np.isfinite(v)]
            if v.size:
                lo, hi = columns.get(name, (np.inf, -np.inf))
                columns[name] = (min(lo, float(v.min())), max(hi, float(v.max())))
    temps = [columns[c] for c in (*spec.sensor_columns, *(b.input for b in spec.boundaries))
             if c in columns]
    low = min((lo for lo, _ in temps), default=0.0)
    high = max((hi for _, hi in temps), default=0.0)
    return DataSpan((low, high), columns)


# Kelvin an added node may sit over what it touches, its heat inputs at their largest
# logged magnitude: no body in a thermal network runs a thousand kelvin over its neighbours.
MAX_RISE_K = 1000.0


def lifted_node(lowered: ModelSpec, span: DataSpan) -> str | None:
    """Why an added node of the fitted (lowered) model is no body: the steady rise its own
    heat inputs give it over what it touches, Σ |gain| max |u| / Σ G, beyond `MAX_RISE_K`;
    None where every added node stays within it."""
    for node in (n for n in lowered.nodes if n.added_by_effect):
        heats = [h for h in lowered.heat_inputs if h.node == node.name]
        power = sum(abs(h.gain.value) * max(abs(v) for v in span.columns.get(h.input, (0, 0)))
                    for h in heats)
        g = (sum(k.conductance.value for k in lowered.links if node.name in k.between)
             + sum(b.conductance.value for b in lowered.boundaries if b.node == node.name))
        if power > 0 and (g <= 0 or power / g > MAX_RISE_K):
            return (f"the added node {node.name} would sit {power / g if g > 0 else np.inf:.3g}"
                    f" K above what it touches at the largest logged "
                    f"{', '.join(h.input for h in heats)} ({power:.3g} W through {g:.3g} W/K, "
                    f"{node.capacitance.value:.3g} J/K): a lag, not a body")
    return None


def reject_unphysical(cands: list[Candidate], span: DataSpan) -> None:
    """Mark supported candidates whose fitted parameters leave their kind's physical
    range, or whose fitted model lifts an added node beyond `MAX_RISE_K` (`lifted_node`),
    as not supported, saying why, in place."""
    for c in cands:
        if c.method != "refit" or not c.parameters:
            continue
        why = KINDS[c.kind].unphysical(tuple(c.where), c.parameters, span)
        if not why and c.learned is not None:
            why = KINDS["expression"].reverses_heat(c.learned.text(c.where), tuple(c.where),
                                                     c.parameters, span)
        if not why and c.result is not None:
            why = lifted_node(c.result.result.lowered_spec, span)
        if why:
            c.physical = False
            if c.supported:
                c.supported = False
            c.add_note(f"not physical: {why}", first=True)


def prefer_physics(cands: list[Candidate], separation_advice) -> None:
    """Where the best supported candidate is a sensor artifact and a supported physical
    effect lies within `MIN_BIC_DROP` of its deflated Δ BIC, the artifact steps aside
    (not supported, with the near-tie and what measurement separates them), in place.
    `separation_advice(kinds)`: the measurement that tells kinds apart."""
    supported = [c for c in cands if c.supported]
    if not supported or supported[0].kind not in SENSOR_ARTIFACTS:
        return
    artifact = supported[0]
    physical = [c for c in supported if c.kind not in SENSOR_ARTIFACTS]
    for p in physical:
        d = max(artifact.lr_deflation, p.lr_deflation, 1.0)
        a_bic, p_bic = deflated_delta_bic(artifact, d), deflated_delta_bic(p, d)
        if p_bic <= a_bic + MIN_BIC_DROP:
            advice = separation_advice({artifact.kind, p.kind})
            artifact.supported = False
            artifact.add_note(
                f"a physical effect, {p.kind} {list(p.where)}, explains nearly as much "
                f"(deflated Δ BIC {p_bic:.1f} against {a_bic:.1f}): the physical effect "
                f"is preferred to a sensor artifact; {advice}", first=True)
            p.add_note(f"preferred to the sensor artifact {artifact.kind} "
                       f"{list(artifact.where)} (deflated Δ BIC {a_bic:.1f}), which it "
                       "nearly ties", first=True)
            return
