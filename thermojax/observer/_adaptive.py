"""An adaptive extended Kalman filter: node temperatures and slowly drifting conductances.

The answer to ageing (die-attach voiding, thermal-interface pump-out): the logs of
the conductances that may drift are states beside the node temperatures, each a random
walk `d log g = σ_g dβ`, and an extended Kalman filter estimates both from the sensors.
The covariance is float64 throughout (double-precision covariance, as firmware keeps it).

Each step (sample period `dt`, inputs held as the model file says):

- predict `x⁻ = Φ(g) x + B0(g) u[k−1] + B1(g) u[k]` with the exact discretization at the
  current estimate `g`; `F = ∂(x⁻, log g)/∂(x, log g)` by forward-mode differentiation
  through the matrix exponential; `P⁻ = F P Fᵀ + diag(Q_x(g), σ_g² dt)`, `Q_x` Van Loan's
  integral of the nodes' process noise;
- correct with the sensors (Joseph form, valid for any gain), `y = T[sensors]`;
- **excitation gate**: a conductance is corrected only while heat measurably flows
  through it: the predicted difference across it (node − node, or node − boundary
  input) beyond `excitation` of its own std. Otherwise its gain row is zero. Without the
  gate, a conductance nothing informs wanders: the filter linearizes at estimated
  temperatures whose noise makes a sensitivity that is not there (a dwell's 10 h moved an
  untouched die attach by a factor 2.6);
- **covariance ceiling**: a log-conductance std above `ceiling` is scaled back to it (rows
  and columns of `P` scaled by `ceiling/std ≤ 1`, which keeps `P` positive semidefinite).
  Under weak excitation (a long dwell: no heat flows through the conductance) nothing
  informs `g` and a random walk's variance would grow without bound; the ceiling is the
  unit-to-unit prior the factory knows, so the filter never claims less than that;
- **step detection**: the normalized innovations `eᵀS⁻¹e` summed over the last `window`
  samples are χ² with `p·window` degrees of freedom while the model holds; above the
  `1 − alarm` quantile the step is flagged (a delaminating die attach changes `g` faster
  than its random walk allows), and with `reacquire` the conductances' covariance is
  reset to the ceiling so the filter re-learns them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ..dynamics._discretize import discretize, discretize_process_noise
from .._errors import InputError
from ..model._network import ThermalNetwork


@dataclasses.dataclass(frozen=True, eq=False)
class AdaptiveRun:
    """What `track_conductances` returns, per sample `k` (after its correction):

    - `states`, `state_std`: node temperatures and their std, (T, nodes) °C;
    - `conductances`: the tracked conductances `exp(log g)`, (T, tracked) W/K;
      `log_std`: the std of their logs, (T, tracked) (a 95 % band is
      `g · exp(±1.96 log_std)`);
    - `nis`: the normalized innovation squared `eᵀS⁻¹e`, (T,);
    - `flags`: step detections (T,) bool, `threshold` the windowed NIS they exceeded;
    - `names`: the tracked conductances' names (`links.a-b.conductance`, ...).
    """

    states: np.ndarray
    state_std: np.ndarray
    conductances: np.ndarray
    log_std: np.ndarray
    nis: np.ndarray
    flags: np.ndarray
    threshold: float
    names: tuple[str, ...]


def conductance_names(spec) -> list[str]:
    """Report names of every conductance of `spec`, links first then boundaries: the
    order of `concatenate([log_conductance, log_boundary_conductance])`."""
    from ..model._parameters_by_name import spec_parameters

    return [k for k in spec_parameters(spec) if k.startswith(("links.", "boundaries."))]


def _with_log_conductances(network, tracked, values):
    """`network` with the conductances at `tracked` (indices into links + boundaries)
    set to `exp(values)`."""
    n_links = network.log_conductance.shape[0]
    every = jnp.concatenate([network.log_conductance, network.log_boundary_conductance])
    every = every.at[jnp.asarray(tracked)].set(values)
    return eqx.tree_at(lambda n: (n.log_conductance, n.log_boundary_conductance), network,
                       (every[:n_links], every[n_links:]))


def _predict(network, tracked, dt, z, u_prev, u):
    n = network.topology.n_nodes
    d = discretize(_with_log_conductances(network, tracked, z[n:]).linear_system(), dt)
    return jnp.concatenate([d.Phi @ z[:n] + d.B0 @ u_prev + d.B1 @ u, z[n:]])


def _ends(network, tracked):
    """Per tracked conductance: its node `a`, the other node `b` (−1 for a boundary) and
    the boundary's input column `c` (−1 for a link)."""
    t = network.topology
    ends = [(i, j, -1) for i, j in t.links] + [(a, -1, c) for a, c in
                                              zip(t.boundary_nodes, t.boundary_inputs)]
    return np.array([ends[i] for i in tracked], int).T


@eqx.filter_jit
def _filter(network, tracked, dt, q, drift, R, ceiling, threshold, reacquire, excitation,
            z0, P0, u, y, window: int):
    n = network.topology.n_nodes
    k = len(tracked)
    H = jnp.concatenate([network.output_matrix(), jnp.zeros((R.shape[0], k))], axis=1)
    eye = jnp.eye(n + k)
    a, b, c = _ends(network, tracked)
    link = b >= 0

    def excited(z, P, uk):
        """Whether heat flows through each tracked conductance, beyond its noise."""
        other = jnp.where(link, z[jnp.maximum(b, 0)], uk[jnp.maximum(c, 0)])
        var = P[a, a] + jnp.where(link, P[jnp.maximum(b, 0), jnp.maximum(b, 0)]
                                  - 2 * P[a, jnp.maximum(b, 0)], 0.0)
        return jnp.abs(z[a] - other) > excitation * jnp.sqrt(jnp.maximum(var, 0.0))

    def correct(z, P, yk, gate):
        e = yk - H @ z
        S = H @ P @ H.T + R
        K = jnp.linalg.solve(S, H @ P).T
        K = K * jnp.concatenate([jnp.ones(n), gate.astype(K.dtype)])[:, None]
        IKH = eye - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        P = 0.5 * (P + P.T)
        s = jnp.sqrt(jnp.diagonal(P)[n:])
        scale = jnp.concatenate([jnp.ones(n), jnp.minimum(1.0, ceiling / s)])
        return z + K @ e, P * scale[:, None] * scale[None, :], e @ jnp.linalg.solve(S, e)

    def step(carry, inputs):
        z, P, buf, i = carry
        u_prev, uk, yk = inputs
        def predicted(z):  # the prediction and its Jacobian from one forward pass
            out = _predict(network, tracked, dt, z, u_prev, uk)
            return out, out

        F, z_pred = jax.jacfwd(predicted, has_aux=True)(z)
        A = _with_log_conductances(network, tracked, z[n:]).linear_system().A
        _, Qx = discretize_process_noise(A, jnp.diag(q ** 2), dt)
        Q = jax.scipy.linalg.block_diag(Qx, jnp.diag(drift ** 2 * dt))
        P_pred = F @ P @ F.T + Q
        z, P, nis = correct(z_pred, P_pred, yk, excited(z_pred, P_pred, uk))
        buf = buf.at[i % window].set(nis)
        flag = jnp.sum(buf) > threshold
        reset = flag & reacquire  # the conductances' covariance back to the ceiling
        P_re = P.at[n:, :].set(0.0).at[:, n:].set(0.0).at[n:, n:].set(jnp.diag(ceiling ** 2))
        P = jnp.where(reset, P_re, P)
        buf = jnp.where(reset, jnp.zeros_like(buf), buf)
        return (z, P, buf, i + 1), (z, jnp.diagonal(P), nis, flag)

    z, P, nis0 = correct(z0, P0, y[0], excited(z0, P0, u[0]))
    buf = jnp.zeros(window).at[0].set(nis0)
    _, (zs, vs, nis, flags) = jax.lax.scan(step, (z, P, buf, 1), (u[:-1], u[1:], y[1:]))
    zs = jnp.concatenate([z[None], zs])
    vs = jnp.concatenate([jnp.diagonal(P)[None], vs])
    return zs, vs, jnp.concatenate([nis0[None], nis]), jnp.concatenate([jnp.array([False]),
                                                                        flags])


def track_conductances(spec, tracked: Sequence[str], u, y, dt: float, drift, *,
                       ceiling=0.5, process_noise=None, sensor_noise=None, x0=None,
                       initial_std: float = 1.0, excitation: float = 3.0,
                       window_s: float = 300.0, alarm: float = 1e-6, reacquire: bool = True
                       ) -> AdaptiveRun:
    """Run the adaptive filter over one log.

    **Arguments:**

    - `spec`: the model (`ModelSpec`, e.g. `thermojax.io.load_model(path)`): nominal
      conductances are the starting estimates; a linear network (no effects).
    - `tracked`: names of the conductances to track (`links.die-pcb.conductance`,
      `boundaries.case-T_chamber.conductance`).
    - `u (T, m)`, `y (T, p)`: inputs and sensor readings in the model's column order, at
      period `dt` (s).
    - `drift`: random-walk intensity of each tracked log-conductance, per √s (scalar or
      (tracked,)): `drift · √t` is the expected relative change over `t` seconds.
    - `ceiling`: largest std of a log-conductance (the unit-to-unit spread; also the
      starting std).
    - `process_noise (nodes,)` °C/√s, `sensor_noise (p,)` °C: default the model file's
      (a node without a process noise gets the model's default, 1e-3; at least 1e-4).
    - `x0 (nodes,)`: starting temperatures, std `initial_std`; default the steady state of
      `u[0]`.
    - `excitation`: the gate, in stds of the temperature difference across a conductance
      (0: always corrected).
    - `window_s`, `alarm`: step detection over the last `window_s` seconds at a false-alarm
      probability `alarm` per window; `reacquire`: reset the conductances' covariance to
      the ceiling on a detection.
    """
    st = _settings(spec, tracked, dt, drift, ceiling, process_noise, sensor_noise,
                   window_s, alarm)
    network, index, n = st.network, st.index, st.network.topology.n_nodes
    u, y = _checked_log(network, u, y)
    if x0 is None:
        x0 = np.asarray(network.linear_system().steady_state(jnp.asarray(u[0])))
    every = np.concatenate([np.asarray(network.log_conductance),
                            np.asarray(network.log_boundary_conductance)])
    z0 = np.concatenate([np.asarray(x0, float), every[list(index)]])
    P0 = np.diag(np.concatenate([np.full(n, initial_std ** 2), st.ceiling ** 2]))
    zs, vs, nis, flags = _filter(network, index, jnp.asarray(dt), jnp.asarray(st.q),
                                 jnp.asarray(st.drift), jnp.diag(jnp.asarray(st.r) ** 2),
                                 jnp.asarray(st.ceiling), st.threshold,
                                 jnp.asarray(reacquire), jnp.asarray(float(excitation)),
                                 jnp.asarray(z0), jnp.asarray(P0), jnp.asarray(u),
                                 jnp.asarray(y), st.window)
    zs, sd = np.asarray(zs), np.sqrt(np.asarray(vs))
    return AdaptiveRun(zs[:, :n], sd[:, :n], np.exp(zs[:, n:]), sd[:, n:], np.asarray(nis),
                       np.asarray(flags), st.threshold, tuple(tracked))


def adaptive_design(spec, tracked: Sequence[str], dt: float, drift, *, ceiling=0.5,
                    process_noise=None, sensor_noise=None, initial_std: float = 1.0,
                    excitation: float = 3.0, window_s: float = 300.0, alarm: float = 1e-6,
                    reacquire: bool = True, substeps: int | None = None):
    """The firmware filter's `thermojax.reference.AdaptiveDesign` (NumPy reference and
    C): the same settings as `track_conductances` (`drift` and `ceiling` then relative,
    per √s and as a fraction of `g`: equal to the log ones to first order), integrated with
    `substeps` Tustin steps a sample (default: each at most half the network's fastest
    time constant)."""
    from ..reference._adaptive import AdaptiveDesign

    st = _settings(spec, tracked, dt, drift, ceiling, process_noise, sensor_noise,
                   window_s, alarm)
    net = st.network
    t = net.topology
    if substeps is None:
        tau = 1.0 / np.max(np.abs(np.linalg.eigvals(np.asarray(net.linear_system().A))))
        substeps = max(1, int(np.ceil(2.0 * dt / tau)))
    g, gb, gain = (np.asarray(a, float).tolist() for a in (net.conductance,
                                                           net.boundary_conductance,
                                                           net.heat_gain))
    return AdaptiveDesign(
        capacitance=tuple(np.asarray(net.capacitance, float).tolist()),
        links=tuple((a, b, v) for (a, b), v in zip(t.links, g)),
        boundaries=tuple((a, c, v) for a, c, v in zip(t.boundary_nodes, t.boundary_inputs,
                                                       gb)),
        heats=tuple((a, c, v) for a, c, v in zip(t.heat_nodes, t.heat_inputs, gain)),
        sensors=tuple(t.sensor_nodes), holds=tuple(t.input_holds), tracked=st.index,
        dt=float(dt), substeps=int(substeps), process_noise=tuple(st.q.tolist()),
        sensor_noise=tuple(st.r.tolist()), drift=tuple(st.drift.tolist()),
        ceiling=tuple(st.ceiling.tolist()), excitation=float(excitation), window=st.window,
        threshold=st.threshold, reacquire=bool(reacquire), initial_std=float(initial_std))


@dataclasses.dataclass(frozen=True)
class _Settings:
    network: ThermalNetwork
    index: tuple[int, ...]
    drift: np.ndarray
    ceiling: np.ndarray
    q: np.ndarray
    r: np.ndarray
    window: int
    threshold: float


def _settings(spec, tracked, dt, drift, ceiling, process_noise, sensor_noise, window_s,
              alarm) -> _Settings:
    """The filter's numbers from the model and the arguments, checked."""
    import scipy.stats

    from ..model._model import ThermalModel

    model = ThermalModel.from_spec(spec)
    if model.effect_terms:
        raise InputError("the adaptive filter takes a linear network: this model has "
                         "effects; track conductances of the network without them.")
    network = model.network
    names = conductance_names(spec)
    unknown = [t for t in tracked if t not in names]
    if unknown or not tracked:
        raise InputError(f"no conductance {unknown or '(none given)'} to track; the model's "
                         f"conductances are {names}.", field="tracked")
    if not (np.isfinite(dt) and dt > 0):
        raise InputError(f"the sample period must be positive, got {dt}.", field="dt")
    k, n = len(tracked), network.topology.n_nodes
    p = len(network.topology.sensor_nodes)
    q = (np.maximum(np.asarray(model.process_noise), 1e-4) if process_noise is None
         else np.broadcast_to(np.asarray(process_noise, float), (n,)).copy())
    r = (np.asarray(model.noise) if sensor_noise is None
         else np.broadcast_to(np.asarray(sensor_noise, float), (p,)).copy())
    window = max(1, int(round(window_s / dt)))
    return _Settings(network, tuple(names.index(t) for t in tracked),
                     np.broadcast_to(np.asarray(drift, float), (k,)).copy(),
                     np.broadcast_to(np.asarray(ceiling, float), (k,)).copy(), q, r, window,
                     float(scipy.stats.chi2.isf(alarm, p * window)))


def _checked_log(network, u, y):
    """`u`, `y` as float arrays of the model's shapes, every sample finite."""
    u, y = np.asarray(u, float), np.asarray(y, float)
    p, m = len(network.topology.sensor_nodes), len(network.topology.input_names)
    if u.ndim != 2 or y.ndim != 2 or u.shape[0] != y.shape[0] or y.shape[1] != p \
            or u.shape[1] != m:
        raise InputError(f"u and y must be (T, {m}) and (T, {p}) with the same T; got "
                         f"{u.shape} and {y.shape}.")
    bad = np.argwhere(~np.isfinite(u).all(1) | ~np.isfinite(y).all(1))
    if bad.size:
        raise InputError(f"sample {int(bad[0, 0])} is not finite: the adaptive filter needs "
                         "every input and reading (drop or fill the gap first).")
    return u, y
