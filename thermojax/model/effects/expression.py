"""`expression` (docs/formats.md §3a): a heat flow by a law written in the model file.

`where = [a]`: the expression is heat into node `a` (W); `where = [a, b]`: heat from `b`
into `a`, which node `b` loses. Its names are node temperatures (°C), input columns and
the parameters it declares (`model._expression`). Candidates of this kind are not
enumerated from places: the discovery stage proposes them from the missing heat.
"""

from __future__ import annotations

import numpy as np

from .._expression import evaluate, evaluate_numpy, names, parse, resolve
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

    def reverses_heat(self, text: str, where, parameters: dict, span) -> str | None:
        """Why a passive law between two temperatures (`where = [a, b]`, reading no
        other signal) carries heat from the colder to the warmer somewhere in the
        data's range (`span.temperatures`, °C), in words; else None. A law that reads a
        power or any other column is a source, and is not judged."""
        if len(where) != 2:
            return None
        tree = parse(text)
        params = tuple(parameters)
        if set(names(tree)) - set(where) - set(params):
            return None
        program = resolve(tree, tuple(where), (), params)
        lo, hi = span.temperatures
        grid = np.linspace(lo, hi, 25)
        ta, tb = np.meshgrid(grid, grid, indexing="ij")
        T = np.stack([ta.ravel(), tb.ravel()], axis=-1)
        q = np.asarray(evaluate_numpy(program, T, np.zeros((len(T), 0)),
                                      [parameters[k] for k in params]), float)
        dT = T[:, 1] - T[:, 0]
        scale = np.nanmax(np.abs(q)) if np.isfinite(q).any() else 0.0
        wrong = (q * dT < 0) & (np.abs(dT) > 0.5) & (np.abs(q) > 1e-3 * scale)
        if not wrong.any():
            return None
        k = int(np.flatnonzero(wrong)[0])
        return (f"the law carries {abs(q[k]):.3g} W from the colder to the warmer "
                f"({where[1]} at {T[k, 1]:.3g} °C, {where[0]} at {T[k, 0]:.3g} °C), within "
                "the data's temperatures: a passive path between two temperatures cannot")
