"""`expression` (docs/formats.md §3a): a heat flow by a law written in the model file.

`where = [a]`: the expression is heat into node `a` (W); `where = [a, b]`: heat from `b`
into `a`, which node `b` loses. Its names are node temperatures (°C), input columns and
the parameters it declares (`model._expression`). Candidates of this kind are not
enumerated from places: the discovery stage proposes them from the missing heat.
"""

from __future__ import annotations

from .._expression import evaluate, parse, resolve
from ._base import PathEffect, Term


class Expression(PathEffect):
    kind = "expression"

    def term(self, spec, effect, slot):
        nodes, cols = spec.node_names, spec.input_columns
        params = tuple(effect.parameters)
        program = resolve(parse(effect.expression), nodes, cols, params)
        b = effect.where[1] if len(effect.where) > 1 else None
        return Term(self.kind, params, tuple(False for _ in params), slot,
                    a=nodes.index(effect.where[0]),
                    b=nodes.index(b) if b in nodes else -1,
                    column_b=cols.index(b) if b is not None and b not in nodes else -1,
                    program=program)

    def heat(self, term, values, T, u, network):
        n = len(term.parameters)
        flow = evaluate(term.program, T, u, values[term.slot:term.slot + n])
        return self.into_a(term, flow, T)

    def places(self, spec, columns):
        return []

    def initial_parameters(self, spec, where):
        return {}

    def score_direction(self, ctx, where):
        raise NotImplementedError("expression candidates are refitted, not score-tested")

