"""The vocabulary of missing physics (docs/formats.md §3): one module per effect kind.

`KINDS[kind]` is the kind's `AbstractEffect`; `lower_effects(spec)` writes the
structural effects of a model as plain nodes, links, boundaries and heat inputs.
"""

from __future__ import annotations

from dataclasses import dataclass

from .._spec import Effect, ModelSpec, Parameter
from ._base import AbstractEffect, DataSpan, ParameterLink, Term
from .boundary import Boundary
from .capacitance_temperature import CapacitanceTemperature
from .conductance_input import ConductanceInput
from .conductance_temperature import ConductanceTemperature
from .expression import Expression
from .extra_node import ExtraNode
from .heat_source import HeatSource
from .radiation import Radiation
from .sensor_gain import SensorGain
from .sensor_lag import SensorLag
from .sensor_offset import SensorOffset
from .viscoelastic import Viscoelastic

KINDS: dict[str, AbstractEffect] = {k.kind: k for k in (
    ExtraNode(), Radiation(), ConductanceTemperature(), CapacitanceTemperature(), HeatSource(),
    Boundary(), ConductanceInput(), SensorLag(), SensorOffset(), SensorGain(), Viscoelastic(), Expression())}

__all__ = ["KINDS", "AbstractEffect", "DataSpan", "Lowered", "ParameterLink", "Term", "lower_effects",
           "raise_effects", "effect_parameter_name"]


def effect_parameter_name(effect: Effect, parameter: str) -> str:
    """The report's dotted name, `effects.<kind>.<where joined by ->.<parameter>`."""
    return f"effects.{effect.kind}.{'-'.join(effect.where)}.{parameter}"


@dataclass(frozen=True)
class Lowered:
    """A spec with its structural effects written as plain entries (`spec`), the original
    (`original`), and where each structural effect parameter lives (`links`: per effect
    index of `original.effects`, its `ParameterLink`s)."""

    spec: ModelSpec
    original: ModelSpec
    links: dict[int, list[ParameterLink]]

    def renames(self) -> dict[str, tuple[str, float, float]]:
        """lowered dotted name -> (effect dotted name, scale, power)."""
        out = {}
        for i, pls in self.links.items():
            e = self.original.effects[i]
            for pl in pls:
                out[pl.lowered] = (effect_parameter_name(e, pl.effect_parameter), pl.scale,
                                   pl.power)
        return out


def lower_effects(spec: ModelSpec) -> Lowered:
    """Write every structural effect of `spec` into plain entries, in file order; term
    effects (and `viscoelastic`) stay in `effects`."""
    out = spec.replace(effects=())
    kept = []
    links: dict[int, list[ParameterLink]] = {}
    for i, e in enumerate(spec.effects):
        kind = KINDS[e.kind]
        new, pls = kind.lower(out, e)
        if pls:
            out = new
            links[i] = pls
        else:
            kept.append(e)
            out = out.replace(effects=tuple(kept))
    return Lowered(out.replace(effects=tuple(kept)), spec, links)


def raise_effects(lowered: Lowered, fitted: ModelSpec) -> ModelSpec:
    """The original spec with every value taken from `fitted` (a fitted copy of
    `lowered.spec`): plain entries as they are, structural effect parameters read back
    from the entries they were lowered to."""
    from .._parameters_by_name import spec_parameters

    values = spec_parameters(fitted)
    orig = lowered.original
    term_effects = iter(fitted.effects)
    effects = []
    for i, e in enumerate(orig.effects):
        if i in lowered.links:
            params = dict(e.parameters)
            for pl in lowered.links[i]:
                p = values[pl.lowered]
                old = params.get(pl.effect_parameter)
                params[pl.effect_parameter] = Parameter(pl.scale * p.value ** pl.power,
                                                        old.fixed if old else False)
            effects.append(Effect(e.kind, e.where, params, e.name, e.hold))
        else:
            effects.append(next(term_effects))
    # plain entries: the original's, with values from the fitted lowered spec
    from .._parameters_by_name import with_spec_parameters

    base = with_spec_parameters(orig.replace(effects=()), values)
    return base.replace(effects=tuple(effects))
