"""`thermojax compensate` (docs/formats.md §5): reconstruct one input of a model (the
fast temperature a lagging sensor sees) from the sensor columns of a log.

The observer is the one firmware runs (`reconstruction_observer`: the input as a
random-walk state, a steady-state Kalman gain), causal, at the log's sample period.
Its one tuning knob, the input's diffusion `input_noise` (°C/√s), is chosen by
maximum likelihood of the innovations over a grid, unless given. The std is the
steady-state filtered one, `sqrt(P_f[input, input])`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._errors import InputError
from ._input_reconstruction import augment_unknown_input
from ._kalman import discrete_process_covariance, steady_state_kalman
from ._observer import Observer, run_observer

INPUT_NOISE_GRID = np.logspace(-4.0, 1.0, 16)  # °C/√s


@dataclass
class Compensation:
    """`ts` (T,) s, `estimate` and `std` (T,) in the input's unit, the `input_noise`
    used (°C/√s) and whether the likelihood chose it."""

    ts: np.ndarray
    estimate: np.ndarray
    std: np.ndarray
    input_noise: float
    chosen: bool


def _observer(model, system, input_index, dt, q_input):
    from ..dynamics._discretize import discretize

    aug = augment_unknown_input(system, input_index)
    discrete = discretize(aug, dt)
    q = np.concatenate([np.asarray(model.process_noise, float), [q_input]])
    kalman = steady_state_kalman(discrete, discrete_process_covariance(aug.A, q, dt),
                                 np.asarray(model.noise, float) ** 2)
    import jax.numpy as jnp

    return Observer(discrete, jnp.asarray(kalman.gain)), kalman, discrete


def _log_likelihood(kalman, discrete, noise, innovations) -> float:
    C = np.asarray(discrete.C, float)
    S = C @ kalman.predicted_covariance @ C.T + np.diag(np.asarray(noise, float) ** 2)
    _, logdet = np.linalg.slogdet(S)
    quad = np.einsum("ti,ij,tj->", innovations, np.linalg.inv(S), innovations)
    return float(-0.5 * (len(innovations) * logdet + quad))


def compensate(spec, telemetry, column: str, input_noise: float | None = None,
               say=None) -> Compensation:
    """Reconstruct input `column` of the model `spec` over one log (`Telemetry`)."""
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

    def run(q):
        obs, kalman, discrete = _observer(model, system, j, dt, q)
        out = run_observer(obs, jnp.asarray(u), jnp.asarray(y), x0)
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
    out, kalman, _ = run(float(input_noise))
    estimate = np.asarray(out.states)[:, -1]
    std = np.full(len(ts), float(np.sqrt(max(kalman.filtered_covariance[-1, -1], 0.0))))
    return Compensation(ts, estimate, std, float(input_noise), chosen)
