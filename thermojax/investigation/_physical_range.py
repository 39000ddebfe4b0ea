"""Effects with physical values only: the range check and the preference for physics.

Every effect kind declares where its parameters stay physical over the data
(`AbstractEffect.unphysical`): a sensor gain far from a calibration error, an offset
beyond any sensor's, a capacitance or conductance factor that falls below 2 % of its reference value or
crosses zero within the data's temperatures. A refitted candidate outside its range is
not supported, whatever its likelihood. A sensor artifact (gain, offset, lag) is not
chosen over a supported physical effect that the data support nearly as well (deflated
Δ BIC within `MIN_BIC_DROP`): a sensor error is the last explanation, not the first.
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


def reject_unphysical(cands: list[Candidate], span: DataSpan) -> None:
    """Mark supported candidates whose fitted parameters leave their kind's physical
    range as not supported, saying why, in place."""
    for c in cands:
        if c.method != "refit" or not c.parameters:
            continue
        why = KINDS[c.kind].unphysical(tuple(c.where), c.parameters, span)
        if not why and c.learned is not None:
            why = KINDS["expression"].reverses_heat(c.learned.text(c.where), tuple(c.where),
                                                     c.parameters, span)
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
