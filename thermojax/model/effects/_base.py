"""The abstract effect: what one kind of missing physics (docs/formats.md §3) contributes to a model.

An effect kind is a stateless object. It enters a model in one of two ways:

- *structural* kinds (`extra_node`, `heat_source`, `boundary`, `sensor_lag`) are
  lowered into plain nodes, links, boundaries and heat inputs (`lower`), so the
  model stays linear and keeps its exact discretization and fast Jacobians;
- *term* kinds keep a few parameters of their own in the model (`ThermalModel.effect_values`)
  and add either a heat flow (`heat`, W, for the nonlinear kinds) or an affine
  change of a sensor's reading (`output`, for offsets and gains).

Every kind also knows where it can act (`places`), a physical first guess of its
parameters (`initial_parameters`) and the direction in which it would first move
the outputs of a fitted model (`score_direction`), which the candidate search uses.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..._errors import InputError
from .._spec import EFFECT_KINDS, Effect, ModelSpec, Parameter

T_REF = 25.0  # °C, reference temperature of every temperature coefficient
KELVIN = 273.15
# A sensor's calibration slope error beyond this (20 %) is no calibration error: a sensor
# that sees 1 − 0.99 of its node's swing is a model explaining physics away.
MAX_SENSOR_GAIN = 0.2
# A sensor offset beyond this (°C) is a broken sensor or a wrong column, not an offset.
MAX_SENSOR_OFFSET = 10.0
# A temperature- or input-dependent factor (1 + c (x − x0)) must stay above this
# fraction of its value at the reference over the data's whole range: a capacitance or
# conductance that vanishes or crosses zero within the data is not a property of matter.
# (The range is the hull of every measured and boundary temperature, wider than any one
# node sees: on a building log a link's conductance with α = 0.037/K, well supported,
# falls to 7 % at the coldest outdoor sample, which its mean temperature never reaches.)
MIN_FACTOR = 0.02


@dataclass(frozen=True)
class DataSpan:
    """The ranges a fitted effect must stay physical over: `temperatures` (°C, (min,
    max)) of every measured and boundary temperature, and each data column's (min,
    max) in its own unit."""

    temperatures: tuple[float, float]
    columns: dict


def factor_leaves_range(coefficient: float, low: float, high: float, x0: float,
                        what: str, unit: str) -> str | None:
    """Why `1 + coefficient (x − x0)` falls below `MIN_FACTOR` for some x in [low, high],
    or None."""
    worst = min(1.0 + coefficient * (low - x0), 1.0 + coefficient * (high - x0))
    if worst >= MIN_FACTOR:
        return None
    at = low if 1.0 + coefficient * (low - x0) < 1.0 + coefficient * (high - x0) else high
    return (f"the {what} would fall to {worst:.0%} of its value at {x0:g} {unit} at "
            f"{at:.3g} {unit}, within the data's range [{low:.3g}, {high:.3g}] {unit}"
            + (" (it crosses zero there)" if worst <= 0 else ""))


@dataclass(frozen=True)
class ParameterLink:
    """An effect parameter carried by a lowered spec's parameter:
    `effect value = scale * lowered value ** power`."""

    effect_parameter: str
    lowered: str  # dotted report name in the lowered spec, e.g. "links.a-b.conductance"
    scale: float = 1.0
    power: float = 1.0


@dataclass(frozen=True)
class Term:
    """A term effect as the model holds it: static indices, parameters in `effect_values`.

    `slot`: index of the first parameter in `ThermalModel.effect_values`; `logs`: per
    parameter, whether the stored value is its log (positive parameters).
    `a`, `b`: node indices (`b` = -1 when the second place is an input column);
    `column_b`: input index of `b` when it is a column; `column`: the input index of a
    third place (`conductance_input`); `path`: ("link" | "boundary", index) of the
    conductance a temperature or input coefficient modulates. The sensor of an offset or
    gain is data, not structure (`ThermalModel.effect_sensors`): candidates of one kind
    at different sensors share one compiled program. A heat
    term's indices stay static: read as data, they slowed the per-sample Jacobian by
    15-45 % (measured on imu6).
    The names (`where`) live in the spec (`model._model.term_effects`).
    """

    kind: str
    parameters: tuple[str, ...]
    logs: tuple[bool, ...]
    slot: int
    a: int = -1
    b: int = -1
    column_b: int = -1
    column: int = -1
    path: tuple[str, int] = ("", -1)
    program: tuple = ()  # an `expression` effect's resolved tree (`model._expression`)


class AbstractEffect:
    """One kind of the vocabulary. Subclasses set `kind` and override what applies."""

    kind: str = ""
    nonlinear: bool = False  # adds a state-dependent heat flow (no exact discretization)

    @property
    def parameters(self) -> tuple[str, ...]:
        return EFFECT_KINDS[self.kind].parameters

    @property
    def positive(self) -> tuple[str, ...]:
        return EFFECT_KINDS[self.kind].positive

    # -- structure ---------------------------------------------------------------------
    def lower(self, spec: ModelSpec, effect: Effect) -> tuple[ModelSpec, list[ParameterLink]]:
        """Structural kinds: `spec` with the effect written as plain entries, and where
        each effect parameter now lives. Term kinds return `spec` unchanged."""
        return spec, []

    @property
    def is_term(self) -> bool:
        return False

    def term(self, spec: ModelSpec, effect: Effect, slot: int) -> Term:
        """Term kinds: the static description of the effect in `spec` (lowered)."""
        raise NotImplementedError

    def heat(self, term: Term, values, T, u, network):
        """Extra heat flow into every node (W), (nodes,), for nonlinear kinds."""
        return None

    # -- physical range ----------------------------------------------------------------
    def unphysical(self, where: tuple[str, ...], parameters: dict, span: DataSpan
                   ) -> str | None:
        """Why fitted `parameters` (name -> value in the file's units) at `where` are
        outside the range where this kind is physical over the data (`span`), in words;
        None where they are inside it. Kinds whose parameters are positive by
        construction are always inside."""
        return None

    def output(self, term: Term, values):
        """`(scale, offset)` added to its sensor's reading `scale · T + offset`, or None."""
        return None

    # -- candidates --------------------------------------------------------------------
    def places(self, spec: ModelSpec, columns: dict[str, str]) -> list[tuple[str, ...]]:
        """Every `where` the topology allows. `columns` maps each data column the model
        does not use to its role guess ("temperature" or "power")."""
        return []

    def initial_parameters(self, spec: ModelSpec, where: tuple[str, ...]) -> dict[str, float]:
        """A physical first guess of every parameter at this place."""
        raise NotImplementedError

    def held_by(self, spec: ModelSpec, where: tuple[str, ...]) -> bool:
        """Whether `spec` (lowered) already has this effect at `where`. Kinds a learned
        law nests answer it (`discovery.LibraryTerm.nested`); others need not."""
        return False

    def direction_time_constant(self, ctx, j: int) -> float | None:
        """The time constant (s) that score direction `j` of `score_direction` tried, for
        a kind whose own time constant the first-order score cannot know; else None."""
        return None

    def with_time_constant(self, spec: ModelSpec, where: tuple[str, ...], params: dict,
                           tau: float) -> dict:
        """`params` (first guesses) changed so that the effect's local time constant is
        `tau` (s): a refit start at the time constant the score test found best."""
        return params

    def score_direction(self, ctx, where: tuple[str, ...]):
        """How the effect first moves the model at its null value (no effect):
        `("heat", w)` with `w` (runs, T, nodes) W injected into the nodes, or
        `("output", d)` with `d` (runs, T, outputs) added to the readings, per unit of
        the effect's leading parameter. `ctx` is a `ScoreContext` (`_candidates`)."""
        raise NotImplementedError


def fail(spec: ModelSpec, effect: Effect, message: str) -> None:
    i = spec.effects.index(effect) if effect in spec.effects else 0
    raise InputError(message, file=spec.source, field=f"effects[{i}].where")


def param(effect: Effect, name: str, default: float) -> Parameter:
    return effect.parameters.get(name, Parameter(default))


def path_between(spec: ModelSpec, a: str, b: str):
    """`("link", i)` for the link a–b (either order) or `("boundary", i)` for node a's
    boundary to column b; None if there is none."""
    for i, link in enumerate(spec.links):
        if set(link.between) == {a, b}:
            return "link", i
    for i, bd in enumerate(spec.boundaries):
        if bd.node == a and bd.input == b:
            return "boundary", i
    return None


def conduction_paths(spec: ModelSpec) -> list[tuple[str, str]]:
    """Every link `(a, b)` and every boundary `(node, column)`, in file order."""
    return [tuple(k.between) for k in spec.links] + [(b.node, b.input) for b in spec.boundaries]


def total_capacitance(spec: ModelSpec) -> float:
    return float(sum(n.capacitance.value for n in spec.nodes))


def unique_name(spec: ModelSpec, stem: str) -> str:
    names = set(spec.node_names)
    name, i = stem, 2
    while name in names:
        name, i = f"{stem}_{i}", i + 1
    return name


class PathEffect(AbstractEffect):
    """Shared plumbing of the kinds acting between `a` and `b` (a node, or an input column
    of a boundary of `a`): indices, the far temperature, and the path's conductance."""

    nonlinear = True

    @property
    def is_term(self):
        return True

    def term(self, spec, effect, slot):
        a, b = effect.where[:2]
        nodes = spec.node_names
        cols = spec.input_columns
        path = path_between(spec, a, b) or ("", -1)
        third = cols.index(effect.where[2]) if len(effect.where) > 2 else -1
        return Term(self.kind, self.parameters,
                    tuple(p in self.positive for p in self.parameters), slot,
                    a=nodes.index(a), b=nodes.index(b) if b in nodes else -1,
                    column_b=cols.index(b) if b not in nodes else -1, column=third, path=path)

    @staticmethod
    def far(term: Term, T, u):
        """Temperature (°C) at the `b` end."""
        return T[term.b] if term.b >= 0 else u[term.column_b]

    @staticmethod
    def path_conductance(term: Term, network):
        kind, i = term.path
        return network.conductance[i] if kind == "link" else network.boundary_conductance[i]

    @staticmethod
    def into_a(term: Term, flow, T):
        """Heat `flow` (W) into `a`, and out of `b` when `b` is a node: (nodes,)."""
        import jax.numpy as jnp

        h = jnp.zeros_like(T).at[term.a].add(flow)
        return h.at[term.b].add(-flow) if term.b >= 0 else h

    def places(self, spec, columns):
        return conduction_paths(spec)

    def path_value(self, spec, where) -> float:
        kind, i = path_between(spec, *where[:2])
        return (spec.links[i].conductance.value if kind == "link"
                else spec.boundaries[i].conductance.value)

    @staticmethod
    def split(ctx, where, flow):
        """Score direction of a heat `flow` (runs, T) into `a` and out of node `b`."""
        w = np.zeros_like(ctx.T)
        w[..., ctx.node(where[0])] = flow
        if ctx.is_node(where[1]):
            w[..., ctx.node(where[1])] -= flow
        return w


class ScaledPathEffect(PathEffect):
    """A path whose conductance is `G0 (1 + s)`: the extra heat into `a` is
    `G0 · s · (T_b − T_a)` (W), with the scale `s` given by `scale` (traced) and
    `scale_direction` (the score test's NumPy form, per unit parameter)."""

    def scale(self, term, values, ta, tb, u):
        """`s` at one time (traced): `values` the effect parameters, `u` the inputs."""
        raise NotImplementedError

    def scale_direction(self, ctx, where, ta, tb):
        """`∂s/∂parameter` (NumPy, (runs, T)) for the score test."""
        raise NotImplementedError

    def heat(self, term, values, T, u, network):
        ta, tb = T[term.a], self.far(term, T, u)
        g0 = self.path_conductance(term, network)
        return self.into_a(term, g0 * self.scale(term, values, ta, tb, u) * (tb - ta), T)

    def score_direction(self, ctx, where):
        ta = ctx.T[..., ctx.node(where[0])]
        tb = ctx.temperature(where[1])
        g0 = ctx.path_conductance(where)
        flow = g0 * self.scale_direction(ctx, where, ta, tb) * (tb - ta)
        return "heat", [self.split(ctx, where, flow)]
