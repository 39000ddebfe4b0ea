"""`thermojax compensate` (docs/formats.md §5): reconstruct one input of a model (the
fast temperature a lagging sensor sees) from the sensor columns of a log.

The model is the one the firmware observer runs (`reconstruction_observer`: the input
as a random-walk state, at the log's sample period). Its one tuning knob, the input's
diffusion `input_noise` (°C/√s), is chosen by maximum likelihood of the steady-state
observer's innovations over a grid, unless given.

A log is read whole, so the estimate written is the fixed-interval (Rauch–Tung–
Striebel) smoother of that model: a Kalman filter from an honest prior (the input
as uncertain as the readings' spread allows) forward, then backward, so each sample
is estimated from readings on both sides of it, and `std` is that estimate's own std
at every sample. Near the record's ends fewer readings lie on one side, so the std
grows there (at the last sample the smoother is the causal filter); `settled` marks
the samples whose std is within 25 % of the smoother's interior (steady-state) std.
The causal estimate the firmware observer gives (`export --reconstruct`) is kept as
`causal`. Where the std is larger than the spread of the signal it reconstructs, the
log does not determine the input, and `warning` says so.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._errors import InputError
from ._input_reconstruction import augment_unknown_input
from ._kalman import discrete_process_covariance, steady_state_kalman
from ._observer import Observer, run_observer

INPUT_NOISE_GRID = np.logspace(-4.0, 1.0, 16)  # °C/√s


SETTLED = 1.25  # a sample is settled when its std is within 25 % of the interior std


@dataclass
class Compensation:
    """`ts` (T,) s; `estimate` and `std` (T,) in the input's unit: the smoothed estimate
    and its std at every sample; `settled` (T,) bool: the std within 25 % of the
    interior std (False near the record's ends); `causal` (T,): the firmware
    observer's causal estimate; `interior_std`: the smoother's std away from the ends;
    `filter_std`: the causal observer's steady-state std; the `input_noise` used
    (°C/√s) and whether the likelihood chose it; `warning`: None, or why the estimate
    should not be trusted."""

    ts: np.ndarray
    estimate: np.ndarray
    std: np.ndarray
    input_noise: float
    chosen: bool
    settled: np.ndarray | None = None
    causal: np.ndarray | None = None
    interior_std: float = float("nan")
    filter_std: float = float("nan")
    warning: str | None = None


class _Designs:
    """The observers of one model, input and period for any input noise: the sampled
    system and the process covariance's two parts (the nodes' own, and the input's per
    unit q²) computed once, so a grid of input noises costs one Riccati solve each."""

    def __init__(self, model, system, input_index, dt):
        from ..dynamics._discretize import discretize

        aug = augment_unknown_input(system, input_index)
        self.discrete = discretize(aug, dt)
        nodes = np.asarray(model.process_noise, float)
        self.qd_nodes = np.asarray(discrete_process_covariance(aug.A, np.r_[nodes, 0.0], dt),
                                   float)
        self.qd_unit = np.asarray(discrete_process_covariance(
            aug.A, np.r_[np.zeros_like(nodes), 1.0], dt), float)
        self.noise = np.asarray(model.noise, float)

    def qd(self, q_input: float) -> np.ndarray:
        return self.qd_nodes + q_input ** 2 * self.qd_unit

    def __call__(self, q_input: float):
        """`(Observer, KalmanGain, DiscreteSystem)` at input noise `q_input` (°C/√s)."""
        import jax.numpy as jnp

        kalman = steady_state_kalman(self.discrete, self.qd(q_input), self.noise ** 2)
        return Observer(self.discrete, jnp.asarray(kalman.gain)), kalman, self.discrete


def _solve_right(M, P):
    """`M P⁻¹` for a covariance `P` (a pseudo-inverse where it is singular)."""
    try:
        return np.linalg.solve(P.T, M.T).T
    except np.linalg.LinAlgError:
        return M @ np.linalg.pinv(P)


def smooth(discrete, qd, noise, u, y, x0, P0):
    """The Kalman filter from `(x0, P0)` and the Rauch–Tung–Striebel smoother of the
    sampled system `discrete` (`x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1] + w`, `w ~ N(0,
    qd)`; `y = C x + D u + v`, `v ~ N(0, diag(noise²))`), in NumPy.

    Returns `(xs, Ps)`: the smoothed states (T, n) and their covariances (T, n, n).
    """
    Phi, B0, B1 = (np.asarray(discrete.Phi, float), np.asarray(discrete.B0, float),
                   np.asarray(discrete.B1, float))
    C, D = np.asarray(discrete.C, float), np.asarray(discrete.D, float)
    R = np.diag(np.asarray(noise, float) ** 2)
    T, n = len(y), Phi.shape[0]
    eye = np.eye(n)
    xp, Pp = np.zeros((T, n)), np.zeros((T, n, n))
    xf, Pf = np.zeros((T, n)), np.zeros((T, n, n))
    x, P = np.asarray(x0, float), np.asarray(P0, float)
    for k in range(T):
        if k > 0:
            x = Phi @ xf[k - 1] + B0 @ u[k - 1] + B1 @ u[k]
            P = Phi @ Pf[k - 1] @ Phi.T + qd
        xp[k], Pp[k] = x, P
        S = C @ P @ C.T + R
        K = _solve_right(P @ C.T, S)
        ImKC = eye - K @ C
        xf[k] = x + K @ (y[k] - C @ x - D @ u[k])
        Pf[k] = ImKC @ P @ ImKC.T + K @ R @ K.T  # Joseph form: symmetric, positive
    xs, Ps = xf.copy(), Pf.copy()
    for k in range(T - 2, -1, -1):
        J = _solve_right(Pf[k] @ Phi.T, Pp[k + 1])
        xs[k] = xf[k] + J @ (xs[k + 1] - xp[k + 1])
        Ps[k] = Pf[k] + J @ (Ps[k + 1] - Pp[k + 1]) @ J.T
    return xs, Ps


def interior_std(discrete, kalman, index: int, steps: int = 100_000) -> float:
    """The smoother's std of state `index` far from both ends of a long record: the
    backward covariance recursion iterated with the steady-state filter's
    covariances until it stops changing."""
    Phi = np.asarray(discrete.Phi, float)
    Pf, Pp = np.asarray(kalman.filtered_covariance), np.asarray(kalman.predicted_covariance)
    J = _solve_right(Pf @ Phi.T, Pp)
    Ps = Pf.copy()
    for _ in range(steps):
        new = Pf + J @ (Ps - Pp) @ J.T
        done = np.max(np.abs(new - Ps)) <= 1e-12 * max(np.max(np.abs(Ps)), 1e-300)
        Ps = new
        if done:
            break
    return float(np.sqrt(max(Ps[index, index], 0.0)))


def _log_likelihood(kalman, discrete, noise, innovations) -> float:
    C = np.asarray(discrete.C, float)
    S = C @ kalman.predicted_covariance @ C.T + np.diag(np.asarray(noise, float) ** 2)
    _, logdet = np.linalg.slogdet(S)
    quad = np.einsum("ti,ij,tj->", innovations, np.linalg.inv(S), innovations)
    return float(-0.5 * (len(innovations) * logdet + quad))


def compensate(spec, telemetry, column: str, input_noise: float | None = None,
               say=None) -> Compensation:
    """Reconstruct input `column` of the model `spec` over one log (`Telemetry`)."""
    import equinox as eqx
    import jax.numpy as jnp

    from ..model._model import ThermalModel
    from ..model.effects import lower_effects

    say = say or (lambda _m: None)
    source = telemetry.path or "<log>"
    lowered = lower_effects(spec).spec
    model = ThermalModel.from_spec(lowered)
    if model.is_nonlinear:
        kinds = sorted({t.kind for t in model.effect_terms})
        raise InputError(f"the model has nonlinear effects ({', '.join(kinds)}); compensate "
                         "runs the linear observer firmware runs: export it at an operating "
                         "point (`thermojax export`) or remove the effects.",
                         file=spec.source, field="effects")
    inputs = list(lowered.input_columns)
    if column not in inputs:
        raise InputError(f"'{column}' is not an input of the model; its inputs are "
                         f"{inputs}. Name the input to reconstruct.", field="--input")
    ts = np.asarray(telemetry.ts, float)
    if len(ts) < 2:
        raise InputError("the log needs at least two samples.", file=source)
    steps = np.diff(ts)
    dt = float(np.median(steps))
    if np.max(np.abs(steps - dt)) > 1e-6 * dt:
        k = int(np.argmax(np.abs(steps - dt)))
        raise InputError(f"the samples are not uniform (a step of {steps[k]:g} s at row "
                         f"{k + 2} against the median {dt:g} s); the observer runs at one "
                         "rate: run `thermojax resample` on the log first.",
                         file=source, field="time_s")
    rest = [c for c in inputs if c != column]
    needed = [*rest, *lowered.sensor_columns]
    for c in needed:
        if c not in telemetry.names:
            raise InputError(f"no column '{c}' (the model needs it); the log has "
                             f"{list(telemetry.names)}.", file=source, field=c)
        bad = ~np.isfinite(np.asarray(telemetry.column(c), float))
        if bad.any():
            raise InputError(f"column '{c}' has an empty or non-finite cell at row "
                             f"{int(np.argmax(bad)) + 1} of the data; the observer needs every "
                             "sample: run `thermojax resample --model ...` to fill the "
                             "inputs, or cut the log.", file=source, field=c)
    u = np.stack([np.asarray(telemetry.column(c), float) for c in rest], 1) if rest else \
        np.zeros((len(ts), 0))
    y = np.stack([np.asarray(telemetry.column(c), float) for c in lowered.sensor_columns], 1)
    system = model.linear_system()
    j = inputs.index(column)
    # the prior: the steady state with the unknown input at the first reading (a
    # temperature input: the sensors read it at rest), or at zero (a power)
    guess = float(np.mean(y[0])) if column in lowered.boundary_columns else 0.0
    u0 = np.insert(u[0], j, guess)
    x0 = jnp.concatenate([system.steady_state(jnp.asarray(u0)), jnp.asarray([guess])])

    scan = eqx.filter_jit(run_observer)  # traced once for the whole grid of input noises
    designs = _Designs(model, system, j, dt)

    def run(q):
        obs, kalman, discrete = designs(q)
        out = scan(obs, jnp.asarray(u), jnp.asarray(y), x0)
        return out, kalman, discrete

    chosen = input_noise is None
    if chosen:
        best = None
        for q in INPUT_NOISE_GRID:
            try:
                out, kalman, discrete = run(q)
            except InputError:
                continue
            ll = _log_likelihood(kalman, discrete, model.noise, np.asarray(out.innovations))
            if best is None or ll > best[0]:
                best = (ll, q)
        if best is None:
            raise InputError("no observer could be designed: the sensors do not observe the "
                             f"input '{column}'.", file=spec.source, field="--input")
        input_noise = float(best[1])
        say(f"input noise {input_noise:.3g} °C/√s, chosen by maximum likelihood")
    out, kalman, discrete = run(float(input_noise))
    causal = np.asarray(out.states)[:, -1]
    filter_std = float(np.sqrt(max(kalman.filtered_covariance[-1, -1], 0.0)))
    qd = designs.qd(float(input_noise))
    # the prior: the steady-state uncertainty, and the input (with every node) as
    # uncertain as the spread of the readings allows (converted to the input's unit by
    # the sensors' steady-state gain to it)
    spread = max(float(np.max(np.ptp(y, axis=0))), float(np.max(model.noise)))
    A, B = np.asarray(system.A, float), np.asarray(system.B, float)
    Cs, Ds = np.asarray(system.C, float), np.asarray(system.D, float)
    dc = np.abs(Cs @ np.linalg.solve(A, -B[:, j]) + Ds[:, j])
    sigma_u = spread / max(float(np.max(dc)), 1e-12)
    P0 = np.asarray(kalman.predicted_covariance, float) + np.diag(
        np.r_[np.full(A.shape[0], spread), sigma_u] ** 2)
    u_np = np.asarray(u, float)
    xs, Ps = smooth(discrete, qd, model.noise, u_np, y, np.asarray(x0, float), P0)
    estimate = xs[:, -1]
    std = np.sqrt(np.maximum(Ps[:, -1, -1], 0.0))
    inner = interior_std(discrete, kalman, -1)
    settled = std <= SETTLED * inner
    warning = _warning(column, estimate, std, settled, inner)
    return Compensation(ts, estimate, std, float(input_noise), chosen, settled=settled,
                        causal=causal, interior_std=inner, filter_std=filter_std,
                        warning=warning)


def _warning(column, estimate, std, settled, inner) -> str | None:
    """Why the estimate should not be trusted, or None: its typical std larger than the
    spread (std over time) of the signal it reconstructs, so most of what it shows may
    be noise."""
    where = settled if settled.sum() >= 2 else np.ones_like(settled)
    typical = float(np.median(std[where]))
    signal = float(np.std(estimate[where]))
    if typical <= signal:
        return None
    return (f"the reconstruction of {column} is not determined by this log: its std "
            f"({typical:.3g} at a typical sample) is larger than the spread of the signal "
            f"it reconstructs ({signal:.3g}, the estimate's std over time), so most of "
            "what it shows may be noise. A faster or less noisy sensor, a shorter sample "
            "period or a model with less lag between the input and the sensor would "
            "determine it; the std column says how far to trust each sample.")
