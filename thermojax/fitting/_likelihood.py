"""The two likelihoods of measured runs: output error and the Kalman prediction error.

Both follow docs/formats.md §2 ("Likelihood"), the definitions of CTSM-R and pySIP:

- output error: free-run simulation residuals `e = y - ŷ`, Gaussian with one
  std per sensor, `-log L = Σ_j [N_j/2 log(2π σ_j²) + Σ e²/(2σ_j²)]`;
- Kalman: continuous-discrete filter, update before predict, every measured
  sample included, `-log L = Σ_k ½ (log det(2π S_k) + e_kᵀ S_k⁻¹ e_k)`.

Dropped samples (NaN in the CSV, `mask` False) contribute nothing.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..compilation._traced_cache import stored_jit
from ..measurements._data import Dataset
from ..dynamics._discretize import discretize, discretize_process_noise, sample_period
from ..model._model import ThermalModel
from ..dynamics._etdrk4 import etdrk4_step
from ..dynamics._nonlinear import initial_state_nonlinear
from ..dynamics._sensitivity import dataset_block_outputs

LOG_2PI = math.log(2 * math.pi)


def simulate_dataset(model: ThermalModel, data: Dataset, run_initial=None
                     ) -> Float[Array, "runs times outputs"]:
    """Free-run outputs of every run (°C), each from its own initial state (`run_initial`:
    (runs, len(model.initial_nodes)) °C, or the model's). The blocked exact-hold
    recurrence of `dynamics._sensitivity`: the simulator the fit differentiates."""
    return dataset_block_outputs(model, data, run_initial)[:, :data.outputs.shape[1]]


def output_error_nll(residuals: np.ndarray, mask: np.ndarray, sigma: np.ndarray) -> float:
    """`-log L` of residuals (runs, times, outputs) °C with per-sensor std `sigma` (outputs,)
    °C, in NumPy."""
    return output_error_nll_from_sums((residuals ** 2).sum(axis=(0, 1)), mask.sum(axis=(0, 1)),
                                      sigma)


def output_error_nll_from_sums(ssr: np.ndarray, n: np.ndarray, sigma: np.ndarray) -> float:
    """`output_error_nll` from each sensor's sum of squared residuals `ssr` (°C²) over its
    `n` measured samples, std `sigma` (outputs,) °C."""
    return float(np.sum(0.5 * n * (LOG_2PI + 2 * np.log(sigma)) + 0.5 * ssr / sigma ** 2))


def ml_sigma(residuals: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """The maximum-likelihood noise std per sensor `sqrt(SSR_j / N_j)` (outputs,) °C, in
    NumPy."""
    n = np.maximum(mask.sum(axis=(0, 1)), 1)
    return np.sqrt((residuals ** 2).sum(axis=(0, 1)) / n)


class KalmanOutput(eqx.Module):
    """Per-sample filter quantities of one run."""

    nll: Float[Array, ""]
    innovations: Float[Array, "times outputs"]  # e_k (0 where unmeasured)
    innovation_std: Float[Array, "times outputs"]  # sqrt(diag S_k)
    m_filt: Float[Array, "times states"]
    P_filt: Float[Array, "times states states"]
    m_pred: Float[Array, "times states"]  # prior mean at k (before the update)
    P_pred: Float[Array, "times states states"]
    sample_nll: Float[Array, " times"]  # each sample's term of `nll` (0 where unmeasured)
    innovation_cov: Float[Array, "times outputs outputs"]  # S_k (identity rows where unmeasured)


def kalman_run(model: ThermalModel, ts, u, y, mask, run_initial=None, substeps=None
               ) -> KalmanOutput:
    """The continuous-discrete Kalman filter over one run (covariance update `P − K S Kᵀ`).

    Process noise `Qc = diag(q²)` is discretized by Van Loan; inputs are held
    as their `hold` says; the initial mean is the model's initial state, the
    initial covariance `diag(initial_std²)`. A linear model's covariances do not depend
    on the data: once they settle (`_settled`) they are reused until a sample is missing
    (`_settling_covariances`). `substeps`: a nonlinear model's integration steps per
    sample period (`_extended_transition`) when not `model.etd2_substeps` (possibly
    traced: `_integration`'s check).
    """
    system = model.linear_system()
    dt = sample_period(ts)  # the median step (docs/formats.md §1 allows jitter)
    _, Qd = discretize_process_noise(system.A, jnp.diag(model.process_noise ** 2), dt)
    R = jnp.diag(model.noise ** 2)
    C = system.C
    m0 = (initial_state_nonlinear(model, system, u[0], run_initial) if model.is_nonlinear
          else model.initial_state(system, u[0], run_initial))
    offset = model.output_offset()
    P0 = jnp.diag(model.initial_std ** 2)
    u_next = jnp.concatenate([u[1:], u[-1:]], axis=0)

    def mean_update(m, g: _Covariances, inp):
        """The filtered mean and the sample's outputs."""
        _, _, y_k, mask_k = inp
        e = jnp.where(mask_k, y_k - C @ m - offset, 0.0)
        w = g.W @ e
        m_f = m + g.K @ e
        return m_f, (0.5 * (g.logdet + w @ w), e, g.std, m_f, g.P_f, m, g.P, g.S)

    inputs = (u, u_next, y, mask)
    if model.is_nonlinear:  # the extended filter: Φ depends on the mean, nothing settles
        transition = _extended_transition(model, system, dt, substeps)

        def step(carry, inp):
            m, P = carry
            g = _update(P, inp[3], C, R)
            m_f, out = mean_update(m, g, inp)
            m_next, F = transition(m_f, inp[0], inp[1])
            P_next = F @ g.P_f @ F.T + Qd
            return (m_next, 0.5 * (P_next + P_next.T)), out

        _, outs = jax.lax.scan(step, (m0, P0), inputs)
    else:
        disc = discretize(system, dt)

        def linear_step(m, g, inp):
            m_f, out = mean_update(m, g, inp)
            return disc.Phi @ m_f + disc.B0 @ inp[0] + disc.B1 @ inp[1], out

        def settled_chunk(m, g, chunk):
            """`linear_step` over a fully measured chunk at the settled covariances `g`:
            the filter is then time-invariant, `m⁺ = F m + b_k` with `F = Φ(I − KC)`, so
            one product a sample is left in the recursion and the mean updates are
            computed for the whole chunk at once."""
            u_k, u_k1, y_k, _ = chunk
            F = disc.Phi - disc.Phi @ g.K @ C
            b = (y_k - offset[None]) @ (disc.Phi @ g.K).T + u_k @ disc.B0.T + u_k1 @ disc.B1.T
            priors, m_end = _time_invariant(F, b, m)
            _, outs = jax.vmap(lambda m_k, inp: mean_update(m_k, g, inp))(priors, chunk)
            return m_end, outs

        outs = _settling_covariances(_riccati_step(C, R, disc.Phi, Qd), linear_step, m0,
                                     P0, inputs, mask, settled_chunk)
    nll, e, s, m_f, P_f, m_p, P_p, S = outs
    return KalmanOutput(jnp.sum(nll), e, s, m_f, P_f, m_p, P_p, nll, S)


class _Covariances(NamedTuple):
    """One sample's covariances: prior `P`, innovation `S` = L Lᵀ, gain `K`, posterior
    `P_f` (the sensors `mask` measured) and what the mean update takes from them (`W`,
    `logdet`, `std`); a linear filter's also the next prior `P_next` and whether it
    `settles` (the measurement update's `_update` leaves them None; `_riccati_step` fills
    them)."""

    P: jax.Array
    S: jax.Array
    L: jax.Array
    K: jax.Array
    P_f: jax.Array
    mask: jax.Array  # (outputs,) which sensors measured
    W: jax.Array  # L⁻¹: whitens the innovations
    logdet: jax.Array  # log det(2π S), the measured rows' (unmeasured rows: S = 1)
    std: jax.Array  # sqrt(diag S), 0 where unmeasured
    P_next: jax.Array | None = None
    settles: jax.Array | None = None


def _update(P, mask_k, C, R) -> _Covariances:
    """The measurement update's covariances at prior `P`, the sensors `mask_k` measured
    (unmeasured rows of `S` are identity rows, their gain columns zero). The posterior is
    `P − K S Kᵀ` as `P − UᵀU`: with the optimal gain the Joseph form's matrix, at half the
    cost of its forward derivatives (the Riccati steps of a scoring call); a measured
    node's posterior variance carries a relative rounding error of about 1e-16 × prior /
    sensor variance (1e-12 for a prior of 1 °C² and a sensor of 0.01 °C)."""
    Cm = C * mask_k[:, None]
    both = mask_k[:, None] & mask_k[None, :]
    S = jnp.where(both, Cm @ P @ Cm.T + R, jnp.eye(C.shape[0]))
    L = jnp.linalg.cholesky(S)
    W = jax.scipy.linalg.solve_triangular(L, jnp.eye(C.shape[0]), lower=True)
    U = W @ (Cm @ P)  # L⁻¹ C P: the gain is Uᵀ L⁻¹ = P Cᵀ S⁻¹, and K S Kᵀ = Uᵀ U
    return _Covariances(
        P, S, L, U.T @ W, P - U.T @ U, mask_k, W=W,
        logdet=2 * jnp.sum(jnp.log(jnp.diag(L))) + mask_k.sum() * LOG_2PI,
        std=jnp.sqrt(jnp.diag(S)) * mask_k)


def _riccati_step(C, R, Phi, Qd):
    """`covariances(P, mask_k) -> _Covariances` of a linear filter: the measurement update
    at prior `P`, what the mean update takes from it (reused with it once settled), then
    the next prior `Φ P_f Φᵀ + Qd` and whether it settles (`_settled`, on the scale of the
    smallest sensor variance too)."""
    floor = jnp.min(jnp.diag(R))

    def covariances(P, mask_k):
        g = _update(P, mask_k, C, R)
        P_next = Phi @ g.P_f @ Phi.T + Qd
        P_next = 0.5 * (P_next + P_next.T)
        return g._replace(P_next=P_next, settles=_settled(P_next, P, floor))
    return covariances


# Relative change below which one Riccati step leaves the prior covariance settled: its
# derivatives then differ from the exact filter's by ~1e-12.
_SETTLED = 1e-14


def _settled(P_next, P, floor):
    """Whether one more step moved no element of the prior covariance by more than
    `_SETTLED` of its scale, `sqrt(P_ii P_jj)` + `floor` (°C²): a node whose variance
    decays towards zero (no process noise) settles once its changes are below the
    sensors' variance `floor`, which they cannot move by more than rounding."""
    d = jnp.sqrt(jnp.abs(jnp.diagonal(P)))
    return jnp.all(jnp.abs(P_next - P) <= _SETTLED * (jnp.outer(d, d) + floor))


def _time_invariant(F, b, x0):
    """`x_{j+1} = F x_j + b_j` from `x0` over `b` (L, n): `(x_0..x_{L-1}, x_L)`."""
    def step(x, b_j):
        return F @ x + b_j, x
    x_end, xs = jax.lax.scan(step, x0, b)
    return xs, x_end


def _settling_covariances(covariances, mean_step, x0, P0, inputs, mask, settled_chunk=None):
    """`lax.scan` of a linear filter whose covariances (`covariances(P, mask_k) ->
    _Covariances`) depend on the data only through which sensors measured: once a step
    with every sensor measured leaves `P` settled (`_Covariances.settles`), the next fully
    measured steps reuse its covariances (the Riccati recursion and its derivatives, most
    of a filter's work, are skipped) and a missing sample runs the recursion again. A
    steady state reached to rounding, so the likelihood is the exact filter's (to ~1e-15
    relative). `mean_step(x, g, inp) -> (x_next, out)`; returns the stacked `out`.

    Runs of `_CHUNKED_FROM` samples or more go in chunks of `_CHUNK`, one `lax.cond` a
    chunk (its carry's copies cost as much as a settled step) and the settled chunks'
    mean steps by `settled_chunk(x, g, chunk inputs) -> (x after the chunk, stacked
    out)`, by default `mean_step` by `mean_step`; shorter runs do not earn back the larger
    program's compilation and choose the covariances sample by sample."""
    def step(carry, inp, may_reuse=False):
        x, P, settled, last = carry
        inp_k, mask_k = inp
        full = jnp.all(mask_k)
        g = (jax.lax.cond(settled & full, lambda: last, lambda: covariances(P, mask_k))
             if may_reuse else covariances(P, mask_k))
        x_next, out = mean_step(x, g, inp_k)
        return (x_next, g.P_next, full & g.settles, g), out

    # never read (nothing has settled at the first step): zeros of the right structure
    unused = jax.tree.map(lambda a: jnp.zeros(a.shape, a.dtype),
                          jax.eval_shape(covariances, P0, mask[0]))
    start = (x0, P0, jnp.array(False), unused)
    n = mask.shape[0]
    if n < _CHUNKED_FROM:
        return jax.lax.scan(lambda c, inp: step(c, inp, may_reuse=True), start,
                            (inputs, mask))[1]

    if settled_chunk is None:
        def settled_chunk(x, g, chunk):
            return jax.lax.scan(lambda x, inp: mean_step(x, g, inp), x, chunk)

    def chunk_at_settled(carry, chunk):
        x, P, settled, last = carry
        x, outs = settled_chunk(x, last, chunk[0])
        return (x, P, settled, last), outs

    def one_chunk(carry, chunk):
        skip = carry[2] & jnp.all(chunk[1])
        return jax.lax.cond(skip, chunk_at_settled, lambda c, ch: jax.lax.scan(step, c, ch),
                            carry, chunk)

    pad = -n % _CHUNK  # unmeasured samples past the end: they change no output before it
    chunks = jax.tree.map(
        lambda a: jnp.concatenate([a, jnp.zeros((pad,) + a.shape[1:], a.dtype)]
                                  ).reshape((-1, _CHUNK) + a.shape[1:]), (inputs, mask))
    _, outs = jax.lax.scan(one_chunk, start, chunks)
    return jax.tree.map(lambda a: a.reshape((-1,) + a.shape[2:])[:n], outs)


# Samples per chunk of `_settling_covariances`, and the run length from which it chunks:
# chunks made the six-node IMU's scoring call (4,921 samples) a quarter faster and its
# programs compile 0.3-0.45 s slower. On PRBS1's 1,691 samples the loop took as long
# either way, and the tests' shorter runs were faster without (benchmarks/README.md).
_CHUNK = 16
_CHUNKED_FROM = 2000


def _extended_transition(model, system, dt, substeps=None):
    """`f(m, u_k, u_k1) -> (mean at the next sample, its Jacobian in m)` of a model with
    nonlinear effects: the fourth-order exponential step (`dynamics._etdrk4`: the
    filter's likelihood sees every sample's one-step error, which ETD2 made too large at
    few substeps) and its Jacobian (an extended Kalman filter). The Jacobian is the
    linearized step applied to the identity: the same numbers as `jax.jacfwd(step)`,
    with the step evaluated once (under the fit's own forward derivatives, the filter
    with the earlier ETD2 step ran 1.7× faster on PRBS1's four-state model).

    The substeps run as a loop, never written out: under the fit's forward derivatives
    the written-out steps' programs took longer to compile than they saved in calls
    (measured with ETD2: PRBS1's loop, whose last two steps fit nonlinear models in 4-8
    substeps: 80.9 s against 86.8 s, two runs each, the same likelihoods; at 16 substeps
    the scoring program's compilation measured 16 s against 30 s)."""
    step = etdrk4_step(model, system, dt,
                       model.etd2_substeps if substeps is None else substeps)

    def f(m, u_k, u_k1):
        m_next, tangent = jax.linearize(lambda x: step(x, u_k, u_k1), m)
        return m_next, jax.vmap(tangent, out_axes=1)(jnp.eye(m.shape[0], dtype=m.dtype))
    return f


def kalman_runs(model: ThermalModel, data: Dataset, run_initial, per_run, substeps=None):
    """`per_run(ts, kalman_run(...))` of every run, stacked over runs."""
    def one(ts, u, y, mask, r0):
        return per_run(ts, kalman_run(model, ts, u, y, mask, r0, substeps))

    if run_initial is None:
        return _each_run(lambda ts, u, y, m: one(ts, u, y, m, None),
                         data.ts, data.inputs, data.outputs, data.mask)
    return _each_run(one, data.ts, data.inputs, data.outputs, data.mask, run_initial)


def _each_run(fn, *arrays):
    """`fn` of every run's slices of `arrays`, stacked: a loop (`lax.map`), not `vmap`,
    so that a run's settled covariances skip their recursion (under `vmap` a `lax.cond`
    evaluates both branches)."""
    return jax.lax.map(lambda a: fn(*a), arrays)


def kalman_nll(model: ThermalModel, data: Dataset, run_initial=None, substeps=None
               ) -> Float[Array, ""]:
    """`-log L` of all runs under the Kalman filter (`substeps`: as `kalman_run`'s)."""
    return jnp.sum(kalman_runs(model, data, run_initial, lambda ts, kf: kf.nll, substeps))


# `kalman_nll` with the substeps traced: one program for every number (`_integration`).
# Called a few times per fit (its start's and its solution's check), so compiled as a
# program run about once: PRBS1's step 3 alone 47.3 s against 49.7 s (two runs each).
kalman_nll_in_substeps = stored_jit(kalman_nll, once=True)


@stored_jit(once=True)
def kalman_sample_nll(model: ThermalModel, data: Dataset, run_initial=None
                      ) -> Float[Array, "runs times"]:
    """Each sample's `−log p(y_k | y_<k)` under the filter (0 where unmeasured): summed
    over a held-out block, the prequential score of parameters fitted without it."""
    return kalman_runs(model, data, run_initial, lambda ts, kf: kf.sample_nll)


def rts_smoother(model: ThermalModel, ts, kf: KalmanOutput):
    """Rauch-Tung-Striebel smoothed means and stds of every node: ((times, states), (times, states))."""
    system = model.linear_system()
    # With nonlinear effects the gain uses the linear part's Φ: they are small corrections.
    Phi = discretize(system, sample_period(ts)).Phi

    def back(carry, inp):
        m_s_next, P_s_next = carry
        m_f, P_f, m_p_next, P_p_next = inp
        G = jnp.linalg.solve(P_p_next, Phi @ P_f).T  # P_f Φᵀ P_pred⁻¹ (P_pred symmetric)
        m_s = m_f + G @ (m_s_next - m_p_next)
        P_s = P_f + G @ (P_s_next - P_p_next) @ G.T
        P_s = 0.5 * (P_s + P_s.T)
        return (m_s, P_s), (m_s, P_s)

    last = (kf.m_filt[-1], kf.P_filt[-1])
    _, (m_s, P_s) = jax.lax.scan(back, last, (kf.m_filt[:-1], kf.P_filt[:-1], kf.m_pred[1:],
                                              kf.P_pred[1:]), reverse=True)
    m_s = jnp.concatenate([m_s, kf.m_filt[-1:]], axis=0)
    P_s = jnp.concatenate([P_s, kf.P_filt[-1:]], axis=0)
    return m_s, jnp.sqrt(jnp.clip(jnp.diagonal(P_s, axis1=1, axis2=2), 0.0))


def innovation_map(model: ThermalModel, ts, mask, P0, V):
    """The whitened innovations of one run that output-space perturbations `V` (times,
    outputs, m) cause: the Kalman filter's recursion with its own (data-independent)
    gains applied to `V`, `ε⁺ = F (ε + K e)`, `e = V − C ε`, whitened by the Cholesky
    factor of `S_k` (zero where unmeasured). Linear in `V`: the innovations of the data
    are the map of the free-run residuals (exactly, for a linear model), and the
    derivative of the innovations along an effect that enters as a free-run output
    direction `d` is minus the map of `d`. With nonlinear effects `F` is the linear
    part's `Φ`."""
    system = model.linear_system()
    dt = sample_period(ts)
    Phi = discretize(system, dt).Phi
    _, Qd = discretize_process_noise(system.A, jnp.diag(model.process_noise ** 2), dt)
    R = jnp.diag(model.noise ** 2)
    C = system.C

    def step(eps, g, v):
        e = (v - C @ eps) * g.mask[:, None]
        w = (g.W @ e) * g.mask[:, None]
        return Phi @ (eps + g.K @ e), w

    eps0 = jnp.zeros((Phi.shape[0], V.shape[-1]), V.dtype)
    return _settling_covariances(_riccati_step(C, R, Phi, Qd), step, eps0, P0, V, mask)


@stored_jit(once=True)
def dataset_innovation_map(model: ThermalModel, data: Dataset, V):
    """`innovation_map` of every run: `V` (runs, times, outputs, m) -> same shape."""
    P0 = jnp.diag(model.initial_std ** 2)
    return _each_run(lambda ts, mask, v: innovation_map(model, ts, mask, P0, v),
                     data.ts, data.mask, V)
