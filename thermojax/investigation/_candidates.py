"""Candidate effects for a fitted model: enumerate, score, refit, rank.

Every kind of the vocabulary is tried at every place the topology allows, data
columns the model does not use included. Each candidate is first scored at no
refitting cost by the *score test* (Rao's efficient score): at the fitted model
the effect is absent (its parameter at the null value), and the derivative of the
outputs along it, `d`, is known from the effect's physics (`score_direction`: a heat
flow into nodes, propagated through the fitted network, or a change of a reading).
With `J` the Jacobian of the fitted parameters and `r` the noise-weighted residuals,
the part of `d` the fitted parameters cannot mimic is `d⊥ = (I − J J⁺) d`, and

    S = (d⊥ᵀ r)² / (d⊥ᵀ d⊥)  ~  χ²₁ when the effect is absent.

An effect whose parameter is positive (a mass, a radiation coefficient, a
conductance, a lag) sits on the boundary of its parameter space when absent: its
test is one-sided (Self & Liang 1987: half the χ²₁ tail, and nothing for a
negative score). The best candidates are then refitted; their statistic becomes the
likelihood ratio `2 (nll_before − nll_after)`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

from ..compilation._traced_cache import stored_jit
from ..dynamics._lag import first_order_lag
from ..dynamics._model_arrays import free_run_states, linear_parts
from ..measurements._data import Dataset
from ..model._spec import EFFECT_KINDS, Effect, ModelSpec, Parameter
from ..model.effects import KINDS
from ..model.effects._base import path_between, unique_name


@dataclass
class Candidate:
    """One effect at one place, with its evidence."""

    kind: str
    where: tuple[str, ...]
    score: float  # χ² statistic: score test, or likelihood ratio once refitted
    p_value: float
    method: str = "score"  # "score" or "refit"
    delta_bic: float | None = None
    tied_with: list = field(default_factory=list)
    supported: bool = False
    parameters: dict | None = None  # fitted effect parameters (refit only)
    note: str = ""
    holdout_gain: float | None = None  # held-out −log L improvement (leave one run out)
    result: object = field(default=None, repr=False)  # FitResult of the refit
    lr_deflation: float = 1.0  # long-run variance ratio dividing the statistic (non-white)
    holdout_votes: list = field(default_factory=list)  # `_selection.FoldVote` per fold
    refit_start: str | None = None  # which start of the refit won (`_refits._refit`)
    score_test: float | None = None  # the score-test statistic (kept once refitted)
    hold: str | None = None  # the hold the likelihood chose for a column the effect brings
    duplicate: str = ""  # why the refitted effect only duplicates existing structure
    absorbed_by: dict = field(default_factory=dict)  # unmeasured node -> moved parameters
    # The score test's one-step estimate of the effect's leading parameter (its units):
    # the least-squares coefficient of its direction, the fitted parameters' projected out.
    estimate: float | None = None
    # For a kind with a time constant of its own (a mass, a lag): the trial time constant
    # (s) of the best score direction, where a refit also starts (`_refits`).
    time_constant: float | None = None
    # A learned law of the library (`discovery.LearnedLaw`) and the shape values (an
    # exponent, a temperature rate) of its best score direction; None for a kind.
    learned: object = field(default=None, repr=False)
    shape: tuple | None = None
    # False where the refitted parameters leave the kind's physical range
    # (`_physical_range.reject_unphysical`); the note says why.
    physical: bool = True
    # Wall time of the refit's fits, s, summed over its starts (fits side by side overlap),
    # and how many fits that was: what a model of its structure costs to fit.
    refit_seconds: float | None = None
    refit_fits: int = 0
    # A refined law (`_symbolic_step.refine_laws`): the indices in the step's
    # `spec.effects` of the laws it replaces, and their expressions.
    replaces: tuple[int, ...] = ()
    replaced: tuple[str, ...] = ()

    def __post_init__(self):
        if self.score_test is None and self.method == "score":
            self.score_test = self.score

    def add_note(self, text: str, *, first: bool = False) -> None:
        """Join `text` to the note (after it, or before it with `first`), "; "-separated."""
        parts = (text, self.note) if first else (self.note, text)
        self.note = "; ".join(filter(None, parts))

    @property
    def likelihood_ratio(self) -> float | None:
        """2 (−log L before − −log L after): the refitted candidate's statistic."""
        return self.score if self.method == "refit" else None

    @property
    def key(self) -> tuple[str, tuple[str, ...]]:
        return self.kind, tuple(self.where)

    def as_json(self) -> dict:
        # `score`: the ranking's evidence statistic (spec); `score_test` and
        # `likelihood_ratio` say the two statistics apart (None where not computed).
        return {"kind": self.kind, "where": list(self.where), "score": _finite(self.score),
                "score_test": _finite(self.score_test),
                "likelihood_ratio": _finite(self.likelihood_ratio),
                "delta_bic": _finite(self.delta_bic), "p_value": _finite(self.p_value),
                "tied_with": [[k, list(w)] for k, w in self.tied_with],
                "supported": bool(self.supported), "method": self.method,
                "holdout_gain": _finite(self.holdout_gain),
                "holdout_folds": [v.as_json() for v in self.holdout_votes],
                "refit_start": self.refit_start, "parameters": self.parameters,
                "hold": self.hold, "absorbed_by": self.absorbed_by, "note": self.note,
                "physical": bool(self.physical),
                **({"expression": self.expression, "law": self.learned.term.name}
                   if self.learned is not None else {}),
                **({"replaces": list(self.replaced)} if self.replaced else {})}

    @property
    def expression(self) -> str | None:
        """A learned law's expression at its place (None for a kind)."""
        return self.learned.text(self.where) if self.learned is not None else None

    def columns(self) -> list[str]:
        """The names of `where`, and the data columns a learned law reads."""
        extra = [self.learned.column] if self.learned is not None and \
            self.learned.column is not None else []
        return list(dict.fromkeys([*self.where, *extra]))


def _finite(x):
    return None if x is None or not np.isfinite(x) else float(x)


# ---------------------------------------------------------------------------
# Columns and places


def column_role(name: str, values: np.ndarray) -> str:
    """A guess of what an unused data column measures: "temperature", "power" or "other"."""
    low = name.lower()
    if low.startswith("t_") or "temp" in low or low.startswith("t") and low[1:2].isdigit():
        return "temperature"
    if low.startswith(("p_", "q_")) or "power" in low or "heat" in low:
        return "power"
    return "other"


def helper_nodes(spec: ModelSpec, lowered: ModelSpec) -> set[str]:
    """Nodes lowering made that the model file does not name (a lag's sensing element):
    no candidate acts on them."""
    return set(lowered.node_names) - set(spec.node_names) - {
        e.name for e in spec.effects if e.kind == "extra_node"}


def enumerate_places(spec: ModelSpec, lowered: ModelSpec, unused: dict[str, str]
                     ) -> list[tuple[str, tuple[str, ...]]]:
    """Every `(kind, where)` the vocabulary allows on `spec` (its lowered form `lowered`),
    except effects it already has and places on helper nodes lowering made."""
    helpers = helper_nodes(spec, lowered)
    have = {(e.kind, tuple(e.where)) for e in spec.effects}
    # Paths an extra_node effect made (its mass to its ends): their conductances are that
    # effect's parameters, so a second mass cannot split them; it may go on the far side.
    made = {frozenset((e.name, w)) for e in spec.effects if e.kind == "extra_node"
            for w in e.where}
    lagged = {e.where[0] for e in spec.effects if e.kind == "sensor_lag"}
    out = []
    for kind, impl in KINDS.items():
        for where in impl.places(lowered, unused):
            where = tuple(where)
            if helpers & set(where) or (kind, where) in have:
                continue
            if kind == "sensor_lag" and where[0] in lagged:
                continue
            if kind == "extra_node" and frozenset(where) in made:
                continue
            if kind in ("radiation", "conductance_temperature") and len(where) == 2 and \
                    (kind, where[::-1]) in have:
                continue
            out.append((kind, where))
    return out


def new_effect(spec: ModelSpec, lowered: ModelSpec, kind: str, where, holds: dict[str, str],
               leading: float | None = None, time_constant: float | None = None) -> Effect:
    """The effect `kind` at `where` with its first-guess parameters, ready to add; a data
    column it brings in is held as `holds` says (column name -> "zoh" or "foh").
    `leading`: a value of the leading parameter to start from instead, used when finite
    and, for a positive parameter, positive."""
    impl = KINDS[kind]
    first_guess = impl.initial_parameters(lowered, where)
    if time_constant is not None:
        first_guess = impl.with_time_constant(lowered, tuple(where), first_guess,
                                              time_constant)
    params = {k: Parameter(float(v)) for k, v in first_guess.items()}
    first = EFFECT_KINDS[kind].parameters[0]
    if leading is not None and np.isfinite(leading) and (
            leading > 0 or first not in EFFECT_KINDS[kind].positive):
        params[first] = Parameter(float(leading))
    if kind == "extra_node" and len(where) == 1:
        params.pop("conductance_b", None)
    name = unique_name(lowered, "mass_" + "_".join(where)) if kind == "extra_node" else None
    hold = next((holds[w] for w in where if w in holds), None)
    return Effect(kind, tuple(where), params, name, hold)


# ---------------------------------------------------------------------------
# The score test


FAST_TRIALS = (20.0, 200.0, 2000.0)  # s
SHORT_TRIALS = (2.0, 6.0)  # sample periods, where shorter than FAST_TRIALS[0]
SLOW_SAMPLING_S = 60.0
SLOW_TRIALS = (2.0, 6.0, 20.0, 60.0, 200.0)  # sample periods


class ScoreContext:
    """The fitted model's reconstructed states and the data, for `score_direction`.

    Arrays are (runs, T, ...) on the padded time grid of the `Dataset`."""

    def __init__(self, spec: ModelSpec, model, data: Dataset, run_initial, columns: dict,
                 states=None):
        self.spec = spec
        self.names = list(spec.node_names)
        x = np.asarray(free_run_states(model, data, run_initial) if states is None
                       else states)
        A, B, C, capacitance, _ = (np.asarray(a) for a in linear_parts(model))
        self.A, self.C = A, C
        u = np.asarray(data.inputs)
        self.T = x
        self.dTdt = x @ A.T + u @ B.T
        self.capacitance = capacitance
        self.y = x @ self.C.T
        self.dts = np.asarray(data.dt)
        self.columns = columns
        self.sensor_columns = list(spec.sensor_columns)
        self.sensor_nodes = [self.names.index(s.node) for s in spec.sensors]
        self.model = model

    def node(self, name: str) -> int:
        return self.names.index(name)

    def is_node(self, name: str) -> bool:
        return name in self.names

    def sensor(self, column: str) -> int:
        return self.sensor_columns.index(column)

    def sensor_node(self, s: int) -> int:
        return self.sensor_nodes[s]

    def column(self, name: str) -> np.ndarray:
        return self.columns[name]

    def temperature(self, name: str) -> np.ndarray:
        return self.T[..., self.node(name)] if self.is_node(name) else self.columns[name]

    def is_heat_column(self, node: str, column: str) -> bool:
        return any(h.node == node and h.input == column for h in self.spec.heat_inputs)

    def trial_time_constants(self) -> tuple[float, ...]:
        """Time constants (s) at which a lag-like effect's score direction is tried (the
        best one scores): 20, 200 and 2000 s for data sampled faster than once a minute
        (sensor modules), after 2 and 6 sample periods where those are shorter than 20 s;
        else 2, 6, 20, 60 and 200 sample periods (buildings sampled every 5 to 15 min,
        whose heaters, sensors and envelopes lag by an hour to days: on PRBS1 a grid of 2,
        20 and 200 periods scored the heater's mass 143 where its likelihood ratio is 478,
        and the loop never refitted it). On a module sampled every 2 s whose die reads
        through a 2 s mass, every mass scored under 50 from 20 s on and the sensor lag
        (whose score also tries its local direction) was added unopposed; with a 4 s
        trial a mass at housing–pcb scored 780 beside the lag's 790 and its refit did
        better (likelihood ratio 1613 against 1602)."""
        dt = float(np.max(self.dts))
        if dt >= SLOW_SAMPLING_S:
            return tuple(k * dt for k in SLOW_TRIALS)
        return tuple(k * dt for k in SHORT_TRIALS if k * dt < FAST_TRIALS[0]) + FAST_TRIALS

    def lag(self, x: np.ndarray, tau: float) -> np.ndarray:
        """First-order lag (`tau` in s) of `x` (runs, T, ...) along time, per run's sample
        period, at rest at the first sample."""
        return np.stack([first_order_lag(x[r], float(self.dts[r]), tau)
                         for r in range(x.shape[0])])

    def path_conductance(self, where) -> float:
        kind, i = path_between(self.spec, where[0], where[1])
        net = self.model.network
        return float(np.asarray(net.conductance if kind == "link"
                                else net.boundary_conductance)[i])


_HEAT_BATCH = 16  # heat directions per call: one program for every step of a loop


def heat_responses(A, C, capacitance, ts, W) -> np.ndarray:
    """Output responses (K, runs, T, p) of the linear network `A` (n, n), `C` (p, n),
    `capacitance` (n,) J/K to heat inputs `W` (K arrays (runs, T, n), W), each from the
    steady state of its first sample; `ts` (runs, T) s. In batches of `_HEAT_BATCH` (the
    last padded with zeros), so that the program depends on the shapes alone, not on the
    model or K."""
    K = len(W)
    out = np.empty((K, *np.shape(ts), C.shape[0]))
    for k in range(0, K, _HEAT_BATCH):
        batch = np.zeros((_HEAT_BATCH, *np.shape(W[k])))
        batch[:min(_HEAT_BATCH, K - k)] = W[k:k + _HEAT_BATCH]
        out[k:k + _HEAT_BATCH] = np.asarray(_heat_batch(A, C, capacitance, ts,
                                                        batch))[:K - k]
    return out


@stored_jit
def _heat_batch(A, C, capacitance, ts, W):
    from ..dynamics._simulate import ExactHold
    from ..model._system import LinearSystem

    n = A.shape[0]
    heat = LinearSystem(A, jnp.diag(1.0 / capacitance), C, jnp.zeros((C.shape[0], n)),
                        holds=("foh",) * n, capacitance=capacitance)

    def one(w, t):
        x0 = heat.steady_state(w[0])
        return ExactHold().run(heat, x0, w, t).outputs

    return jax.vmap(lambda wk: jax.vmap(one)(wk, ts))(W)


def score_candidates(result, data: Dataset, places, columns: dict, weights, residuals,
                     jacobian, deflation: float = 1.0, whiten=None, states=None
                     ) -> list[Candidate]:
    """Score-test every `(kind, where)` in `places` at the fitted `result`.

    `residuals` (N,) and `jacobian` (N, P): the noise-weighted output-error residuals
    (data rows, (runs, T, p) flattened, zero where unmeasured) and their Jacobian in the
    fitted parameters; `weights` (runs, T, p): 1/σ where measured, else 0.
    `deflation`: the residuals' long-run variance ratio; p-values are those of the
    statistic divided by it (the reported score is not). `whiten`, when given, maps
    output-space directions (runs, T, p, m) to the rows of `residuals` (N, m) instead of
    weighting them (the Kalman likelihood's innovations: `innovation_directions`).
    `states`: the fitted model's node temperatures (runs, T, n) when at hand (a nonlinear
    fit's, from `output_error_at`); else simulated here.
    """
    ctx = ScoreContext(result.lowered_spec, result.model, data, result.state.run_initial,
                       columns, states)
    # The fitted parameters' column space, by a truncated SVD (unidentifiable directions
    # carry no information either way).
    U, s, _ = np.linalg.svd(jacobian, full_matrices=False)
    U = U[:, s > 1e-8 * s[0]] if s.size else U
    r = residuals

    raw = []
    for kind, where in places:
        impl = KINDS[kind] if isinstance(kind, str) else kind  # a kind, or a learned law
        try:
            how, dirs = impl.score_direction(ctx, where)
        except (KeyError, ValueError, NotImplementedError, TypeError):
            continue
        raw.append((kind, where, how, dirs))
    heat = [(i, j) for i, (_, _, how, dirs) in enumerate(raw) if how == "heat"
            for j in range(len(dirs))]
    responses = {}
    if heat:
        out = heat_responses(ctx.A, ctx.C, ctx.capacitance, np.asarray(data.ts),
                             [raw[i][3][j] for i, j in heat])
        responses = {key: out[k] for k, key in enumerate(heat)}
    shape = np.shape(weights)
    keys = [(i, j) for i, (_, _, _, dirs) in enumerate(raw) for j in range(len(dirs))]
    directions = {}
    for i, j in keys:
        _, _, how, dirs = raw[i]
        d = responses[(i, j)] if how == "heat" else dirs[j]
        directions[(i, j)] = np.broadcast_to(np.asarray(d, float), shape)
    if whiten is not None and keys:
        finite = [k for k in keys if np.all(np.isfinite(directions[k]))]
        mapped = whiten(np.stack([directions[k] for k in finite], axis=-1)) if finite else []
        directions = {k: mapped[..., n].reshape(-1) for n, k in enumerate(finite)}
    else:
        directions = {k: (d * weights).reshape(-1) for k, d in directions.items()}
    cands = []
    for i, (kind, where, how, dirs) in enumerate(raw):
        impl = KINDS[kind] if isinstance(kind, str) else kind
        lead = EFFECT_KINDS[impl.kind].parameters
        one_sided = bool(lead) and lead[0] in EFFECT_KINDS[impl.kind].positive
        scores, estimates = [], []
        for j in range(len(dirs)):
            dw = directions.get((i, j))
            if dw is None or not np.all(np.isfinite(dw)):
                continue
            dp = dw - U @ (U.T @ dw)
            norm2 = float(dp @ dp)
            if norm2 <= 1e-12 * max(float(dw @ dw), 1e-300):
                stat, u, norm2 = 0.0, 0.0, 1.0
            else:
                u = float(dp @ r)
                stat = u * u / norm2
            scores.append(0.0 if one_sided and u <= 0 else stat)
            estimates.append(u / norm2)
        if not scores:
            continue
        best = int(np.argmax(scores))
        stat = scores[best]
        p = stats.chi2.sf(stat / max(deflation, 1.0), 1) * (0.5 if one_sided else 1.0) \
            * len(dirs)
        learned = None if isinstance(kind, str) else impl
        cands.append(Candidate(impl.kind, tuple(where), float(stat), float(min(1.0, p)),
                               lr_deflation=float(max(deflation, 1.0)),
                               estimate=float(estimates[best]),
                               time_constant=impl.direction_time_constant(ctx, best),
                               learned=learned,
                               shape=learned.shape_of(best) if learned else None))
    cands.sort(key=lambda c: -c.score)
    return cands


def refit_p_value(kind: str, lr: float, n_new: int) -> float:
    """p-value of a likelihood-ratio statistic for `n_new` added parameters, the leading
    one on its boundary for positive kinds (½χ²(k−1) + ½χ²(k) mixture)."""
    lr = max(lr, 0.0)
    params = EFFECT_KINDS[kind].parameters
    if params and params[0] in EFFECT_KINDS[kind].positive:
        lo = stats.chi2.sf(lr, n_new - 1) if n_new > 1 else float(lr <= 0)
        return float(0.5 * lo + 0.5 * stats.chi2.sf(lr, n_new))
    return float(stats.chi2.sf(lr, n_new))


def benjamini_hochberg(p_values, q: float) -> np.ndarray:
    """Which hypotheses the Benjamini-Hochberg procedure rejects at false-discovery rate q."""
    p = np.asarray(p_values, float)
    m = p.size
    if m == 0:
        return np.zeros(0, bool)
    order = np.argsort(p)
    passed = p[order] <= q * np.arange(1, m + 1) / m
    k = np.max(np.nonzero(passed)[0]) + 1 if passed.any() else 0
    out = np.zeros(m, bool)
    out[order[:k]] = True
    return out
