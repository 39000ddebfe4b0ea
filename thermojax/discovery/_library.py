"""The library of learned heat laws (docs/formats.md §3a): physically meaningful
functions of the node temperatures and the recorded columns that no kind of the
vocabulary names.

Each `LibraryTerm` is an `expression` template (the grammar of `model._expression`) of
a heat flow into node `{a}`, linear in a coefficient `c` (W per unit of the term; zero
is the null: no such heat) and, for some, with a shape parameter (an exponent, a
temperature rate) tried at a few values. Placeholders: `{a}` the node, `{b}` the far end
of one of its conduction paths (a node or a boundary column), `{u}` a recorded column
that is not a temperature. A user extends the library by appending to `LIBRARY`.

A term is a candidate like a kind of the vocabulary (`LearnedLaw`): score-tested at
every place, its best shape kept, the best refitted with `c` and its shape free, and
judged by the same selection rule.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model._expression import evaluate_numpy, parse, resolve
from ..model._spec import Effect, Parameter


@dataclass(frozen=True)
class LibraryTerm:
    name: str  # how the report names the law
    template: str  # heat into {a} (W), with coefficient `c` and the shape parameters
    places: str  # "pair" ({a}, {b}), "input" ({a}, {u}) or "node" ({a})
    shape: tuple[str, ...] = ()  # the shape parameters' names in the template
    trials: tuple[tuple[float, ...], ...] = ()  # their values tried by the score test
    # the kind of the vocabulary the law reduces to at some shape (where as a template of
    # {a}, {b}, {u}); the loop refits it beside the law, the simpler form
    nested: tuple[str, tuple[str, ...]] | None = None
    nested_shape: tuple[float, ...] | None = None  # that shape


def _grid(*axes):
    return tuple((a,) if len(axes) == 1 else (a, b) for a in axes[0]
                 for b in (axes[1] if len(axes) > 1 else (None,)))


LIBRARY: list[LibraryTerm] = [
    # conduction or convection that is not linear in the difference (natural convection:
    # n = 0.25 laminar, 0.33 turbulent; n = 1: a quadratic law)
    LibraryTerm("power law of a temperature difference",
                "c * abs({b} - {a})^n * ({b} - {a})", "pair", ("n",),
                _grid((0.25, 0.33, 0.5, 1.0))),
    # dissipation by a power of a column (I² R: p = 2; a fan's speed cubed: p = 3) that
    # grows with the node's temperature (a resistance or leakage rising with T)
    LibraryTerm("power of a column growing exponentially with temperature",
                "c * {u}^p * exp(k * ({a} - 25))", "input", ("p", "k"),
                _grid((1.0, 2.0, 3.0), (0.0, 0.01, 0.02, 0.05)),
                nested=("heat_source", ("{u}", "{a}")), nested_shape=(1.0, 0.0)),
    # self-heating that grows with the node's own temperature (leakage current)
    LibraryTerm("exponential of a temperature", "c * exp(k * ({a} - 25))", "node", ("k",),
                _grid((0.02, 0.05, 0.1))),
]


@dataclass(frozen=True)
class LearnedLaw:
    """One library term as a candidate kind: `kind` is "expression"; `where` is `[a, b]`
    for a pair (heat from `b` into `a`) or `[a]`, and for an input term the column is
    the template's."""

    term: LibraryTerm
    column: str | None = None  # {u}
    kind: str = "expression"
    # {u} is read as `(column / scale)` where given: the column's size in the data
    # (`column_scales`), so that `c` is the heat at that value. On the raw column, a
    # power law's c and exponent move together wherever the column's log varies little
    # around a large mean (a heater's thousands of watts).
    scale: float | None = None

    def text(self, where) -> str:
        fill = {"a": where[0]}
        if self.term.places == "pair":
            fill["b"] = where[1]
        if self.column is not None:
            fill["u"] = (self.column if self.scale is None else
                         f"({self.column} / "
                         f"{np.format_float_positional(self.scale, trim='-')})")
        return self.term.template.format(**fill)

    def effect(self, where, c: float = 0.0, shape: tuple | None = None,
               hold: str | None = None) -> Effect:
        """The `expression` effect at `where` with coefficient `c` and the shape values
        (default: the first trial)."""
        params = {"c": Parameter(float(c))}
        values = shape if shape is not None else (self.term.trials[0] if self.term.trials
                                                  else ())
        for name, v in zip(self.term.shape, values):
            params[name] = Parameter(float(v))
        return Effect("expression", tuple(where), params, hold=hold,
                      expression=self.text(where))

    def score_direction(self, ctx, where):
        """`("heat", [w per trial shape])`: the heat into `a` (and out of a node `b`)
        per unit `c`, at the fitted model's states."""
        cols = self.columns(where, ctx.is_node)
        names = [*ctx.names, *cols]
        values = np.concatenate([ctx.T, *(ctx.column(c)[..., None] for c in cols)], -1)
        out = []
        for shape in self.term.trials or (None,):
            eff = self.effect(where, 1.0, shape)
            tree = resolve(parse(eff.expression), names, [], list(eff.parameters))
            flow = evaluate_numpy(tree, values, values[..., :0],
                                  [p.value for p in eff.parameters.values()])
            w = np.zeros_like(ctx.T)
            w[..., ctx.node(where[0])] = flow
            if len(where) > 1 and ctx.is_node(where[1]):
                w[..., ctx.node(where[1])] -= flow
            out.append(w)
        return "heat", out

    def nested_kind(self, where) -> tuple[str, tuple[str, ...]] | None:
        """`(kind, where)` of the kind of the vocabulary this law reduces to, or None."""
        if self.term.nested is None:
            return None
        fill = {"a": where[0], "b": where[-1], "u": self.column}
        return self.term.nested[0], tuple(w.format(**fill) for w in self.term.nested[1])

    def is_nested_shape(self, shape) -> bool:
        """Whether the law at shape values `shape` is its nested kind (`nested_kind`)."""
        return (self.term.nested_shape is not None and shape is not None
                and tuple(shape) == self.term.nested_shape)

    def columns(self, where, is_node) -> list[str]:
        """The data columns the law reads at `where`."""
        far = where[1] if self.term.places == "pair" else None
        return [c for c in (far, self.column) if c is not None and not is_node(c)]

    def shape_of(self, j: int) -> tuple | None:
        """The shape values of score direction `j`."""
        return self.term.trials[j] if self.term.trials else None

    def direction_time_constant(self, ctx, j):
        return None


def column_scales(columns: dict[str, np.ndarray]) -> dict[str, float]:
    """Per data column (name -> values, any shape), its largest magnitude to three
    significant digits, the `scale` an input term reads it in; a column that is zero
    throughout, or not finite, gets none."""
    out = {}
    for name, values in columns.items():
        size = float(np.max(np.abs(values))) if np.size(values) else 0.0
        if np.isfinite(size) and size > 0.0:
            out[name] = float(f"{size:.3g}")
    return out


def learned_places(lowered, columns: dict[str, str], scales: dict[str, float] | None = None
                   ) -> list[tuple[LearnedLaw, tuple]]:
    """Every `(LearnedLaw, where)` the library allows on a (lowered) spec: pair terms on
    its conduction paths, input terms at every node for each column of `columns` (name ->
    role guess) that is not a temperature, read in its `scales` (`column_scales`) where
    given, node terms at every node."""
    from ..model.effects._base import conduction_paths

    out = []
    inputs = [c for c, role in columns.items() if role != "temperature"]
    scales = scales or {}
    for term in LIBRARY:
        if term.places == "pair":
            out += [(LearnedLaw(term), tuple(p)) for p in conduction_paths(lowered)]
        elif term.places == "input":
            out += [(LearnedLaw(term, u, scale=scales.get(u)), (n,)) for u in inputs
                    for n in lowered.node_names]
        else:
            out += [(LearnedLaw(term), (n,)) for n in lowered.node_names]
    return out
