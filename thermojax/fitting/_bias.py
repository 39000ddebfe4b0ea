"""Inertial bias channels (docs/formats.md §4): a bias column explained by the thermal states.

A `[[biases]]` column reads

    b(t) = Σ_p c_p (T − 25)^p + Σ_g d_g (T_a − T_b) + Σ_r e_r dT_n/dt + Σ_v k_v (T_v − ε_v)

with `T` the bias's `temperature` node (°C) and, for each `viscoelastic` effect on
the column, a strain `dε_v/dt = (T_v − ε_v)/τ_v`, `ε_v(0) = T_v(0)`. Node
temperatures arrive sampled and are taken as piecewise linear between samples,
for which `dynamics._lag.first_order_lag` integrates ε exactly. Given the τ's the
coefficients are linear (least squares); the τ's come from a bounded search on
log τ of the likelihood with the coefficients profiled out. NumPy/SciPy only.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .._errors import InputError
from ..dynamics._lag import first_order_lag
from ..model._spec import Bias, Effect, Parameter

T_REF = 25.0  # °C, reference of the static polynomial
TAU_BOUNDS = (1.0, 1e5)  # s, search range of a relaxation time
TAU_GRID = np.logspace(0.0, 5.0, 26)  # s, first pass of a candidate's τ search
_H = 1e-4  # central-difference step in log τ for ∂ε/∂log τ (error ~ H² relative)
_LOG_2PI = math.log(2.0 * math.pi)


@dataclass
class BiasFit:
    """A fitted bias channel.

    - `names`: coefficient names, `poly0..polyN`, `gradient.a-b`, `rate.n`,
      `viscoelastic.<node>.k`; `coefficients` and `std` follow that order
      (column units per °C^p, per K, per K/s, per K); `std` is NaN where fixed or
      unidentifiable.
    - `time_constants`: `viscoelastic.<node>` → (τ in s, its std or None).
    - `predictions`, `residuals`: per run, shape `(T,)`; residuals are NaN where
      the column was not measured.
    - `sigma`: noise std (ML, or the fixed `noise`); `nll`: Gaussian −log L of the
      measured samples; `n_params`: free coefficients + free τ's + estimated σ.
    - `fixed`: names held fixed (`viscoelastic.<node>.k`, `viscoelastic.<node>`
      for a τ, `noise`).
    """

    column: str
    names: list[str]
    coefficients: np.ndarray
    std: np.ndarray
    time_constants: dict[str, tuple[float, float | None]]
    predictions: list[np.ndarray]
    residuals: list[np.ndarray]
    sigma: float
    nll: float
    n_params: int
    rmse: float
    fixed: tuple[str, ...] = ()


# ---------------------------------------------------------------------------
# The strain state


def _strain_term(ts, temps, tau) -> tuple[np.ndarray, np.ndarray]:
    """`z = T − ε(τ)` and `∂z/∂log τ` (central difference), each `(T,)`; `ts` in s,
    `temps` in °C, `tau` in s."""
    dt = np.diff(ts)
    z = temps - first_order_lag(temps, dt, tau)
    dz = (first_order_lag(temps, dt, tau * math.exp(-_H))
          - first_order_lag(temps, dt, tau * math.exp(_H))) / (2 * _H)
    return z, dz


# ---------------------------------------------------------------------------
# The regression problem of one bias column


def static_design(bias: Bias, ts, temps, rates, index) -> np.ndarray:
    """The bias's static regressors `(T, order + 1 + gradients + rates)`: the powers of
    `(T − 25)` of its temperature node, its node differences (K) and its nodes' rates
    (K/s). `temps` (T, nodes) °C; `rates` (T, nodes) the model's own state derivatives,
    or None for the derivative of the sampled temperatures; `index` node name -> column."""
    if rates is None:
        rates = np.gradient(temps, ts, axis=0) if ts.size > 1 else np.zeros_like(temps)
    return np.column_stack(static_columns(
        temps, rates, index(bias.temperature), bias.order,
        [(index(a), index(b)) for a, b in bias.gradients], [index(n) for n in bias.rates]))


def static_columns(x, xdot, temperature: int, order: int, gradients, rates) -> list:
    """The static regressors of a bias column, each (...) as `x[..., 0]`: the powers 0 to
    `order` of `(T − 25)` of node `temperature`, the differences of the node pairs
    `gradients` (K) and the rates of the nodes `rates` (K/s). `x` node temperatures
    (..., nodes) °C and `xdot` their rates (..., nodes) K/s, NumPy or JAX arrays alike
    (the fit's traced design and the written column's are this one function)."""
    t = x[..., temperature] - T_REF
    cols = [t ** p for p in range(order + 1)]
    cols += [x[..., a] - x[..., b] for a, b in gradients]
    cols += [xdot[..., n] for n in rates]
    return cols


def predict_bias(bias: Bias, effects: list[Effect], ts, temps, rates, node_names) -> np.ndarray:
    """The column a `[[biases]]` entry with `coefficients` reads on states `temps` (T,
    nodes) °C with `rates` (T, nodes) K/s (or None), at times `ts` (s): its static terms
    plus each viscoelastic effect's `k (T_v − ε_v)`. Raises `InputError` where the entry
    or one of its effects lacks a value (nothing fitted yet)."""
    if bias.coefficients is None:
        raise InputError(f"the [[biases]] entry of column '{bias.column}' holds no "
                         "`coefficients`, so its column cannot be computed; fit the model to "
                         "data with that column first (`thermojax fit` writes them), or drop "
                         "the entry from a copy of the model.", field=f"biases.{bias.column}")
    idx = {n: i for i, n in enumerate(node_names)}
    ts, temps = np.asarray(ts, float), np.asarray(temps, float)
    out = static_design(bias, ts, temps, rates, idx.__getitem__) @ np.asarray(bias.coefficients)
    for s in strains_of([bias], effects):
        if s.time_constant is None or s.k is None:
            raise InputError(f"the viscoelastic effect of column '{bias.column}' at node "
                             f"'{s.node}' gives no time_constant and k to compute it with.",
                             field="effects")
        z, _ = _strain_term(ts, temps[:, idx[s.node]], float(s.time_constant.value))
        out = out + float(s.k.value) * z
    return out


@dataclass(frozen=True)
class Strain:
    """One viscoelastic effect: its node, bias column, starting τ and k (None: none) and
    its place in a Prony series (1 for the first term on this node and column)."""

    node: str
    column: str
    time_constant: Parameter | None
    k: Parameter | None
    term: int = 1

    @property
    def suffix(self) -> str:
        return "" if self.term == 1 else f"#{self.term}"

    @property
    def name(self) -> str:
        """Its name inside a `BiasFit`: `viscoelastic.<node>`, `viscoelastic.<node>#2`, ..."""
        return f"viscoelastic.{self.node}{self.suffix}"

    @property
    def prefix(self) -> str:
        """Its dotted report prefix (docs/formats.md §5, `effect_labels`)."""
        return f"effects.viscoelastic.{self.node}-{self.column}{self.suffix}"

    @property
    def parameter(self) -> str:
        """The dotted report name of its τ."""
        return f"{self.prefix}.time_constant"


def strains_of(biases, effects) -> list[Strain]:
    """The viscoelastic effects among `effects`, column by column in `biases`' order; a
    second term on the same node and column continues a Prony series."""
    out = []
    for b in biases:
        terms: dict[str, int] = {}
        for e in effects:
            if e.kind == "viscoelastic" and e.where[1] == b.column:
                terms[e.where[0]] = terms.get(e.where[0], 0) + 1
                out.append(Strain(e.where[0], b.column, e.parameters.get("time_constant"),
                                  e.parameters.get("k"), terms[e.where[0]]))
    return out


class _Problem:
    """Design of one bias column over all runs; evaluates the profiled likelihood in log τ."""

    def __init__(self, bias: Bias, effects: list[Effect], runs, node_names, node_rates):
        node_names = list(node_names)
        idx = {n: i for i, n in enumerate(node_names)}
        self.column = bias.column

        def index(n: str) -> int:
            if n not in idx:
                raise ValueError(f"`fit_bias` for column '{bias.column}' needs node '{n}', "
                                 f"but node_names are {node_names}.")
            return idx[n]

        if node_rates is not None and len(node_rates) != len(runs):
            raise ValueError(f"`fit_bias(node_rates=...)` has {len(node_rates)} runs, "
                             f"runs has {len(runs)}.")
        self.strains = strains_of([bias], effects)
        self.strain_nodes = [index(s.node) for s in self.strains]
        self.static_names = ([f"poly{p}" for p in range(bias.order + 1)]
                             + [f"gradient.{a}-{b}" for a, b in bias.gradients]
                             + [f"rate.{n}" for n in bias.rates])
        self.runs = []  # (ts, node temps, static design (T, n_static), y, measured mask)
        for r, (ts, temps, y) in enumerate(runs):
            ts = np.asarray(ts, dtype=float)
            temps = np.asarray(temps, dtype=float)
            y = np.asarray(y, dtype=float)
            if ts.ndim != 1 or temps.shape != (ts.size, len(node_names)) or y.shape != ts.shape:
                raise ValueError(f"`fit_bias` run {r}: expected ts (T,), node_temps (T, "
                                 f"{len(node_names)}), y (T,); got {ts.shape}, {temps.shape}, "
                                 f"{y.shape}.")
            if ts.size > 1 and not np.all(np.diff(ts) > 0):
                raise ValueError(f"`fit_bias` run {r}: ts must be strictly increasing.")
            if not np.all(np.isfinite(temps)):
                raise ValueError(f"`fit_bias` run {r}: node temperatures must be finite.")
            mask = np.isfinite(y)
            if not mask.any():
                raise InputError(f"bias column '{bias.column}' has no measured sample in run {r} "
                                 "(every value is empty or NaN); drop the column from that run's "
                                 "model or record it.", field=bias.column)
            dT = None if node_rates is None else np.asarray(node_rates[r], dtype=float)
            self.runs.append((ts, temps, static_design(bias, ts, temps, dT, index), y, mask))
        self.y = np.concatenate([y[m] for *_, y, m in self.runs])
        self.n = self.y.size
        self.sigma_fixed = bias.noise.value if bias.noise is not None and bias.noise.fixed else None
        self.free_tau = [s.time_constant is None or not s.time_constant.fixed
                         for s in self.strains]
        self.free_k = [s.k is None or not s.k.fixed for s in self.strains]
        n_params = (len(self.static_names) + sum(self.free_k) + sum(self.free_tau)
                    + (self.sigma_fixed is None))
        if self.n < n_params:
            raise InputError(f"bias column '{bias.column}' has {self.n} measured sample(s) but "
                             f"{n_params} parameters to fit; record more samples or lower the "
                             "polynomial order.", field=bias.column)
        self.n_params = n_params

    # -- evaluation at given τ's ---------------------------------------------------------------

    def terms(self, taus) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per run: strain terms `z` and `∂z/∂log τ`, each `(T, n_strains)`."""
        out = []
        for ts, temps, *_ in self.runs:
            z, dz = np.zeros((2, ts.size, len(self.strains)))
            for v, (node, tau) in enumerate(zip(self.strain_nodes, taus)):
                z[:, v], dz[:, v] = _strain_term(ts, temps[:, node], tau)
            out.append((z, dz))
        return out

    def solve(self, taus):
        """Least squares at fixed τ's: (coefficients in `names` order, residual (N,), J (N, p))."""
        terms = self.terms(taus)
        free_k = np.array(self.free_k, dtype=bool)
        k_fixed = np.array([s.k.value if not f else 0.0 for s, f in zip(self.strains, free_k)])
        X = np.concatenate([np.hstack([D, z[:, free_k]])[m]
                            for (_, _, D, _, m), (z, _) in zip(self.runs, terms)])
        Z = np.concatenate([z[m] for (*_, m), (z, _) in zip(self.runs, terms)])
        dZ = np.concatenate([d[m] for (*_, m), (_, d) in zip(self.runs, terms)])
        target = self.y - Z @ k_fixed
        scale = np.sqrt(np.mean(X ** 2, axis=0))
        scale[scale == 0] = 1.0
        c_scaled, *_ = np.linalg.lstsq(X / scale, target, rcond=None)
        c = c_scaled / scale
        resid = target - X @ c
        n_static = len(self.static_names)
        k = k_fixed.copy()
        k[free_k] = c[n_static:]
        coefs = np.concatenate([c[:n_static], k])
        # ∂prediction/∂log τ_v = k_v ∂z_v/∂log τ, for the free τ's
        J = np.hstack([X, (dZ * k)[:, np.array(self.free_tau, dtype=bool)]])
        return coefs, resid, J

    def nll(self, rss: float) -> float:
        """Profiled −log L of the N measured samples (σ at its ML value unless fixed)."""
        n = self.n
        if self.sigma_fixed is None:
            return 0.5 * n * (math.log(max(rss, 1e-300) / n) + 1.0 + _LOG_2PI)
        s = self.sigma_fixed
        return rss / (2 * s * s) + n * math.log(s) + 0.5 * n * _LOG_2PI

    def objective(self, theta, taus) -> tuple[float, np.ndarray]:
        """−log L and its gradient in the free log τ's (the coefficients profiled out)."""
        taus = np.array(taus, dtype=float)
        taus[np.array(self.free_tau, dtype=bool)] = np.exp(theta)
        _, resid, J = self.solve(taus)
        rss = float(resid @ resid)
        n_tau = len(theta)
        drss = -2.0 * resid @ J[:, J.shape[1] - n_tau:]  # envelope theorem
        if self.sigma_fixed is None:
            return self.nll(rss), 0.5 * self.n * drss / max(rss, 1e-300)
        return self.nll(rss), drss / (2 * self.sigma_fixed ** 2)

    def search(self, taus) -> np.ndarray:
        """τ's (s) minimising −log L from `taus`, free ones searched in [1, 1e5] s on log τ."""
        import scipy.optimize  # where used: it costs every fit's start 0.4 s

        taus = np.array(taus, dtype=float)
        free = np.array(self.free_tau, dtype=bool)
        if not free.any():
            return taus
        lo, hi = np.log(TAU_BOUNDS)
        theta0 = np.clip(np.log(taus[free]), lo, hi)
        res = scipy.optimize.minimize(self.objective, theta0, args=(taus,), jac=True,
                                      method="L-BFGS-B", bounds=[(lo, hi)] * free.sum(),
                                      options=dict(ftol=1e-14, gtol=1e-7, maxiter=200))
        taus[free] = np.exp(res.x)
        return taus

    def grid_start(self, taus, v: int) -> np.ndarray:
        """`taus` with strain `v`'s τ at the best point of `TAU_GRID` (others held)."""
        taus = np.array(taus, dtype=float)
        best = (math.inf, taus[v])
        for tau in TAU_GRID:
            taus[v] = tau
            _, resid, _ = self.solve(taus)
            best = min(best, (self.nll(float(resid @ resid)), tau))
        taus[v] = best[1]
        return taus

    def result(self, taus) -> BiasFit:
        """The BiasFit at `taus`: Gauss–Newton covariance over coefficients and log τ's."""
        coefs, resid, J = self.solve(taus)
        rss = float(resid @ resid)
        sigma = self.sigma_fixed if self.sigma_fixed is not None else math.sqrt(rss / self.n)
        cov = sigma ** 2 * _pinv_gram(J)
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        n_static = len(self.static_names)
        free_k = np.array(self.free_k, dtype=bool)
        std = np.full(coefs.size, np.nan)
        std[:n_static] = sd[:n_static]
        std[n_static:][free_k] = sd[n_static:n_static + free_k.sum()]
        sd_theta = iter(sd[n_static + free_k.sum():])
        time_constants = {}
        for s, tau, f in zip(self.strains, taus, self.free_tau):
            st = next(sd_theta) if f else math.nan
            time_constants[s.name] = (float(tau), float(tau * st) if np.isfinite(st) else None)
        terms = self.terms(taus)
        predictions, residuals = [], []
        for (_, _, D, y, m), (z, _) in zip(self.runs, terms):
            pred = D @ coefs[:n_static] + z @ coefs[n_static:]
            predictions.append(pred)
            residuals.append(np.where(m, y - pred, np.nan))
        fixed = ([f"{s.name}.k" for s, f in zip(self.strains, self.free_k) if not f]
                 + [s.name for s, f in zip(self.strains, self.free_tau) if not f]
                 + (["noise"] if self.sigma_fixed is not None else []))
        return BiasFit(column=self.column,
                       names=self.static_names + [f"{s.name}.k" for s in self.strains],
                       coefficients=coefs, std=std, time_constants=time_constants,
                       predictions=predictions, residuals=residuals, sigma=float(sigma),
                       nll=self.nll(rss), n_params=self.n_params,
                       rmse=math.sqrt(rss / self.n), fixed=tuple(fixed))


def _pinv_gram(J: np.ndarray) -> np.ndarray:
    """(JᵀJ)⁻¹ through a column-scaled SVD; NaN rows/columns for unidentifiable directions."""
    scale = np.sqrt(np.sum(J ** 2, axis=0))
    scale[scale == 0] = 1.0
    _, s, Vt = np.linalg.svd(J / scale, full_matrices=False)
    keep = s > 1e-10 * s[0] if s.size else s > 0
    V = Vt[keep].T / s[keep]
    cov = (V @ V.T) / np.outer(scale, scale)
    null = Vt[~keep]
    bad = np.any(np.abs(null) > 1e-6, axis=0) if null.size else np.zeros(J.shape[1], bool)
    cov[bad, :] = np.nan
    cov[:, bad] = np.nan
    return cov


def _starts(problem: _Problem) -> list[float]:
    return [s.time_constant.value if s.time_constant is not None else math.nan
            for s in problem.strains]


def _fit(problem: _Problem, taus) -> BiasFit:
    missing = [v for v, tau in enumerate(taus) if not np.isfinite(tau)]
    taus = np.where(np.isfinite(taus), taus, 100.0)
    for v in missing:  # a τ without a start is placed on the grid first
        taus = problem.grid_start(taus, v)
    return problem.result(problem.search(taus))


# ---------------------------------------------------------------------------
# Public entry points


def fit_bias(bias: Bias, effects: list[Effect], runs, node_names, node_rates=None) -> BiasFit:
    """Fit one bias channel to reconstructed node temperatures.

    Coefficients by least squares at given τ's; free τ's by a bounded search on
    log τ (1 s to 1e5 s) from their `time_constant` values; σ by maximum
    likelihood unless the bias's `noise` is fixed. Stds come from the
    Gauss–Newton covariance σ² (JᵀJ)⁻¹ over coefficients and log τ's, so they
    include the τ uncertainty (without free τ's this is σ² (XᵀX)⁻¹).

    **Arguments:**

    - `bias`: the `[[biases]]` entry.
    - `effects`: effects of the model; the `viscoelastic` ones naming `bias.column`
      are used, their `time_constant` (s) as start (or held if fixed), `k` held if fixed.
    - `runs`: per run `(ts (T,) s, node_temps (T, nodes) °C, y (T,) with NaN for missing)`.
    - `node_names`: names of `node_temps`' columns.
    - `node_rates`: per run exact dT/dt `(T, nodes)` in K/s; default `np.gradient`.

    **Returns:** a `BiasFit`. Raises `InputError` for a run with no measured sample
    or fewer measured samples than parameters.
    """
    problem = _Problem(bias, effects, runs, node_names, node_rates)
    return _fit(problem, _starts(problem))


def bias_fit_at(bias: Bias, effects: list[Effect], runs, node_names, node_rates,
                taus) -> BiasFit:
    """`fit_bias` with the relaxation times held at `taus` (s, the column's viscoelastic
    effects in file order), e.g. those of a joint fit: the coefficients by least squares,
    stds over coefficients and log τ's as in `fit_bias`."""
    problem = _Problem(bias, effects, runs, node_names, node_rates)
    return problem.result(np.asarray(taus, dtype=float))


def viscoelastic_candidate(bias: Bias, effects: list[Effect], runs, node_names, node: str,
                           node_rates=None) -> tuple[BiasFit, float]:
    """Fit with one more `viscoelastic` effect on `node` and score it.

    The new τ is placed on a log grid (1 s to 1e5 s, others held at their fitted
    values) and then refined with every free τ.

    **Returns:** `(fit, 2 (nll_before − nll_after))`, the likelihood-ratio statistic.
    """
    before = fit_bias(bias, effects, runs, node_names, node_rates)
    new = Effect("viscoelastic", (node, bias.column))
    problem = _Problem(bias, [*effects, new], runs, node_names, node_rates)
    taus = [before.time_constants[s.name][0] for s in problem.strains[:-1]] + [100.0]
    taus = problem.grid_start(taus, len(taus) - 1)
    after = problem.result(problem.search(taus))
    return after, 2.0 * (before.nll - after.nll)


def bias_to_spec(bias: Bias, effects: list[Effect], fit: BiasFit) -> tuple[Bias, list[Effect]]:
    """Write a fit back: the Bias with `coefficients` (poly, gradients, rates) and, if it
    was estimated, `noise`; the viscoelastic effects of its column with fitted
    `time_constant` and `k` (fixed flags kept). Other effects pass unchanged."""
    n_static = bias.order + 1 + len(bias.gradients) + len(bias.rates)
    noise = bias.noise if bias.noise is not None and bias.noise.fixed \
        else Parameter(float(fit.sigma), False)
    coefficients = tuple(float(c) for c in fit.coefficients[:n_static])
    new_bias = dataclasses.replace(bias, noise=noise, coefficients=coefficients)
    coef = dict(zip(fit.names, fit.coefficients))
    strains = iter(strains_of([bias], effects))
    out = []
    for e in effects:
        if e.kind == "viscoelastic" and e.where[1] == bias.column:
            name = next(strains).name
            if name in fit.time_constants:
                def keep(p: str, v: float) -> Parameter:
                    old = e.parameters.get(p)
                    return Parameter(float(v), old.fixed if old is not None else False)
                params = {**e.parameters,
                          "time_constant": keep("time_constant", fit.time_constants[name][0]),
                          "k": keep("k", coef[f"{name}.k"])}
                e = dataclasses.replace(e, parameters=params)
        out.append(e)
    return new_bias, out


def bias_parameters(fit: BiasFit) -> dict[str, dict]:
    """Report entries `{"value", "std", "free"}` under the dotted names of docs/formats.md §5
    (`std` None where fixed or unidentifiable; never NaN)."""
    col = fit.column

    def entry(value, std, free) -> dict:
        std = float(std) if free and std is not None and np.isfinite(std) else None
        return {"value": float(value), "std": std, "free": bool(free)}

    def prefix(strain: str) -> str:  # viscoelastic.<node>[#n] -> effects.viscoelastic.<node>-<col>[#n]
        node, _, term = strain.removeprefix("viscoelastic.").partition("#")
        return f"effects.viscoelastic.{node}-{col}" + (f"#{term}" if term else "")

    out = {}
    for name, v, sd in zip(fit.names, fit.coefficients, fit.std):
        free = name not in fit.fixed
        if name.startswith("viscoelastic."):
            out[f"{prefix(name.removesuffix('.k'))}.k"] = entry(v, sd, free)
        else:
            out[f"biases.{col}.{name}"] = entry(v, sd, free)
    for name, (tau, sd) in fit.time_constants.items():
        out[f"{prefix(name)}.time_constant"] = entry(tau, sd, name not in fit.fixed)
    n = sum(int(np.isfinite(r).sum()) for r in fit.residuals)
    noise_free = "noise" not in fit.fixed
    out[f"biases.{col}.noise"] = entry(fit.sigma, fit.sigma / math.sqrt(2 * n), noise_free)
    return out
