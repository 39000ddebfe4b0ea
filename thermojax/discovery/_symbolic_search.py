"""A search over heat laws that no list holds (docs/formats.md §3a, docs/extensions.md):
expression trees of the grammar `_symbolic_grammar`, their constants fitted to a
target heat (`_symbolic_fit`), ranked by fit against complexity.

The target is a heat with its std per sample: in the loop, the missing heat at a node
(`missing_heat`) over the smoothed temperatures and the recorded columns
(`heat_variables`). The search is generational:

- generation 0: every primitive of every variable, alone, and the forms of today's
  function library (`LIBRARY`: an odd power of a difference, a column's power times an
  exponential of the node's temperature, an exponential of the temperature), so that
  nothing the library finds is lost;
- each later generation: the laws of the *front* (the best fit at each complexity,
  kept only where it fits better than every simpler law) and the best few at each
  complexity are varied: a factor multiplied in, a term added (a second mechanism), a
  primitive or a variable changed, a factor or a term dropped. New laws are fitted, a
  shape at a time.

It stops at its budget (`evaluations` laws or `seconds`), when a generation brings no
new law, or at `generations`; it says its progress through `say`, and an interruption
(Ctrl-C) returns the front found so far. The random choices (which variations are
tried when there are more than `population`, which starts of the constants) come from
`random_state`: the same data and `random_state` give the same front.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from ._library import LearnedLaw, LibraryTerm
from ._symbolic_fit import MAX_PER_TERM, MAX_TERMS, fit_shape, primitive_tables
from ._symbolic_grammar import (PRIMITIVE_INDEX, PRIMITIVES, Tree, Variable, canonical,
                                complexity, n_constants, primitives_for, tree_text)
from ..model._expression import KELVIN, evaluate_numpy, parse, resolve

MAX_SAMPLES = 300  # samples the search fits on (evenly spaced over the runs)
BEAM = 3  # laws kept as parents at each complexity, besides the front
# A law joins the front only where its cost is this share below that of every simpler
# law: a finer fit of the noise is no law.
FRONT_GAIN = 0.01
ADEQUATE = 0.05  # `SymbolicFront.best`: a cost within this share of the lowest is adequate


@dataclass(frozen=True)
class FoundLaw:
    """One law the search fitted: its tree, complexity, weighted sum of squares `cost`
    and R² against the target (the share it explains of the weighted sum of squares the
    nuisance heats leave), its expression over the variables' names with its
    parameter values (`parameters`, name -> value, in the expression's order), its
    expression as a library template (`template`, placeholders `{a}`, `{b}`, `{u}`) and
    what it reads (`far`: the far end of its difference, `column`, `scale`)."""

    tree: Tree
    complexity: int
    cost: float
    r2: float
    expression: str
    parameters: dict
    template: str = ""
    far: str | None = None
    column: str | None = None
    scale: float | None = None
    stds: dict = field(default_factory=dict)  # parameter -> std from the regression

    @property
    def n_parameters(self) -> int:
        return len(self.parameters)

    def as_json(self) -> dict:
        return {"expression": self.expression, "complexity": self.complexity,
                "cost": self.cost, "r2": self.r2, "parameters": dict(self.parameters),
                "parameter_stds": dict(self.stds)}


@dataclass
class SymbolicFront:
    """What `symbolic_search` returns: the Pareto front (best fit per complexity, each
    better than every simpler law, simplest first), how many laws were fitted, over how
    many generations and seconds, and whether it was interrupted or stopped by its
    budget."""

    front: list[FoundLaw]
    evaluated: int
    generations: int
    seconds: float
    stopped: str  # "budget", "seconds", "exhausted", "generations", "interrupted"
    n_samples: int = 0
    # the best law of each complexity, on the front or not (simplest first): the laws a
    # caller may judge by other evidence than the fit to the target (the loop's score
    # test through the dynamics)
    leaders: list[FoundLaw] = field(default_factory=list)

    def best(self, k: int = 3, adequate: float = ADEQUATE) -> list[FoundLaw]:
        """The `k` laws of the front most worth refitting, simplest first: the simplest
        law whose cost is within `adequate` (a share) of the front's lowest, the front's
        knee (the largest drop of log cost per unit of complexity from the next simpler
        law), then the next adequate laws by complexity."""
        if not self.front:
            return []
        lowest = min(law.cost for law in self.front)
        adequate = [i for i, law in enumerate(self.front)
                    if law.cost <= lowest * (1.0 + adequate)]
        drops = [(math.log(max(self.front[i - 1].cost, 1e-300)) -
                  math.log(max(self.front[i].cost, 1e-300))) /
                 max(self.front[i].complexity - self.front[i - 1].complexity, 1)
                 for i in range(1, len(self.front))]
        knee = [1 + int(np.argmax(drops))] if drops else []
        picked = list(dict.fromkeys(adequate[:1] + knee + adequate[1:]))[:k]
        return [self.front[i] for i in sorted(picked)]

    def as_json(self) -> dict:
        return {"front": [law.as_json() for law in self.front], "evaluated": self.evaluated,
                "generations": self.generations, "seconds": self.seconds,
                "stopped": self.stopped, "n_samples": self.n_samples}


def _subsample(n: int, limit: int) -> np.ndarray:
    return np.arange(n) if n <= limit else np.unique(np.linspace(0, n - 1, limit).astype(int))


class _Search:
    """The state of one search: the data, every law fitted so far (tree -> (cost, θ,
    β)), and the budget."""

    def __init__(self, variables, y, std, nuisance, random_state, max_terms, max_factors,
                 max_complexity):
        keep = _subsample(len(y), MAX_SAMPLES)
        self.variables = [Variable(v.name, v.kind, np.asarray(v.values, float)[keep],
                                   v.placeholder, v.far, v.column, v.scale)
                          for v in variables]
        self.tables = primitive_tables(self.variables)
        self.y = np.asarray(y, float)[keep]
        std = np.asarray(std, float)[keep]
        floor = 0.1 * float(np.median(std[std > 0])) if np.any(std > 0) else 1.0
        self.w = 1.0 / np.maximum(std, floor)
        Z = np.zeros((len(keep), 0)) if nuisance is None else \
            np.asarray(nuisance, float).reshape(-1, np.shape(nuisance)[-1])[keep]
        self.Zw = Z * self.w[:, None]
        self.yw = self.y * self.w
        # R² is the share the law explains of what the nuisance heats leave (of the
        # target's spread without them)
        if self.Zw.shape[1]:
            beta = np.linalg.lstsq(self.Zw, self.yw, rcond=None)[0]
            self.total = float(np.sum((self.yw - self.Zw @ beta) ** 2)) or 1.0
        else:
            self.total = float(np.sum((self.yw - np.average(self.yw)) ** 2)) or 1.0
        self.rng = np.random.default_rng(random_state)
        self.max_terms, self.max_factors = max_terms, max_factors
        self.max_complexity = max_complexity
        self.done: dict[Tree, tuple] = {}
        self.prims = [primitives_for(v) for v in self.variables]

    def allowed(self, tree: Tree) -> bool:
        vars_in = [v for term in tree for _, v in term]
        return (len(tree) <= min(self.max_terms, MAX_TERMS)
                and len(vars_in) <= self.max_factors
                and all(len(term) <= MAX_PER_TERM for term in tree)
                and complexity(tree) <= self.max_complexity
                # a variable once per term: x·f(x) is f's own variation
                and all(len({v for _, v in term}) == len(term) for term in tree)
                and len(set(tree)) == len(tree))

    def evaluate(self, trees: list[Tree]) -> None:
        """Fit the trees of `trees` not fitted yet (one program for all: `fit_shape`)."""
        new = [t for t in dict.fromkeys(trees) if t not in self.done]
        if new:
            for t, got in zip(new, fit_shape(new, self.variables, self.tables, self.yw,
                                             self.w, self.Zw, self.rng)):
                self.done[t] = got

    def leaders(self) -> list[Tree]:
        """The best law of each complexity, simplest first."""
        best: dict[int, Tree] = {}
        for t, (cost, _, _) in self.done.items():
            k = complexity(t)
            if np.isfinite(cost) and (k not in best or (cost, t) < (self.done[best[k]][0],
                                                                    best[k])):
                best[k] = t
        return [best[k] for k in sorted(best)]

    def front(self) -> list[Tree]:
        """The Pareto front of the laws fitted so far, simplest first: the best law of
        each complexity whose cost is `FRONT_GAIN` below every simpler one's."""
        out, floor = [], math.inf
        for t in self.leaders():
            cost = self.done[t][0]
            if cost < floor * (1.0 - FRONT_GAIN):
                out.append(t)
                floor = cost
        return out

    def parents(self) -> list[Tree]:
        """The front and the `BEAM` best laws of each complexity."""
        by_k: dict[int, list[Tree]] = {}
        for t, (cost, _, _) in self.done.items():
            if np.isfinite(cost):
                by_k.setdefault(complexity(t), []).append(t)
        out = list(self.front())
        for k, ts in sorted(by_k.items()):
            out += sorted(ts, key=lambda t: (self.done[t][0], t))[:BEAM]
        return list(dict.fromkeys(out))

    def singles(self) -> list[tuple[int, int]]:
        return [(p, v) for v in range(len(self.variables)) for p in self.prims[v]]

    def variations(self, tree: Tree) -> list[Tree]:
        """Every law one variation away from `tree` (see the module's docstring)."""
        out = []
        singles = self.singles()
        n_factors = sum(len(t) for t in tree)
        for i, term in enumerate(tree):
            rest = tree[:i] + tree[i + 1:]
            if n_factors < self.max_factors:
                out += [canonical(rest + (term + (f,),)) for f in singles]  # × a factor
            for j, (p, v) in enumerate(term):
                others = term[:j] + term[j + 1:]
                out += [canonical(rest + (others + ((q, v),),)) for q in self.prims[v]
                        if q != p]  # another primitive
                out += [canonical(rest + (others + ((p, u),),))
                        for u in range(len(self.variables))
                        if u != v and p in self.prims[u]]  # another variable
                if others:
                    out.append(canonical(rest + (others,)))  # a factor dropped
            if rest:
                out.append(canonical(rest))  # a term dropped
        if len(tree) < self.max_terms and n_factors < self.max_factors:
            out += [canonical(tree + (((p, v),),)) for p, v in singles]  # a mechanism added
        return [t for t in dict.fromkeys(out) if self.allowed(t) and t not in self.done]


def library_forms(variables) -> list[Tree]:
    """Today's function library (`LIBRARY`) in the grammar: `c |d|^n d` for each
    difference `d`, `c u^p exp(k (T − 25))` for each nonnegative column `u`, and
    `c exp(k (T − 25))`, at the node's temperature `T`."""
    kinds = {i: v.kind for i, v in enumerate(variables)}
    node = [i for i, k in kinds.items() if k == "celsius"]
    out = []
    for i, v in enumerate(variables):
        if v.kind == "difference" and v.admits(PRIMITIVES[PRIMITIVE_INDEX["spow"]]):
            out.append(canonical([[(PRIMITIVE_INDEX["spow"], i)]]))
        if v.kind == "column" and v.admits(PRIMITIVES[PRIMITIVE_INDEX["pow"]]):
            out += [canonical([[(PRIMITIVE_INDEX["pow"], i), (PRIMITIVE_INDEX["exp"], a)]])
                    for a in node]
    out += [canonical([[(PRIMITIVE_INDEX["exp"], a)]]) for a in node]
    return out


def symbolic_search(variables: list[Variable], target, target_std, *, nuisance=None,
                    evaluations: int = 3000, seconds: float | None = None,
                    generations: int = 6, population: int = 256, max_terms: int = 2,
                    max_factors: int = 3, max_complexity: int = 24, random_state: int = 0,
                    say: Callable[[str], None] | None = None,
                    taken: tuple[str, ...] = ()) -> SymbolicFront:
    """Search laws `q(variables)` for a heat `target` (samples,) W with std `target_std`
    (samples,) W.

    **Arguments:**

    - `variables`: the grammar's leaves (`Variable`, values (samples,)); see
      `heat_variables` for those of a node's missing heat.
    - `nuisance` (samples, z): heats with a free coefficient that every law is fitted
      beside and that no law reports (what a refit of the model adjusts anyway), or None.
    - `evaluations`, `seconds`: the budget, in laws fitted and in seconds (None: none).
    - `generations`, `population`: at most that many generations of at most that many
      new laws each (after generation 0).
    - `max_terms`, `max_factors`, `max_complexity`: the largest law considered.
    - `random_state`: the random choices; the same data and `random_state` give the same
      front.
    - `say`: progress, a line per generation.
    - `taken`: names a parameter must not take (the model's nodes and columns).

    **Returns:** a `SymbolicFront`.
    """
    say = say or (lambda _m: None)
    t0 = time.perf_counter()
    s = _Search(variables, target, target_std, nuisance, random_state, max_terms, max_factors,
                max_complexity)
    stopped, gen = "generations", 0
    try:
        first = [canonical([[f]]) for f in s.singles()] + library_forms(s.variables)
        s.evaluate([t for t in dict.fromkeys(first) if s.allowed(t)][:evaluations])
        say(_progress(s, 0, t0))
        for gen in range(1, generations + 1):
            left = evaluations - len(s.done)
            if left <= 0:
                stopped = "budget"
                break
            if seconds is not None and time.perf_counter() - t0 >= seconds:
                stopped = "seconds"
                break
            pool = list(dict.fromkeys(t for p in s.parents() for t in s.variations(p)))
            if not pool:
                stopped = "exhausted"
                break
            size = min(population, left)
            if len(pool) > size:
                pool = [pool[i] for i in np.sort(s.rng.choice(len(pool), size, replace=False))]
            s.evaluate(pool)
            say(_progress(s, gen, t0))
            if len(s.done) >= evaluations:
                stopped = "budget"
                break
    except KeyboardInterrupt:
        stopped = "interrupted"
        say(f"symbolic search interrupted after {len(s.done)} laws: the front so far is kept")
    front = {t: _found(s, t, taken) for t in s.front()}
    leaders = [front.get(t) or _found(s, t, taken) for t in s.leaders()]
    return SymbolicFront(list(front.values()), len(s.done), gen, time.perf_counter() - t0,
                         stopped, len(s.y), leaders)


def _progress(s: _Search, gen: int, t0: float) -> str:
    front = s.front()
    best = ", ".join(f"{complexity(t)}: {1.0 - s.done[t][0] / s.total:.4f}"
                     for t in front[:6])
    return (f"symbolic search: generation {gen}, {len(s.done)} laws fitted in "
            f"{time.perf_counter() - t0:.1f} s; front (complexity: R²) {best}")


def _found(s: _Search, tree: Tree, taken) -> FoundLaw:
    """The `FoundLaw` of a fitted tree: its expression with the fitted values, checked
    against the fit by the model's own expression evaluator."""
    cost, theta, beta = s.done[tree]
    text, order = tree_text(tree, s.variables, taken=taken)
    coefs = [float(b) for b in beta[:len(tree)]]
    flat = [f for term in tree for f in term]  # θ is per factor, term by term
    const_vals = [float(theta[i]) * PRIMITIVES[p].written for i, (p, _) in enumerate(flat)
                  if PRIMITIVES[p].constant is not None]
    c = coefs[0]
    ratios = [b / c if c != 0 else 0.0 for b in coefs[1:]]
    values = [c, *const_vals, *ratios]
    params = dict(zip(order, values))
    # a flow between the node and one far end when every term reads the difference to it
    # (the far node then loses the heat); else a heat into the node alone
    fars = [{s.variables[v].far for _, v in term} - {None} for term in tree]
    common = set.intersection(*fars) if fars else set()
    far = next(iter(common)) if len(common) == 1 and all(len(f) == 1 for f in fars) else None
    cols = {s.variables[v].column for term in tree for _, v in term if s.variables[v].column}
    column = next(iter(cols)) if len(cols) == 1 else None
    template = tree_text(tree, [_placeholder(v, far, column) for v in s.variables],
                         placeholders=True, taken=taken)[0]
    law = FoundLaw(tree, complexity(tree), float(cost), 1.0 - float(cost) / s.total, text,
                   params, template, far, column,
                   next((v.scale for v in s.variables if v.column == column), None))
    return _with_stds(s, law)


def _placeholder(v: Variable, far, column) -> Variable:
    """`v` as a library template writes it: its far end `{b}` only where it is the law's
    one far end, its column `{u}` only where it is the law's one column (else by name)."""
    text = v.placeholder
    if v.far is not None and v.far != far:
        text = v.name
    if v.column is not None and v.column != column:
        text = v.name
    return Variable(text, v.kind, v.values, text, v.far, v.column, v.scale)


def law_values(law: FoundLaw, variables: list[Variable], params: dict | None = None
               ) -> np.ndarray:
    """The heat (samples,) of `law` over `variables`' values, by the model's expression
    evaluator (`model._expression`): what a model holding it computes."""
    names = [v.name for v in variables]
    return _evaluate(law.expression, names, np.stack([v.values for v in variables], -1),
                     params or law.parameters)


def _evaluate(text, names, values, params):
    tree = parse(_aliased(text, names))
    alias = [f"v{i}" for i in range(len(names))]
    resolved = resolve(tree, alias, [], list(params))
    return evaluate_numpy(resolved, values, values[..., :0], list(params.values()))


def _aliased(text: str, names: list[str]) -> str:
    """`text` with each variable's written form replaced by a plain name `v<i>` (the
    longest first: a difference contains the node's name)."""
    for i in sorted(range(len(names)), key=lambda i: -len(names[i])):
        text = text.replace(names[i], f"v{i}")
    return text


def _with_stds(s: _Search, law: FoundLaw) -> FoundLaw:
    """`law` with each parameter's std: Gauss–Newton over the weighted residuals (finite
    differences of the expression as written), scaled by the residuals' mean square."""
    names = list(law.parameters)
    values = np.stack([v.values for v in s.variables], -1)
    vnames = [v.name for v in s.variables]
    base = np.array(list(law.parameters.values()))

    def heat(p):
        return _evaluate(law.expression, vnames, values, dict(zip(names, p)))

    try:
        # a law that overflows near its constants (exp of a large rate) has no std
        with np.errstate(divide="raise", over="raise", invalid="raise", under="ignore"):
            q0 = heat(base)
            J = np.empty((len(q0), len(base)))
            for j in range(len(base)):
                h = 1e-6 * max(abs(base[j]), 1e-8)
                up, dn = base.copy(), base.copy()
                up[j] += h
                dn[j] -= h
                J[:, j] = (heat(up) - heat(dn)) / (2 * h) * s.w
            if s.Zw.shape[1]:
                J = np.concatenate([J, s.Zw], 1)
            dof = max(len(q0) - J.shape[1], 1)
            cov = np.linalg.pinv(J.T @ J) * (law.cost / dof)
            std = np.sqrt(np.maximum(np.diag(cov)[:len(base)], 0.0))
        stds = {n: float(v) for n, v in zip(names, std)}
    except (ValueError, np.linalg.LinAlgError, FloatingPointError):
        stds = {}
    return FoundLaw(law.tree, law.complexity, law.cost, law.r2, law.expression,
                    law.parameters, law.template, law.far, law.column, law.scale, stds)


def heat_variables(temperatures: list[np.ndarray], nodes, node: str, neighbours,
                   columns: dict[str, list[np.ndarray]], scales: dict[str, float] | None = None
                   ) -> list[Variable]:
    """The grammar's variables at `node` over runs: its temperature (°C) and in kelvin,
    its difference to each of `neighbours` (nodes, or columns of `columns` such as a
    boundary's temperature), and each other column of `columns` (a recorded signal that
    is not a temperature) read in its size `scales[column]` (`column_scales`), as a
    library term reads it.

    **Arguments:**

    - `temperatures`: per run (T, nodes) °C, the smoothed node temperatures
      (`MissingHeat.temperatures`) over `nodes` (names).
    - `columns`: name -> per run (T,) values of the recorded columns to read.
    """
    at = list(nodes).index(node)
    T = np.concatenate([np.asarray(x, float)[:, at] for x in temperatures])

    def series(name):
        if name in nodes:
            j = list(nodes).index(name)
            return np.concatenate([np.asarray(x, float)[:, j] for x in temperatures])
        return np.concatenate([np.asarray(v, float) for v in columns[name]])

    out = [Variable(node, "celsius", T, "{a}"),
           Variable(f"kelvin({node})", "kelvin", T + KELVIN, "kelvin({a})")]
    for b in neighbours:
        out.append(Variable(f"({b} - {node})", "difference", series(b) - T,
                            "({b} - {a})", far=b))
    for c in columns:
        if c in neighbours:
            continue
        scale = (scales or {}).get(c)
        values = series(c)
        if scale is None:
            size = float(np.max(np.abs(values))) if values.size else 0.0
            if not (np.isfinite(size) and size > 0.0):
                continue  # a column that is zero throughout reads as nothing
            scale = float(f"{size:.3g}")
        text = f"({c} / {np.format_float_positional(scale, trim='-')})"
        out.append(Variable(text, "column", values / scale, "{u}", column=c, scale=scale))
    return out


def learned_law(law: FoundLaw, node: str) -> tuple[LearnedLaw, tuple[str, ...]]:
    """`(LearnedLaw, where)`: a found law at `node` as a candidate of the loop, like a
    library term: its expression a template (`FoundLaw.template`), linear in `c`, its
    other parameters the shape, tried at their fitted values. A law of the difference
    to one far end is a flow between the two (`where = [node, far]`), else a heat into
    the node (`[node]`)."""
    shape = tuple(n for n in law.parameters if n != "c")
    places = "pair" if law.far else ("input" if law.column else "node")
    term = LibraryTerm(f"symbolic search, complexity {law.complexity}", law.template,
                       places, shape, (tuple(float(law.parameters[n]) for n in shape),))
    where = (node, law.far) if law.far else (node,)
    return LearnedLaw(term, law.column, scale=law.scale), where
