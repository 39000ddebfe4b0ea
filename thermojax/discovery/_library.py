"""The library of functions a node's missing heat is regressed on (docs/formats.md §3a).

Each entry is an expression template (the `expression` grammar, `model._expression`)
with placeholders `{a}` (the node), `{b}` (a neighbour node or a boundary column of it)
and `{u}` (a recorded input column). A user extends the library by appending a
`LibraryTerm` to `LIBRARY`; nothing else changes. Terms that a kind of the vocabulary
already names (a linear conductance, `heat_source`'s `g · u`, `radiation`'s kelvin⁴
difference) are listed too, so that the regression's explanation is judged against them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model._expression import evaluate_numpy, parse, resolve


@dataclass(frozen=True)
class LibraryTerm:
    template: str  # e.g. "abs({b} - {a})^0.25 * ({b} - {a})"
    places: str  # "pair" ({a}, {b}), "input" ({a}, {u}) or "node" ({a})


LIBRARY: list[LibraryTerm] = [
    LibraryTerm("({b} - {a})", "pair"),
    LibraryTerm("abs({b} - {a}) * ({b} - {a})", "pair"),
    LibraryTerm("abs({b} - {a})^0.25 * ({b} - {a})", "pair"),
    LibraryTerm("abs({b} - {a})^0.33 * ({b} - {a})", "pair"),
    LibraryTerm("kelvin({b})^4 - kelvin({a})^4", "pair"),
    LibraryTerm("{u}", "input"),
    LibraryTerm("{u}^2", "input"),
    LibraryTerm("abs({u})", "input"),
    LibraryTerm("{u}^2 * exp(0.02 * ({a} - 25))", "input"),
    LibraryTerm("{u} * exp(0.02 * ({a} - 25))", "input"),
    LibraryTerm("exp(0.02 * ({a} - 25))", "node"),
    LibraryTerm("({a} - 25)", "node"),
]


def library_columns(node: str, neighbours, inputs, temperatures: dict, columns: dict
                    ) -> dict[str, np.ndarray]:
    """Every library term at `node`, evaluated: expression text -> values (samples,).
    `temperatures` maps node names, `columns` input column names, to their samples."""
    names = [*temperatures, *columns]
    values = np.stack([*temperatures.values(), *columns.values()], -1)
    out = {}
    for term in LIBRARY:
        if term.places == "pair":
            fills = [dict(a=node, b=b) for b in neighbours]
        elif term.places == "input":
            fills = [dict(a=node, u=u) for u in inputs]
        else:
            fills = [dict(a=node)]
        for fill in fills:
            text = term.template.format(**fill)
            tree = resolve(parse(text), names, [], [])
            x = np.broadcast_to(evaluate_numpy(tree, values, values[..., :0], []),
                                values.shape[:-1])
            if np.all(np.isfinite(x)) and np.ptp(x) > 0:
                out[text] = np.asarray(x, float)
    return out
