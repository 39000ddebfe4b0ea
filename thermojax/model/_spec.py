"""The model as written in a file: plain, validated Python data (no JAX).

`ModelSpec` is what `io.load_model` returns and `io.save_model` writes. It holds
physical values in the file's units (J/K, W/K, °C, s) and each parameter's
fixed/free flag; `ThermalNetwork.from_spec` turns it into a differentiable
module. Validation here covers everything that can be checked without data.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from .._errors import InputError

HOLDS = ("foh", "zoh")


@dataclass(frozen=True)
class Parameter:
    """A number in a model file: `value` in physical units, `fixed` if it is known."""

    value: float
    fixed: bool = False


@dataclass(frozen=True)
class Node:
    name: str
    capacitance: Parameter  # J/K
    process_noise: Parameter | None = None  # diffusion std, °C/√s
    # °C. None: estimated per run from the data (`fitting._initial_states`), or where
    # no data are given, the equilibrium at the first input sample given the other nodes.
    initial: Parameter | None = None
    initial_std: float | None = None  # °C
    # `initial = "steady"`: the node starts at the equilibrium of the first input sample.
    steady: bool = False
    # True where `initial` holds a start taken from the data (the first readings), not
    # the file: such a start is written back as absent, to be estimated again.
    initial_from_data: bool = False
    # True for a node an effect adds (an unmodelled mass, a sensor's own element): it
    # starts where it is at rest given the other nodes' starts (`ThermalModel.initial_state`).
    added_by_effect: bool = False


@dataclass(frozen=True)
class Link:
    between: tuple[str, str]
    conductance: Parameter  # W/K

    @property
    def key(self) -> str:
        return f"{self.between[0]}-{self.between[1]}"


@dataclass(frozen=True)
class Boundary:
    node: str
    input: str  # CSV column, °C
    conductance: Parameter  # W/K
    hold: str = "foh"

    @property
    def key(self) -> str:
        return f"{self.node}-{self.input}"


@dataclass(frozen=True)
class HeatInput:
    node: str
    input: str  # CSV column, W
    gain: Parameter  # dimensionless
    hold: str = "foh"
    # False where the file left `hold` out (the default taken): `fit` then checks the
    # other hold against the data (`fitting._hold_check`). Not part of the model's value.
    hold_written: bool = field(default=True, compare=False)

    @property
    def key(self) -> str:
        return f"{self.node}-{self.input}"


@dataclass(frozen=True)
class Sensor:
    node: str
    column: str  # CSV column, °C
    noise: Parameter | None = None  # std, °C; None: estimated


@dataclass(frozen=True)
class Effect:
    """An `[[effects]]` entry (docs/formats.md §3): its kind, where it acts, and its parameters."""

    kind: str
    where: tuple[str, ...]
    parameters: dict[str, Parameter] = field(default_factory=dict)
    name: str | None = None  # the new node's name (extra_node only)
    hold: str | None = None  # hold of a column the effect brings in ("foh" when None)
    expression: str | None = None  # the law of an `expression` effect (§3a)

    @property
    def key(self) -> str:
        return f"{self.kind}.{'-'.join(self.where)}"


def effect_labels(effects) -> list[str]:
    """Each effect's name in reports, `<kind>.<where joined by ->`, with `#2`, `#3`, ...
    on the second and later effects of the same kind and place (several `viscoelastic`
    terms on one node and column make a Prony series)."""
    seen: dict[str, int] = {}
    out = []
    for e in effects:
        seen[e.key] = seen.get(e.key, 0) + 1
        out.append(e.key if seen[e.key] == 1 else f"{e.key}#{seen[e.key]}")
    return out


@dataclass(frozen=True)
class Bias:
    """A `[[biases]]` entry (docs/formats.md §4): an inertial bias channel."""

    column: str
    temperature: str
    order: int = 3
    gradients: tuple[tuple[str, str], ...] = ()
    rates: tuple[str, ...] = ()
    noise: Parameter | None = None
    # fitted linear coefficients: poly0..polyN, then gradients, then rates (file order);
    # viscoelastic k's live on their effects. None: not fitted yet.
    coefficients: tuple[float, ...] | None = None


@dataclass(frozen=True)
class ModelSpec:
    """A whole model file. Lists keep the file's order, which fixes every index."""

    name: str
    nodes: tuple[Node, ...]
    links: tuple[Link, ...] = ()
    boundaries: tuple[Boundary, ...] = ()
    heat_inputs: tuple[HeatInput, ...] = ()
    sensors: tuple[Sensor, ...] = ()
    effects: tuple[Effect, ...] = ()
    biases: tuple[Bias, ...] = ()
    source: str | None = None  # file it came from, for messages

    @property
    def node_names(self) -> tuple[str, ...]:
        return tuple(n.name for n in self.nodes)

    @property
    def input_columns(self) -> tuple[str, ...]:
        """Distinct input columns (boundaries first, then heat inputs, then the columns
        effects read), in file order."""
        return tuple(self._column_holds())

    @property
    def input_holds(self) -> tuple[str, ...]:
        return tuple(self._column_holds().values())

    def hold_for(self, column: str, default: str | None = None) -> str:
        """The hold of an input `column`: the model's own where it already uses the
        column, else `default` (else `"foh"`, the spec's default)."""
        return self._column_holds().get(column, default or "foh")

    def _column_holds(self) -> dict[str, str]:
        holds: dict[str, str] = {}
        for entry in (*self.boundaries, *self.heat_inputs):
            holds.setdefault(entry.input, entry.hold)
        nodes = set(self.node_names) | {e.name for e in self.effects if e.name}
        sensors = set(self.sensor_columns) | {b.column for b in self.biases}
        for e in self.effects:
            if e.kind in _READS_COLUMNS:
                for w in (*e.where, *expression_columns(e, nodes)):
                    if w not in nodes and w not in sensors:
                        holds.setdefault(w, e.hold or "foh")
        return holds

    @property
    def boundary_columns(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(b.input for b in self.boundaries))

    @property
    def heat_columns(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(h.input for h in self.heat_inputs))

    @property
    def sensor_columns(self) -> tuple[str, ...]:
        return tuple(s.column for s in self.sensors)

    def replace(self, **changes) -> "ModelSpec":
        return dataclasses.replace(self, **changes)


# Kinds whose `where` may name an input column beyond the first place.
_READS_COLUMNS = ("extra_node", "radiation", "conductance_temperature", "heat_source",
                  "boundary", "conductance_input", "expression")


def expression_columns(effect: Effect, nodes) -> tuple[str, ...]:
    """The names an `expression` effect reads that are neither nodes nor its parameters:
    its input columns (none for another kind, or an expression that does not parse)."""
    if effect.kind != "expression" or effect.expression is None:
        return ()
    from ._expression import ExpressionError, names, parse

    try:
        used = names(parse(effect.expression))
    except ExpressionError:
        return ()
    return tuple(n for n in used if n not in nodes and n not in effect.parameters)


# ---------------------------------------------------------------------------
# The vocabulary of effects (docs/formats.md §3): where-arity and parameters per kind.
# `where` roles: "node", "node_or_input" (a node, or a boundary/heat input column),
# "input" (any data column), "column" (a sensor column).

@dataclass(frozen=True)
class EffectKind:
    where: tuple[tuple[str, ...], ...]  # allowed role patterns
    parameters: tuple[str, ...]  # parameter names
    positive: tuple[str, ...]  # parameters that must be > 0


EFFECT_KINDS: dict[str, EffectKind] = {
    "extra_node": EffectKind(
        where=(("node", "node_or_input"), ("node",)),
        parameters=("capacitance", "conductance", "conductance_b", "process_noise"),
        positive=("capacitance", "conductance", "conductance_b"),
    ),
    "radiation": EffectKind(where=(("node", "node_or_input"),), parameters=("coefficient",),
                            positive=("coefficient",)),
    "conductance_temperature": EffectKind(where=(("node", "node_or_input"),),
                                          parameters=("alpha",), positive=()),
    "capacitance_temperature": EffectKind(where=(("node",),), parameters=("beta",), positive=()),
    "heat_source": EffectKind(where=(("input", "node"),), parameters=("gain",),
                              positive=("gain",)),
    "boundary": EffectKind(where=(("input", "node"),), parameters=("conductance",),
                           positive=("conductance",)),
    "conductance_input": EffectKind(where=(("node", "node_or_input", "input"),),
                                    parameters=("coefficient",), positive=()),
    "sensor_lag": EffectKind(where=(("column",),), parameters=("time_constant",),
                             positive=("time_constant",)),
    "sensor_offset": EffectKind(where=(("column",),), parameters=("offset",), positive=()),
    "sensor_gain": EffectKind(where=(("column",),), parameters=("gain",), positive=()),
    "viscoelastic": EffectKind(where=(("node", "column"),), parameters=("time_constant", "k"),
                               positive=("time_constant",)),
    # §3a: a learned law; its parameters are the ones it declares
    "expression": EffectKind(where=(("node",), ("node", "node_or_input")), parameters=(),
                             positive=()),
}


# ---------------------------------------------------------------------------
# Validation


def validate(spec: ModelSpec, lines: dict[tuple[str, int], int] | None = None) -> ModelSpec:
    """Check a spec for every mistake that can be seen without data; return it unchanged.

    `lines` maps `(table, index)` to the file line where that entry starts, so a
    message can point at it. Raises `InputError`.
    """
    lines = lines or {}
    file = spec.source

    def fail(msg: str, table: str, index: int, fld: str) -> None:
        raise InputError(msg, file=file, line=lines.get((table, index)),
                         field=f"{table}[{index}].{fld}")

    if not spec.nodes:
        raise InputError("the model has no [[nodes]]; add at least one node with a capacitance.",
                         file=file, field="nodes")
    names = spec.node_names
    seen: set[str] = set()
    for i, node in enumerate(spec.nodes):
        if node.name in seen:
            fail(f"duplicate node name '{node.name}'; every node needs a unique name.",
                 "nodes", i, "name")
        seen.add(node.name)
        _positive(node.capacitance, fail, "nodes", i, "capacitance", "J/K")
        if node.process_noise is not None and not node.process_noise.value >= 0:
            fail("process_noise must be >= 0 (°C/√s).", "nodes", i, "process_noise")
        if node.initial_std is not None and not node.initial_std > 0:
            fail("initial_std must be > 0 (°C).", "nodes", i, "initial_std")

    def known(node: str, table: str, i: int, fld: str) -> None:
        if node not in seen:
            fail(f"unknown node '{node}'; the model's nodes are {list(names)}.", table, i, fld)

    link_pairs: set[frozenset[str]] = set()
    for i, link in enumerate(spec.links):
        if len(link.between) != 2:
            fail("a link needs exactly two nodes, between = [\"a\", \"b\"].", "links", i, "between")
        for n in link.between:
            known(n, "links", i, "between")
        if link.between[0] == link.between[1]:
            fail(f"a link joins '{link.between[0]}' to itself; name two different nodes.",
                 "links", i, "between")
        pair = frozenset(link.between)
        if pair in link_pairs:
            fail(f"a second link between {list(link.between)}; merge them into one conductance.",
                 "links", i, "between")
        link_pairs.add(pair)
        _positive(link.conductance, fail, "links", i, "conductance", "W/K")
    for i, b in enumerate(spec.boundaries):
        known(b.node, "boundaries", i, "node")
        _positive(b.conductance, fail, "boundaries", i, "conductance", "W/K")
        if b.hold not in HOLDS:
            fail(f"hold must be one of {list(HOLDS)}, got '{b.hold}'.", "boundaries", i, "hold")
    for i, h in enumerate(spec.heat_inputs):
        known(h.node, "heat_inputs", i, "node")
        if h.hold not in HOLDS:
            fail(f"hold must be one of {list(HOLDS)}, got '{h.hold}'.", "heat_inputs", i, "hold")
        if not h.gain.value > 0:
            fail("gain must be > 0 (the fraction of the measured power dissipated in the node).",
                 "heat_inputs", i, "gain")
    holds: dict[str, str] = {}
    for table, entries in (("boundaries", spec.boundaries), ("heat_inputs", spec.heat_inputs)):
        for i, e in enumerate(entries):
            if e.input in names:
                fail(f"input column '{e.input}' has the name of a node; rename the column.",
                     table, i, "input")
            if holds.setdefault(e.input, e.hold) != e.hold:
                fail(f"column '{e.input}' is used with holds '{holds[e.input]}' and '{e.hold}'; "
                     "a column must have one hold.", table, i, "hold")
    if set(spec.boundary_columns) & set(spec.heat_columns):
        both = sorted(set(spec.boundary_columns) & set(spec.heat_columns))
        raise InputError(f"column(s) {both} are used both as a boundary temperature and as a "
                         "heat input; a column is either °C or W.", file=file, field="heat_inputs")
    sensor_cols: set[str] = set()
    for i, s in enumerate(spec.sensors):
        known(s.node, "sensors", i, "node")
        if s.column in sensor_cols:
            fail(f"duplicate sensor column '{s.column}'.", "sensors", i, "column")
        if s.column in holds:
            fail(f"sensor column '{s.column}' is also an input column.", "sensors", i, "column")
        sensor_cols.add(s.column)
        if s.noise is not None and not s.noise.value > 0:
            fail("noise must be > 0 (std, °C).", "sensors", i, "noise")
    _check_grounded(spec, fail)
    _validate_effects(spec, fail, set(names), set(holds), sensor_cols)
    _validate_biases(spec, fail, set(names), set(holds) | sensor_cols)
    return spec


def _positive(p: Parameter, fail, table: str, i: int, fld: str, unit: str) -> None:
    if not (p.value > 0 and p.value < float("inf")):
        fail(f"{fld} must be a positive number of {unit}, got {p.value}.", table, i, fld)


def _check_grounded(spec: ModelSpec, fail) -> None:
    """Every node needs a conduction path to a boundary, else A is singular."""
    names = spec.node_names
    neighbours: dict[str, set[str]] = {n: set() for n in names}
    for link in spec.links:
        a, b = link.between
        neighbours[a].add(b)
        neighbours[b].add(a)
    grounded = {b.node for b in spec.boundaries}
    for e in spec.effects:  # an extra boundary path grounds its node too
        # (an unknown node here is reported by _validate_effects, with its line)
        if e.kind == "boundary" and len(e.where) == 2 and e.where[1] in neighbours:
            grounded.add(e.where[1])
    reached = set(grounded)
    frontier = list(grounded)
    while frontier:
        for m in neighbours[frontier.pop()]:
            if m not in reached:
                reached.add(m)
                frontier.append(m)
    for i, node in enumerate(spec.nodes):
        if node.name not in reached:
            fail(f"node '{node.name}' has no conduction path to any boundary, so its temperature "
                 "is undetermined (singular network). Link it to a node that reaches a "
                 "[[boundaries]] entry, or give it a boundary.", "nodes", i, "name")


def _validate_effects(spec, fail, nodes: set[str], inputs: set[str], sensors: set[str]) -> None:
    new_nodes: set[str] = set()
    for i, e in enumerate(spec.effects):
        kind = EFFECT_KINDS.get(e.kind)
        if kind is None:
            fail(f"unknown effect kind '{e.kind}'; the vocabulary is {sorted(EFFECT_KINDS)}.",
                 "effects", i, "kind")
        all_nodes = nodes | new_nodes
        patterns = [p for p in kind.where if len(p) == len(e.where)]
        if not patterns:
            arities = sorted({len(p) for p in kind.where})
            fail(f"'{e.kind}' takes where = a list of {' or '.join(map(str, arities))} names, "
                 f"got {list(e.where)}.", "effects", i, "where")
        if e.kind == "viscoelastic" and not any(b.column == e.where[1] for b in spec.biases):
            fail(f"viscoelastic acts on bias column '{e.where[1]}', which needs a [[biases]] "
                 "entry for that column; add one, or name the column of an existing "
                 "[[biases]] entry.", "effects", i, "where")
        for role, name in zip(patterns[0], e.where):
            ok = {"node": name in all_nodes,
                  "node_or_input": name in all_nodes or name in inputs or name not in sensors,
                  "input": name not in all_nodes and name not in sensors,
                  "column": name in sensors or any(b.column == name for b in spec.biases)}[role]
            if not ok:
                what = {"node": "a node", "node_or_input": "a node or an input column",
                        "input": "a data column (not a node or sensor)",
                        "column": "a sensor or bias column"}[role]
                fail(f"'{name}' should be {what} for '{e.kind}'.", "effects", i, "where")
        if e.kind == "expression":
            _validate_expression(e, fail, i, all_nodes, sensors)
        for pname, p in e.parameters.items():
            if pname not in kind.parameters and e.kind != "expression":
                fail(f"'{e.kind}' has no parameter '{pname}'; its parameters are "
                     f"{list(kind.parameters)}.", "effects", i, pname)
            if pname in kind.positive and not p.value > 0:
                fail(f"{pname} must be > 0, got {p.value}.", "effects", i, pname)
        if e.kind == "extra_node":
            if not e.name:
                fail("extra_node needs a `name` for the new node.", "effects", i, "name")
            if e.name in all_nodes:
                fail(f"extra_node name '{e.name}' is already a node.", "effects", i, "name")
            new_nodes.add(e.name)


def _validate_expression(e: Effect, fail, i: int, nodes: set[str], sensors: set[str]) -> None:
    from ._expression import ExpressionError, constant_fault, names, parse

    if e.expression is None:
        fail("an expression effect needs `expression`, a formula of node temperatures, "
             "input columns and its parameters, e.g. \"h * (T_fluid - housing)\".",
             "effects", i, "expression")
    try:
        used = names(parse(e.expression))
    except ExpressionError as err:
        fail(f"cannot read the expression {e.expression!r}: {err}.", "effects", i, "expression")
    fault = constant_fault(parse(e.expression))
    if fault is not None:
        fail(f"the expression {e.expression!r} cannot be evaluated: {fault}; fix the "
             "formula.", "effects", i, "expression")
    for name in used:
        if name in sensors and name not in nodes and name not in e.parameters:
            fail(f"'{name}' is a sensor column, a measurement the model explains; an "
                 "expression may read node temperatures, input columns and its parameters.",
                 "effects", i, "expression")
    for pname in e.parameters:
        if pname in nodes:
            fail(f"parameter '{pname}' has the name of a node; rename it.", "effects", i,
                 f"parameters.{pname}")
        if pname not in used:
            fail(f"parameter '{pname}' does not appear in the expression, so no data can "
                 "determine it; remove it or use it.", "effects", i, f"parameters.{pname}")


def _validate_biases(spec, fail, nodes: set[str], used: set[str]) -> None:
    for i, b in enumerate(spec.biases):
        if b.temperature not in nodes:
            fail(f"unknown node '{b.temperature}'.", "biases", i, "temperature")
        if not (isinstance(b.order, int) and 0 <= b.order <= 9):
            fail(f"order must be an integer from 0 to 9, got {b.order}.", "biases", i, "order")
        for pair in b.gradients:
            if len(pair) != 2 or any(n not in nodes for n in pair):
                fail(f"gradients entries are pairs of nodes, got {list(pair)}.",
                     "biases", i, "gradients")
        for n in b.rates:
            if n not in nodes:
                fail(f"unknown node '{n}' in rates.", "biases", i, "rates")
        if b.column in used:
            fail(f"bias column '{b.column}' is already a sensor or input column.",
                 "biases", i, "column")
        if b.noise is not None and not b.noise.value > 0:
            fail("noise must be > 0.", "biases", i, "noise")
