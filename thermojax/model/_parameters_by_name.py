"""Every parameter of a `ModelSpec` by its stable dotted report name (docs/formats.md §5)."""

from __future__ import annotations

import dataclasses

from ._spec import ModelSpec, Parameter, effect_labels


def spec_parameters(spec: ModelSpec) -> dict[str, Parameter]:
    """Dotted name -> `Parameter` for every number in `spec` (optional ones when set)."""
    out: dict[str, Parameter] = {}
    for n in spec.nodes:
        out[f"nodes.{n.name}.capacitance"] = n.capacitance
        for key in ("process_noise", "initial"):
            if getattr(n, key) is not None:
                out[f"nodes.{n.name}.{key}"] = getattr(n, key)
    for k in spec.links:
        out[f"links.{k.key}.conductance"] = k.conductance
    for b in spec.boundaries:
        out[f"boundaries.{b.key}.conductance"] = b.conductance
    for h in spec.heat_inputs:
        out[f"heat_inputs.{h.key}.gain"] = h.gain
    for s in spec.sensors:
        if s.noise is not None:
            out[f"sensors.{s.column}.noise"] = s.noise
    for e, label in zip(spec.effects, effect_labels(spec.effects)):
        for p, v in e.parameters.items():
            out[f"effects.{label}.{p}"] = v
    return out


def with_spec_parameters(spec: ModelSpec, values: dict[str, Parameter]) -> ModelSpec:
    """`spec` with the value of every parameter named in `values` replaced (its own
    fixed flag kept); names `values` lacks keep their value."""

    def upd(name: str, p: Parameter | None) -> Parameter | None:
        if name not in values:
            return p
        return Parameter(values[name].value, p.fixed if p is not None else values[name].fixed)

    nodes = tuple(dataclasses.replace(
        n, capacitance=upd(f"nodes.{n.name}.capacitance", n.capacitance),
        process_noise=upd(f"nodes.{n.name}.process_noise", n.process_noise),
        initial=upd(f"nodes.{n.name}.initial", n.initial)) for n in spec.nodes)
    links = tuple(dataclasses.replace(k, conductance=upd(f"links.{k.key}.conductance",
                                                           k.conductance)) for k in spec.links)
    bounds = tuple(dataclasses.replace(b, conductance=upd(f"boundaries.{b.key}.conductance",
                                                            b.conductance))
                   for b in spec.boundaries)
    heats = tuple(dataclasses.replace(h, gain=upd(f"heat_inputs.{h.key}.gain", h.gain))
                  for h in spec.heat_inputs)
    sensors = tuple(dataclasses.replace(s, noise=upd(f"sensors.{s.column}.noise", s.noise))
                    for s in spec.sensors)
    effects = tuple(dataclasses.replace(e, parameters={
        p: upd(f"effects.{label}.{p}", v) for p, v in e.parameters.items()})
        for e, label in zip(spec.effects, effect_labels(spec.effects)))
    return spec.replace(nodes=nodes, links=links, boundaries=bounds, heat_inputs=heats,
                        sensors=sensors, effects=effects)
