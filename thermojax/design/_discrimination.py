"""Design to discriminate: the chamber profile that best tells rival models apart.

For hypotheses `a` (the model as its file gives it) and `b` (a rival), a run of profile
`u` read with white noise of std `σ` gives the log-likelihood-ratio statistic

    Λ_ab = 2 log (L_a / L_b) = (‖d‖² + 2 dᵀe) / σ²,   d = y_a(u) − y_b(u; θ̂_b),

when `a` is true, with `θ̂_b` the rival refitted to `a`'s readings (its starts included):
the design cannot win by the rival's parameters alone. `Λ_ab` is normal with mean
`λ_ab = ‖d/σ‖²` and variance `4 λ_ab`. A run is decisive for `a` when `Λ_ab` exceeds
`2 log 100` (a likelihood ratio of 100 to 1), with probability
`Φ((λ_ab − 2 log 100) / (2 √λ_ab))`.

The search maximizes `Σ log λ_ab` over the ordered pairs of hypotheses (every pair told
apart, whichever is true), the first start from the reference PRBS (power bits, the
chamber still), the others from random schedules. Each round refits every rival to every other hypothesis's
readings on the current profile (Levenberg–Marquardt on exact Jacobians), then improves
the profile with the refits linearized, `λ_ab ≈ ‖d‖² − dᵀJ(JᵀJ)⁻¹Jᵀd` (`J` the rival's
sensitivities: the rival may still move along them), by L-BFGS-B on the exact gradient;
the final `λ` are from exact refits on the final profile.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field

import jax
import jax.numpy as jnp
import numpy as np
import scipy.optimize
import scipy.stats

from .._errors import InputError
from ..model._spec import ModelSpec
from ._information import Prepared, prepare_profiles
from ._limits import ChamberLimits
from ._references import REFERENCES, prbs_start, reference_inputs
from ._schedule import ProfileSchedule

#: The statistic `2 log (L_a / L_b)` a decisive run exceeds: a likelihood ratio of 100.
DECISIVE = 2.0 * math.log(100.0)

_Z_BOUND = 8.0


def decisive_probability(lam: float) -> float:
    """Probability that `2 log LR` exceeds `DECISIVE` when its mean is `lam` (variance
    `4 lam`)."""
    if lam <= 0:
        return 0.0
    return float(scipy.stats.norm.cdf((lam - DECISIVE) / (2.0 * math.sqrt(lam))))


@dataclass
class Hypothesis:
    """One rival model made ready: its name (file), its profile layout and its readings'
    column order mapped to the common one."""

    name: str
    prepared: Prepared
    order: tuple[int, ...]  # its sensor columns in the common order
    spec: ModelSpec = None  # the model as its file gives it (what `fit` takes)

    @property
    def args(self):
        """What `_readings` needs besides `theta` and the profile: arrays, then statics."""
        p = self.prepared
        return (p.template, p.data), (p.index, self.order, p.chamber)

    def readings(self, theta, T, P):
        arrays, statics = self.args
        return _readings(theta, T, P, *arrays, *statics)


def _readings(theta, T, P, template, data, index, order, chamber):
    """Free-run readings (times, sensors) in the common column order."""
    import dataclasses

    from ..dynamics._sensitivity import dataset_outputs
    from ..model._parameters import with_free_parameters

    state = with_free_parameters(template, index, theta)
    u = jnp.stack([T if c else P for c in chamber], axis=1).astype(theta.dtype)
    data = dataclasses.replace(data, inputs=u[None])
    return dataset_outputs(state.model, data, state.run_initial)[0][:, np.array(order)]


@functools.partial(jax.jit, static_argnames=("index", "order", "chamber"))
def _residual_and_jacobian_of(theta, T, P, target, sigma, template, data, index, order,
                              chamber):
    def r(t):
        return ((target - _readings(t, T, P, template, data, index, order, chamber))
                / sigma[None, :]).reshape(-1)

    return r(theta), jax.jacfwd(r)(theta)


def _hypotheses(specs: list[tuple[str, ModelSpec]], ts, limits: ChamberLimits, noise):
    out, columns = [], None
    for name, spec in specs:
        prep = prepare_profiles(spec, ts, limits.start_c, limits.start_power_w, noise)
        cols = list(prep.spec.sensor_columns)
        if columns is None:
            columns, sigma = cols, prep.sigma
            roles = _roles(prep)
        if sorted(cols) != sorted(columns):
            raise InputError(f"the rival reads the sensor columns {', '.join(cols)}, the model "
                             f"{', '.join(columns)}; rivals must read the same sensors.",
                             file=spec.source, field="sensors")
        if _roles(prep) != roles:
            raise InputError("the rival's inputs differ from the model's (a chamber "
                             "temperature and a power must drive both alike).",
                             file=spec.source, field="boundaries")
        out.append(Hypothesis(name, prep, tuple(cols.index(c) for c in columns), spec))
    return out, columns, sigma


def _roles(prep: Prepared) -> tuple[bool, bool]:
    return (any(prep.chamber), not all(prep.chamber))


def _residual_and_jacobian(h: Hypothesis, sigma):
    arrays, statics = h.args
    index, order, chamber = statics

    def rj(theta, T, P, target):
        return _residual_and_jacobian_of(theta, T, P, target, sigma, *arrays, index=index,
                                         order=order, chamber=chamber)

    return rj


def refit(h: Hypothesis, theta0, T, P, target, sigma, rj=None, max_steps: int = 60):
    """The rival's parameters (P,) that best reproduce `target` (times, sensors) on the
    profile, and the weighted misfit `λ = ‖(target − y)/σ‖²`: the better of `fit` (the
    fit a user would run, from the file's values) and Levenberg–Marquardt from `theta0`,
    each polished by Levenberg–Marquardt."""
    rj = rj or _residual_and_jacobian(h, sigma)
    best = _lm(theta0, T, P, target, rj, max_steps)
    by_fit = _fitted(h, T, P, target)
    if by_fit is not None:
        other = _lm(by_fit, T, P, target, rj, max_steps)
        if other[1] < best[1]:
            best = other
    return best


def _fitted(h: Hypothesis, T, P, target):
    """The rival's parameters as `fit` finds them on the noise-free readings `target`."""
    import warnings

    from ..fitting import fit
    from ..measurements._data import Experiment

    boundary = set(h.spec.boundary_columns)
    T, P, target = (np.asarray(a, float) for a in (T, P, target))
    U = np.stack([T if c in boundary else P for c in h.spec.input_columns], axis=1)
    inverse = np.argsort(np.asarray(h.order))  # common order -> the rival's own
    ts = h.prepared.data.ts[0]
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = fit(h.spec, [Experiment(np.asarray(ts), U, target[:, inverse], name=h.name)],
                      polish=False, restart_plateaus=False)
    except (ValueError, FloatingPointError):
        return None
    if res.theta is None or len(res.theta) != len(h.prepared.names):
        return None
    return np.asarray(res.theta, float)


def _lm(theta0, T, P, target, rj, max_steps: int):
    """Levenberg–Marquardt from `theta0`: `(theta, λ)`. A trial that overflows is a
    rejected step."""
    with np.errstate(all="ignore"):
        return _lm_steps(theta0, T, P, target, rj, max_steps)


def _lm_steps(theta0, T, P, target, rj, max_steps: int):
    theta = np.asarray(theta0, float)
    r, J = (np.asarray(a) for a in rj(jnp.asarray(theta), T, P, target))
    cost, mu = float(r @ r), 1e-3
    for _ in range(max_steps):
        g, H = J.T @ r, J.T @ J
        d = np.diag(H).copy() + 1e-300
        try:
            step = np.linalg.solve(H + mu * np.diag(d), g)
        except np.linalg.LinAlgError:
            step = np.full_like(theta, np.nan)
        if not np.all(np.isfinite(step)):
            mu *= 10
            if mu > 1e8:
                break
            continue
        # J = ∂r/∂θ = −∂y/∂θ / σ: the Gauss-Newton step is −(JᵀJ)⁻¹ Jᵀ r
        trial = theta - step
        r2, J2 = (np.asarray(a) for a in rj(jnp.asarray(trial), T, P, target))
        c2 = float(r2 @ r2)
        if np.isfinite(c2) and c2 < cost:
            done = cost - c2 < 1e-10 * max(cost, 1e-300)
            theta, r, J, cost, mu = trial, r2, J2, c2, max(mu / 3, 1e-9)
            if done:
                break
        else:
            mu *= 4
            if mu > 1e8:
                break
    return theta, cost


@dataclass
class Discrimination:
    """A profile designed to tell the hypotheses apart, and what it is expected to do.

    - `names`: the hypotheses (the model first, then the rivals).
    - `pairs`: `(a, b)` -> `{"expected_2log_lr", "p_decisive"}` when `a` is true and `b`
      is refitted, for the design and for each reference (`references[name][(a, b)]`).
    """

    schedule: ProfileSchedule
    params: np.ndarray
    temperature: np.ndarray
    power: np.ndarray
    names: list[str]
    pairs: dict
    references: dict
    columns: list[str]
    sigma: np.ndarray
    wall_time_s: float
    violations: list[str] = field(default_factory=list)

    @property
    def ts(self):
        return self.schedule.ts


def discriminate(specs: list[tuple[str, ModelSpec]], duration_s: float, *,
                 limits: ChamberLimits | None = None, dt: float = 1.0, n_starts: int = 2,
                 rounds: int = 2, temperature_segments: int | None = None,
                 power_segments: int | None = None, noise: float | None = None, seed: int = 0,
                 max_steps: int = 100, references: tuple[str, ...] = REFERENCES,
                 progress=None) -> Discrimination:
    """Design a profile of `duration_s` s that tells the models `specs` (`(name, spec)`,
    the first the model, the others its rivals) apart; see the module's docstring."""
    from ._design import KNOT_S, POWER_STEP_S

    say = progress or (lambda *a, **k: None)
    if len(specs) < 2:
        raise InputError("discrimination needs the model and at least one rival.",
                         field="--rivals")
    limits = limits or ChamberLimits()
    n_periods = max(int(round(duration_s / dt)), 1)
    K = (min(max(int(round(duration_s / KNOT_S)), 1), n_periods)
         if temperature_segments is None else temperature_segments)
    M = (min(max(int(round(duration_s / POWER_STEP_S)), 1), n_periods)
         if power_segments is None else power_segments)
    spec0 = specs[0][1]
    K = K if spec0.boundary_columns else 0
    M = M if spec0.heat_columns else 0
    schedule = ProfileSchedule(float(duration_s), float(dt), limits, K, M)
    t0 = time.perf_counter()
    say("preparing the rival models over the profile's samples")
    hyps, columns, sigma = _hypotheses(specs, schedule.ts, limits, noise)
    sig = jnp.asarray(sigma)
    pairs = [(a, b) for a in range(len(hyps)) for b in range(len(hyps)) if a != b]
    rjs = {b: _residual_and_jacobian(hyps[b], sig) for b in range(len(hyps))}
    truth = {a: jnp.asarray(hyps[a].prepared.theta) for a in range(len(hyps))}

    def refits(T, P, start=None):
        out = {}
        for a, b in pairs:
            target = hyps[a].readings(truth[a], T, P)
            th0 = hyps[b].prepared.theta if start is None else start[(a, b)][0]
            out[(a, b)] = refit(hyps[b], th0, T, P, target, sig, rjs[b])
        return out

    def loss_fn(z, fitted):
        T, P = schedule.sampled(z)
        total = 0.0
        for a, b in pairs:
            d = ((hyps[a].readings(truth[a], T, P) - hyps[b].readings(fitted[(a, b)], T, P))
                 / sig[None, :]).reshape(-1)
            J = jax.jacfwd(lambda t: (hyps[b].readings(t, T, P) / sig[None, :]).reshape(-1))(
                fitted[(a, b)])
            H = J.T @ J
            s = jnp.sqrt(jnp.clip(jnp.diag(H), 1e-300))
            g = (J.T @ d) / s
            lam = d @ d - g @ jnp.linalg.solve(H / (s[:, None] * s[None, :])
                                               + 1e-10 * jnp.eye(H.shape[0]), g)
            total = total - jnp.log(jnp.maximum(lam, 1e-12))
        return total

    value_and_grad = jax.jit(jax.value_and_grad(loss_fn))
    rng = np.random.default_rng(seed)
    n = schedule.n_parameters
    best = None
    for i in range(max(n_starts, 1)):
        z = prbs_start(schedule) if i == 0 else rng.normal(0.0, 2.0, n)
        fitted = None
        for r in range(max(rounds, 1)):
            say(f"search {i + 1}/{n_starts}, round {r + 1}/{rounds}: refitting the rivals "
                f"({time.perf_counter() - t0:.0f} s)")
            T, P = schedule.sampled(jnp.asarray(z))
            fitted = refits(T, P, fitted)
            thetas = {k: jnp.asarray(v[0]) for k, v in fitted.items()}

            def fun(x):
                v, g = value_and_grad(jnp.asarray(x), thetas)
                v, g = float(v), np.asarray(g, float)
                return (v, g) if np.isfinite(v) else (1e300, np.zeros_like(g))

            if n:
                res = scipy.optimize.minimize(fun, z, jac=True, method="L-BFGS-B",
                                              bounds=[(-_Z_BOUND, _Z_BOUND)] * n,
                                              options={"maxiter": max_steps})
                z = np.asarray(res.x)
        T, P = schedule.sampled(jnp.asarray(z))
        final = refits(T, P, fitted)
        score = -sum(math.log(max(v[1], 1e-12)) for v in final.values())
        if best is None or score < best[0]:
            best = (score, z, final)
    wall = time.perf_counter() - t0
    _, z, final = best
    T, P = (np.asarray(a) for a in schedule.sampled(jnp.asarray(z)))
    names = [h.name for h in hyps]

    def summary(fits):
        return {(names[a], names[b]): {"expected_2log_lr": float(v[1]),
                                       "p_decisive": decisive_probability(float(v[1]))}
                for (a, b), v in fits.items()}

    refs = {}
    say(f"judging the references ({time.perf_counter() - t0:.0f} s)")
    for name in references:
        rT, rP = reference_inputs(name, schedule, spec0)
        # a reference starts where the design does only if its first sample does
        if rT[0] != limits.start_c or rP[0] != limits.start_power_w:
            lim = ChamberLimits(limits.temperature_c, limits.ramp_c_per_min, limits.power_w,
                                float(rT[0]), float(rP[0]))
            rh, _, _ = _hypotheses(specs, schedule.ts, lim, noise)
        else:
            rh = hyps
        fits = {}
        for a, b in pairs:
            target = rh[a].readings(jnp.asarray(rh[a].prepared.theta), jnp.asarray(rT),
                                    jnp.asarray(rP))
            fits[(a, b)] = refit(rh[b], rh[b].prepared.theta, jnp.asarray(rT), jnp.asarray(rP),
                                 target, sig)
        refs[name] = summary(fits)
    return Discrimination(schedule, z, T, P, names, summary(final), refs, columns,
                          np.asarray(sigma), wall, limits.violations(schedule.ts, T, P))
