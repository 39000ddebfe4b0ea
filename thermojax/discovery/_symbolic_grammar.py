"""The grammar the symbolic search builds heat laws from (docs/formats.md §3a,
docs/extensions.md): variables, primitive functions of one variable, and trees that
add products of them.

A law is a tree

    q = c₁ · f₁₁(v) · f₁₂(w) + c₂ · f₂₁(x) + …          (W, heat into a node)

whose leaves are **variables** (`Variable`: the node's temperature in °C and in kelvin,
its differences to its conduction neighbours, the recorded columns that are not
temperatures, each read in its size) and whose inner nodes are the operators `+` and
`×` over **primitives** of one variable (`PRIMITIVES`), each written with the grammar
of `model._expression` and holding at most one constant of its own:

| primitive | written                          | constant                    |
|-----------|----------------------------------|-----------------------------|
| `x`       | `x`                              |                             |
| `pow`     | `x^n`                            | exponent n (x ≥ 0)          |
| `spow`    | `abs(x)^n * x`                   | exponent n (an odd power)   |
| `exp`     | `exp(k * (x - 25))`, `exp(k * x)`| rate k (1/K or per unit)    |
| `arrh`    | `exp(-E * (1000 / x - 1000 / 298.15))` | E (kK), x in kelvin   |
| `sat`     | `x / (1 + b * abs(x))`           | saturation b (1/unit)       |
| `rat`     | `x / (1 + b * x)`                | b (x > 0)                   |
| `log`     | `log(x)`                         | (x > 0)                     |
| `inv`     | `1 / x`                          | (x > 0)                     |
| `abs`     | `abs(x)`                         |                             |

The coefficients `c` are linear (the search solves them by weighted least squares
for every value of the primitives' constants). The **complexity** of a law is the
number of nodes of its tree as written, each variable one leaf: `c * exp(k * x)` is 6,
`c * abs(d)^n * d` 8, a sum `c₁ f + c₂ g` adds one `+` and a coefficient. A shift
such as `- 25` or `- 1 / 298.15` is not counted: it only moves the coefficient to a
value at 25 °C, which keeps the refit well conditioned; likewise the `1000 /`, which
states E in kK.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model._expression import KELVIN

T_REF = 25.0  # °C, where an exponential's coefficient is the heat
K_REF = T_REF + KELVIN  # K, where an Arrhenius law's coefficient is the heat


@dataclass(frozen=True)
class Primitive:
    """One function of one variable: its name, how it is written (`{x}` the variable,
    `{k}` its constant), its cost in tree nodes, whether it holds a constant, and where
    it applies ("any", "nonnegative", "positive", "signed", "kelvin", "not_kelvin")."""

    name: str
    text: str
    cost: int
    constant: str | None  # the constant's parameter name stem, or None
    applies: str
    # the constant's starting values, in units of 1 / (the variable's spread) (`rate`,
    # `saturation`) or as they are (`exponent`)
    starts: tuple[float, ...] = ()
    start_unit: str = "one"
    # the constant as written is the fitted one times this (E in kK: a constant of
    # thousands on its own scale looks unidentifiable beside the logs of C and G)
    written: float = 1.0


PRIMITIVES: tuple[Primitive, ...] = (
    Primitive("x", "{x}", 1, None, "any"),
    Primitive("pow", "{x}^{k}", 3, "n", "nonnegative", (0.5, 1.0, 2.0)),
    Primitive("spow", "abs({x})^{k} * {x}", 6, "n", "signed", (-0.5, 0.25, 1.0)),
    Primitive("exp", "exp({k} * {x})", 4, "k", "not_kelvin", (-2.0, -0.5, 0.5, 2.0),
              "rate"),
    Primitive("arrh", "exp(-{k} * (1000 / {x} - 1000 / 298.15))", 4, "E", "kelvin",
              (10.0, 3.0, 1.0, -3.0), "inverse_rate", 1e-3),
    Primitive("sat", "{x} / (1 + {k} * abs({x}))", 8, "b", "signed", (0.1, 1.0, 5.0),
              "saturation"),
    Primitive("rat", "{x} / (1 + {k} * {x})", 7, "b", "positive", (0.1, 1.0, 5.0),
              "saturation"),
    Primitive("log", "log({x})", 2, None, "positive"),
    Primitive("inv", "1 / {x}", 3, None, "positive"),
    Primitive("abs", "abs({x})", 2, None, "signed"),
)
PRIMITIVE_INDEX = {p.name: i for i, p in enumerate(PRIMITIVES)}


@dataclass(frozen=True)
class Variable:
    """A leaf of the grammar: `name` as an expression reads it, `kind` ("celsius",
    "kelvin", "difference", "column"), its `values` (samples,) on the search's data, and
    how a library template writes it (`placeholder`: `{a}`, `kelvin({a})`,
    `({b} - {a})`, `{u}`), with the far end `far` of a difference and the `column` (read
    as `column / scale`) of a column."""

    name: str
    kind: str
    values: np.ndarray = field(compare=False, hash=False, repr=False)
    placeholder: str = ""
    far: str | None = None
    column: str | None = None
    scale: float | None = None

    @property
    def signed(self) -> bool:
        return bool(np.min(self.values) < 0.0)

    def admits(self, prim: Primitive) -> bool:
        """Whether `prim` applies to this variable's values."""
        v = self.values
        return {"any": True,
                "nonnegative": bool(np.min(v) >= 0.0 and np.max(v) > 0.0),
                "positive": bool(np.min(v) > 0.0),
                "signed": self.signed,
                "kelvin": self.kind == "kelvin",
                "not_kelvin": self.kind != "kelvin"}[prim.applies]

    def centre(self, prim: Primitive) -> float:
        """The shift of `prim` at this variable (not counted in the complexity): 25 °C in
        an exponential of a temperature, 1/298.15 K⁻¹ in an Arrhenius law, else 0."""
        if prim.name == "exp" and self.kind == "celsius":
            return T_REF
        if prim.name == "arrh":
            return 1.0 / K_REF
        return 0.0


# A factor is (primitive index, variable index); a term a sorted tuple of factors; a tree
# a sorted tuple of terms (its canonical form: equal laws are equal tuples).
Factor = tuple[int, int]
Term = tuple[Factor, ...]
Tree = tuple[Term, ...]


def canonical(terms) -> Tree:
    """The canonical form of a tree given as terms of factors (any order)."""
    return tuple(sorted(tuple(sorted(t)) for t in terms))


def complexity(tree: Tree) -> int:
    """Nodes of the tree as written (see the module's docstring)."""
    total = len(tree) - 1  # the + between terms
    for term in tree:
        total += 1 + len(term)  # its coefficient and the × joining it to each factor
        total += sum(PRIMITIVES[p].cost for p, _ in term)
    return total


def n_constants(tree: Tree) -> int:
    """The primitives' constants of `tree` (its coefficients not counted)."""
    return sum(PRIMITIVES[p].constant is not None for term in tree for p, _ in term)


def parameter_names(tree: Tree, taken=()) -> tuple[list[str], list[list[str | None]]]:
    """`(coefficient names, per term per factor its constant's name or None)`: `c` for
    the law's scale, `r2`, `r3`… for the later terms' ratios to the first, and the
    primitives' stems numbered from their second use; a name in `taken` (a node or a
    column) gets a `p_` in front."""
    used: set[str] = set(taken)

    def fresh(stem: str) -> str:
        name, i = stem, 2
        while name in used:
            name, i = f"{stem}{i}", i + 1
        if name in taken:
            name = "p_" + name
        used.add(name)
        return name

    coefs = [fresh("c")] + [fresh(f"r{j + 1}") for j in range(1, len(tree))]
    consts = [[fresh(PRIMITIVES[p].constant) if PRIMITIVES[p].constant else None
               for p, _ in term] for term in tree]
    return coefs, consts


def factor_text(prim: Primitive, var_text: str, const: str | None, kind: str) -> str:
    """One factor as written, its constant named `const`."""
    x = var_text
    if prim.name == "exp" and kind == "celsius":
        return f"exp({const} * ({x} - 25))"
    return prim.text.format(x=x, k=const)


def tree_text(tree: Tree, variables, placeholders: bool = False, taken=()) -> tuple[str, list]:
    """`(expression, parameter names in order)` of `tree` over `variables` (their names,
    or their `placeholder`s for a library template): `c * (F₁ + r2 * F₂)` for a sum, so
    that `c` is the law's scale (zero: no heat) and the law is linear in it."""
    coefs, consts = parameter_names(tree, taken)
    products = []
    for term, names in zip(tree, consts):
        parts = [factor_text(PRIMITIVES[p], variables[v].placeholder if placeholders
                             else variables[v].name, k, variables[v].kind)
                 for (p, v), k in zip(term, names)]
        products.append(" * ".join(parts))
    if len(tree) == 1:
        text = f"{coefs[0]} * {products[0]}"
    else:
        inner = " + ".join([products[0]] + [f"{r} * {p}" for r, p in
                                             zip(coefs[1:], products[1:])])
        text = f"{coefs[0]} * ({inner})"
    order = [coefs[0]] + [k for names in consts for k in names if k] + coefs[1:]
    return text, order


def primitives_for(variable: Variable) -> list[int]:
    """Indices of the primitives that apply to `variable`."""
    return [i for i, p in enumerate(PRIMITIVES) if variable.admits(p)]
