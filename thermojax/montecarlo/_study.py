"""The first unit-variance study: each unit through a chamber profile, compensated
(a) with the nominal model and (b) with its own model.

For every unit (parameters from `sample_units`), in one compiled program vmapped over
the units of a chunk:

1. the unit's network is sampled exactly at the profile's period (`discretize`) and
   simulated from the steady state of the first input sample: its true node
   temperatures, its sensors' readings (plus white noise of each sensor's `noise` std,
   keyed by `(seed, unit)`), and its true inertial bias (the model file's first bias
   channel, or `spec.bias`, with the file's coefficients, the same for every unit:
   this study is about the thermal model);
2. **nominal**: the steady-state Kalman observer of the *nominal* model (batch-level
   default matrices) runs on the unit's readings; the bias model is evaluated on its
   estimates;
3. **own model**: the same, with the observer of the unit's *true* parameters (its gain
   from the same Riccati solution, computed in JAX by structured doubling so that it
   vmaps): the bound that a perfect per-unit identification would reach;
4. **fitted** (when the study has a prior, `run_montecarlo` always gives one): the unit
   is identified from its own *calibration* run (the calibration profile, by default
   the test profile again, with its own noise: sensor readings and, unless switched
   off, the measured bias column with the channel's `noise` std and its known
   coefficients) by a MAP output-error fit of its varied log-parameters, then
   compensated with the observer of its fitted model. The fit is a trust-region
   Gauss-Newton from the nominal model, run per unit until it converges (`Study.fit`),
   with exact Jacobians by the fitting stage's forward sensitivities through the blocked
   simulation (`_sensitivity.run_tangents`; equal to `jax.jacfwd` to roundoff); the
   population is its Gaussian prior on the log-deviations (mean, covariance), so
   directions the data do not determine stay at the prior. Traceable: one compiled
   program fits every unit of a chunk, one after another on each device;
5. **batch** (when the study has a batch model, `fit.batch_units > 0`): one parameter
   set for every unit, the same MAP fit pooled over the calibration runs of a sample of
   units (batch-level default matrices fitted to a sample), compensated like nominal.

Per unit and method: RMS and peak error of the estimated temperature of the bias
channel's node (K) and of the compensated bias (the channel's units). The report gives
their percentiles, the fraction of units within the bias specification, and a
sensitivity ranking (least-squares regression of the nominal method's peak bias error
on the standardized log-deviations of the varied parameters, with the correlations).

The fitted method's per-unit extras: `fitted_log_deviation` and `fitted_log_std`
(units, parameters: the MAP estimate and its posterior std from the Gauss-Newton
Hessian there), `fit_param_rms` (RMS of fitted minus true log-deviation, over the varied
parameters), `fit_rms` (RMS of the calibration residuals in noise stds; about 1 when
the fit converged) and `fit_steps` (the Gauss-Newton steps it took; above
`iterations + POLISH_STEPS - 1` only when it stopped at that cap, not converged).

The steady-state gain by doubling (`_gain_doubling`) and the report's summary of the
results (`_summary`) have files of their own. The per-unit fit's methods (`fit`, `_fit_evaluate`, `fit_units`, ...) stay on `Study`: they
share its compiled programs, its prior and its profile arrays with the simulation.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import numpy as np

from ._gain_doubling import kalman_gain_doubling
from .._errors import InputError
from ..model._network import SCALABLE_LEAVES


T_REF = 25.0  # °C: centre of the bias polynomials (docs/formats.md §4)
METHODS = {"nominal": "nominal model (batch-level default observer)",
           "batch": "batch model fitted to a sample of units (batch-level calibration)",
           "trim_step": "end-of-line trim from a single-point power step (eol_step: one "
                        "capacitance and one conductance factor)",
           "trim_sweep": "end-of-line trim from a two-tone power sweep (eol_sweep: the same "
                         "two factors)",
           "fitted": "unit's own identified model (per-unit calibration)",
           "own": "unit's own true model (ideal per-unit calibration bound)"}
METRICS = ("temp_rms", "temp_peak", "bias_rms", "bias_peak", "temp_offset", "step_overshoot",
           "phase_loss")
PHASE_PERIOD_S = 300.0  # s: the chamber period of the `phase_loss` metric (imu6's housing τ)
TRIM_STEPS = 12  # Levenberg–Marquardt steps of a unit's end-of-line trim (two factors)
STEP_K = 20.0  # K: the chamber step of the `step_overshoot` metric
POLISH_STEPS = 3  # steps of a fit allowed beyond `iterations`
INITIAL_RADIUS = 0.2  # the fit's first trust region, in log-deviation (20 %)
RADIUS_GROWTH = 2.0  # the trust region's growth after a good step that reached it
STEP_TOLERANCE = 1e-4  # posterior stds: a fit stops where its next step is shorter
ROUNDOFF_STEP = 1e-3  # posterior stds: shorter steps are taken without a cost test
_PROGRAMS: dict = {}  # compiled programs, shared by the studies of one structure (`_shared`)
_MAX_PROGRAMS = 8


def ramp_profile(lo: float, hi: float, rate: float, dwell: float, dt: float,
                 start: float = T_REF):
    """`(ts, chamber)`, s and °C, shapes `(times,)`: soak at `start` for `dwell` s, `rate`
    °C/min down to `lo`, dwell, up to `hi`, dwell, back to `start`, dwell (the
    one-rate `calibration_schedule` of `thermojax.measurements`)."""
    from ..measurements._profiles import calibration_schedule

    p = calibration_schedule(dt, lo, hi, (rate,), dwell, start, soak_s=dwell, end_c=start)
    return np.array(p.ts), np.array(p.temperature)


@dataclass(frozen=True)
class BiasChannel:
    column: str
    temperature: int
    order: int
    gradients: tuple[tuple[int, int], ...]
    rates: tuple[int, ...]
    coefficients: tuple[float, ...]


def profile_inputs(topology, profile: dict):
    """`(ts, inputs, dt)` of a ramp profile (`ramp_profile` keys, plus `power` in W on
    every heat input): the chamber temperature into every boundary input."""
    ts, chamber = ramp_profile(profile["lo"], profile["hi"], profile["rate"],
                               profile["dwell"], profile["dt"], profile.get("start", T_REF))
    heat = {topology.input_names[i] for i in topology.heat_inputs}
    inputs = np.column_stack([np.full(ts.size, profile.get("power", 0.0)) if c in heat
                              else chamber for c in topology.input_names])
    return ts, inputs, float(profile["dt"])


class Study:
    """Everything a chunk needs that is the same for every unit (see the module
    docstring).

    **Arguments:**

    - `spec`: the model; `names`: the varied parameters (`varied_names`), `k` of them.
    - `profile`: the test profile (`ramp_profile` keys, `dt` in s, `power` in W).
    - `bias`: the bias channel's column (default: the model's first).
    - `sensor_noise`: add each sensor's white noise to the simulated readings.
    - `prior`: `(mean, covariance)` of the log-deviations, shapes (k,) and (k, k)
      (`log_prior`); enables the `fitted` method. None: nominal and own only.
    - `calibration`: the calibration profile (default: `profile`, new noise).
    - `iterations`: each fit takes at most `iterations + POLISH_STEPS` steps (it stops
      earlier on convergence, `fit`).
    - `fit_bias`: fit the measured bias column too (known coefficients).
    - `trim`: add the end-of-line trim methods (`trim_step`, `trim_sweep`; the model needs a
      heat input).
    """

    def __init__(self, spec, names, profile: dict, bias: str | None = None,
                 sensor_noise: bool = True, file: str | None = None, prior=None,
                 calibration: dict | None = None, iterations: int = 50,
                 fit_bias: bool = True, trim: bool = False):
        import jax.numpy as jnp

        from ..model import ThermalNetwork, spec_parameters

        self.spec = spec
        thermal = spec.replace(effects=(), biases=())
        self.network = ThermalNetwork.from_spec(thermal)
        topo = self.network.topology
        self.names = tuple(names)
        # where each varied parameter sits among the network's log leaves
        self.slots = []
        keys = {"nodes": [n.name for n in spec.nodes], "links": [k.key for k in spec.links],
                "boundaries": [b.key for b in spec.boundaries],
                "heat_inputs": [h.key for h in spec.heat_inputs]}
        for name in self.names:
            group, _, rest = name.partition(".")
            key, _, what = rest.rpartition(".")
            if group not in SCALABLE_LEAVES or what != SCALABLE_LEAVES[group][1] \
                    or key not in keys[group]:
                raise InputError(f"the study can vary capacitances, conductances and heat "
                                 f"gains only, not {name!r}.", file=file,
                                 field="population.spreads")
            self.slots.append((SCALABLE_LEAVES[group][0], keys[group].index(key)))
        self.nominal_values = np.array([spec_parameters(spec)[n].value for n in self.names])
        # the bias channel
        if not spec.biases:
            raise InputError("the model has no [[biases]] channel to evaluate.", file=file,
                             field="model")
        chosen = [b for b in spec.biases if bias is None or b.column == bias]
        if not chosen:
            raise InputError(f"the model has no bias channel {bias!r}; it has "
                             f"{', '.join(b.column for b in spec.biases)}.", file=file,
                             field="spec.bias")
        b = chosen[0]
        n_coef = b.order + 1 + len(b.gradients) + len(b.rates)
        if b.coefficients is None or len(b.coefficients) < n_coef:
            raise InputError(f"bias channel {b.column!r} needs {n_coef} coefficients in the "
                             "model file.", file=file, field="model")
        idx = topo.node_names.index
        self.bias = BiasChannel(b.column, idx(b.temperature), b.order,
                                tuple((idx(p), idx(q)) for p, q in b.gradients),
                                tuple(idx(r) for r in b.rates), tuple(b.coefficients[:n_coef]))
        self.bias_noise = float(b.noise.value) if b.noise is not None else 0.0
        # the profiles: chamber temperature into boundary inputs, constant power into heat ones
        self.profile = dict(profile)
        ts, inputs, dt = profile_inputs(topo, profile)
        self.ts, self.inputs, self.dt = ts, jnp.asarray(inputs), dt
        self.calibration = dict(calibration) if calibration is not None else dict(profile)
        ts_c, inputs_c, dt_c = profile_inputs(topo, self.calibration)
        self.ts_cal, self.inputs_cal, self.dt_cal = ts_c, jnp.asarray(inputs_c), dt_c
        sensor_std = np.array([s.noise.value if s.noise is not None else 0.01
                               for s in thermal.sensors])
        self.noise = sensor_std * (1.0 if sensor_noise else 0.0)
        self.sensor_std = sensor_std
        self.r = sensor_std ** 2
        from ..model._model import DEFAULT_PROCESS_NOISE

        self.q = np.array([n.process_noise.value if n.process_noise is not None
                           else DEFAULT_PROCESS_NOISE for n in thermal.nodes])
        # the fit: prior, step cap, which columns
        self.iterations = int(iterations)
        self.fit_bias = bool(fit_bias) and self.bias_noise > 0
        self.prior = None
        if prior is not None and len(self.names):
            mean, cov = (np.asarray(a, dtype=float) for a in prior)
            k = len(self.names)
            if mean.shape != (k,) or cov.shape != (k, k):
                raise InputError(f"the prior needs a mean of shape ({k},) and a covariance "
                                 f"of shape ({k}, {k}), got {mean.shape} and {cov.shape}.",
                                 file=file, field="population")
            # whitening: r_prior = W (d - mean), W = chol(cov)^-1
            self.prior = (mean, np.linalg.inv(np.linalg.cholesky(cov)))
        self.batch_logdev = None  # set by `set_batch_model`
        self.trim = None
        if trim:
            self.trim = self._trim_setup(topo, file)
        # the chamber step of `step_overshoot`: 25 -> 45 °C after 60 s, at the test period
        n_step = int(round(1800.0 / self.dt)) + 1
        t_step = np.arange(n_step) * self.dt
        heat = {topo.input_names[i] for i in topo.heat_inputs}
        chamber = np.where(t_step >= 60.0, T_REF + STEP_K, T_REF)
        self.inputs_step = jnp.asarray(np.column_stack(
            [np.full(n_step, profile.get("power", 0.0)) if c in heat else chamber
             for c in topo.input_names]))

    def _trim_setup(self, topo, file):
        """The end-of-line trim's inputs per method (`eol_step`, `eol_sweep` at 1 s, the
        chamber at 25 °C, the power into every heat input) and its factor map `(k, 2)`:
        every varied capacitance by the first factor, every varied conductance by the
        second (docs/observer.md §13)."""
        import jax.numpy as jnp

        from ..measurements._profiles import builtin_profile

        if not topo.heat_inputs:
            raise InputError("the end-of-line trim drives the unit's heater: the model has "
                             "no heat input.", file=file, field="fit.trim")
        heat = {topo.input_names[i] for i in topo.heat_inputs}
        inputs = {}
        for method, name in (("trim_step", "eol_step"), ("trim_sweep", "eol_sweep")):
            p = builtin_profile(name, dt=1.0)
            inputs[method] = jnp.asarray(np.column_stack(
                [p.power if c in heat else p.temperature for c in topo.input_names]))
        M = np.zeros((len(self.names), 2))
        for j, name in enumerate(self.names):
            if name.startswith("nodes."):
                M[j, 0] = 1.0
            elif name.startswith(("links.", "boundaries.")):
                M[j, 1] = 1.0
        M = M[:, M.any(axis=0)]
        return {"inputs": inputs, "map": jnp.asarray(M)}

    def trim_factors(self, logdev, unit, seed, method: str):
        """One unit's end-of-line trim (traceable): its test (`method`'s inputs, 1 s
        samples) simulated with sensor noise, and the log-factors `θ` (2,) fitted by
        `TRIM_STEPS` Levenberg–Marquardt steps from 0 (the rest nominal). The unit's
        trimmed log-deviations are `map @ θ`."""
        import jax
        import jax.numpy as jnp

        from ..dynamics._discretize import discretize

        u = self.trim["inputs"][method]
        M = self.trim["map"]
        key = jax.random.fold_in(self._keys(unit, seed)[0], 3 if method == "trim_step" else 4)

        def outputs(d):
            system = self.unit_network(d).linear_system()
            disc = discretize(system, 1.0)
            return self._simulate(system, disc, u) @ disc.C.T + u @ disc.D.T

        y = outputs(logdev)
        y = y + jax.random.normal(key, y.shape, y.dtype) * jnp.asarray(self.noise)[None, :]
        std = jnp.asarray(self.sensor_std)[None, :]

        def residuals(theta):
            return ((y - outputs(M @ theta)) / std).ravel()

        def step(_, theta):
            r = residuals(theta)
            J = jax.jacfwd(residuals)(theta)
            H = J.T @ J
            H = H + 1e-6 * jnp.diag(jnp.diag(H))
            delta = -jnp.linalg.solve(H, J.T @ r)
            return theta + jnp.clip(delta, -0.5, 0.5)

        return jax.lax.fori_loop(0, TRIM_STEPS, step, jnp.zeros(M.shape[1], M.dtype))

    @property
    def methods(self) -> dict[str, str]:
        """The methods this study computes (keys of `METHODS`, in its order)."""
        on = {"nominal": True, "own": True, "fitted": self.prior is not None,
              "batch": self.batch_logdev is not None, "trim_step": self.trim is not None,
              "trim_sweep": self.trim is not None}
        return {m: label for m, label in METHODS.items() if on[m]}

    # -- per unit ---------------------------------------------------------------------

    def unit_network(self, logdev):
        """The network of one unit from its log-deviations, shape (k,) (traceable)."""
        import equinox as eqx

        net = self.network
        for j, (leaf, i) in enumerate(self.slots):
            net = eqx.tree_at(lambda n, leaf=leaf: getattr(n, leaf), net,
                              getattr(net, leaf).at[i].add(logdev[j]))
        return net

    def observer_of(self, network):
        """`(system, discrete system, steady-state Kalman gain)` of a network at the test
        profile's period (traceable)."""
        import jax.numpy as jnp

        from ..dynamics._discretize import discretize, discretize_process_noise

        system = network.linear_system()
        disc = discretize(system, self.dt)
        _, Qd = discretize_process_noise(system.A, jnp.diag(jnp.asarray(self.q) ** 2), self.dt)
        gain = kalman_gain_doubling(disc.Phi, disc.C, Qd, jnp.diag(jnp.asarray(self.r)))
        return system, disc, gain

    def _bias(self, system, x, u):
        """The bias channel at states `x` (times, nodes) of a model `system`."""
        import jax.numpy as jnp

        b, c = self.bias, self.bias.coefficients
        d = x[:, b.temperature] - T_REF
        out = sum(c[p] * d ** p for p in range(b.order + 1))
        k = b.order + 1
        for (p, q) in b.gradients:
            out = out + c[k] * (x[:, p] - x[:, q])
            k += 1
        if b.rates:
            xdot = x @ system.A.T + u @ system.B.T
            for r in b.rates:
                out = out + c[k] * xdot[:, r]
                k += 1
        return jnp.asarray(out)

    @staticmethod
    def _simulate(system, disc, u):
        """Node temperatures (times, nodes) from the steady state at `u[0]`: the exact-hold
        recurrence, blocked (`ExactHold`'s; matrix products instead of a long chain of
        tiny steps, also for its `jax.jacfwd` tangents)."""
        from ..dynamics._simulate import _blocked_hold

        return _blocked_hold(disc, system.steady_state(u[0]), u)[0]

    def _keys(self, unit, seed):
        import jax

        key = jax.random.fold_in(jax.random.PRNGKey(seed), unit)
        return key, jax.random.fold_in(key, 1), jax.random.fold_in(key, 2)

    def calibration_data(self, logdev, unit, seed):
        """One unit's calibration run: its readings (times, sensors) in °C and its measured
        bias column (times,) in the channel's units, both with noise (traceable)."""
        import jax
        import jax.numpy as jnp

        from ..dynamics._discretize import discretize

        _, k_y, k_b = self._keys(unit, seed)
        u = self.inputs_cal
        system = self.unit_network(logdev).linear_system()
        disc = discretize(system, self.dt_cal)
        x = self._simulate(system, disc, u)
        noise = jax.random.normal(k_y, (x.shape[0], disc.C.shape[0]), x.dtype)
        y = x @ disc.C.T + u @ disc.D.T + noise * jnp.asarray(self.noise)[None, :]
        b = self._bias(system, x, u) + jax.random.normal(k_b, (x.shape[0],), x.dtype) * (
            self.bias_noise if self.noise.any() else 0.0)
        return y, b

    def _residuals(self, logdev, y, b):
        """Calibration residuals in noise stds: readings, bias column, prior rows."""
        import jax.numpy as jnp

        from ..dynamics._discretize import discretize

        u = self.inputs_cal
        system = self.unit_network(logdev).linear_system()
        disc = discretize(system, self.dt_cal)
        x = self._simulate(system, disc, u)
        std = jnp.asarray(self.sensor_std)[None, :]
        parts = [((y - x @ disc.C.T - u @ disc.D.T) / std).ravel()]
        if self.fit_bias:
            parts.append((b - self._bias(system, x, u)) / self.bias_noise)
        mean, W = self.prior
        return jnp.concatenate(parts), jnp.asarray(W) @ (logdev - jnp.asarray(mean))

    def _fit_maps(self, d):
        """The small part of the fit's simulation at log-deviations `d` (k,): the blocked
        maps `(DL, N, O)` of the calibration run (`_blocked.block_maps`) and the initial
        `z0 = x0 - B1 u[0]` from the steady state at the first input sample. `O` reads the
        sensors, then, when the bias column is fitted, the two readouts the bias needs:
        the temperature node, and the sum of the channel's linear terms (its gradients
        and rates, `xdot = A x + B u`), so that the bias is a polynomial in the first plus
        the second (`_fit_bias`)."""
        import jax.numpy as jnp

        from ..dynamics._blocked import block_maps
        from ..dynamics._discretize import discretize
        from ..dynamics._sensitivity import _steady_state_small

        u0 = self.inputs_cal[0]
        system = self.unit_network(d).linear_system()
        disc = discretize(system, self.dt_cal)
        C, D = disc.C, disc.D
        if self.fit_bias:
            bc = self.bias
            n, m = disc.B0.shape
            eye = jnp.eye(n, dtype=C.dtype)
            c = bc.coefficients[bc.order + 1:]
            lin_c = jnp.zeros(n, C.dtype)
            lin_d = jnp.zeros(m, D.dtype)
            for j, (p, q) in enumerate(bc.gradients):
                lin_c = lin_c + c[j] * (eye[p] - eye[q])
            for j, r in enumerate(bc.rates):
                lin_c = lin_c + c[len(bc.gradients) + j] * system.A[r]
                lin_d = lin_d + c[len(bc.gradients) + j] * system.B[r]
            C = jnp.concatenate([C, eye[bc.temperature][None], lin_c[None]])
            D = jnp.concatenate([D, jnp.zeros((1, m), D.dtype), lin_d[None]])
        DL, N, (O,) = block_maps(disc.Phi, disc.B0, disc.B1, ((C, D),))
        x0 = _steady_state_small(system, u0)
        return (DL, N, O), x0 - disc.B1 @ u0

    def _fit_bias(self, t, lin):
        """The bias channel from `_fit_maps`' two bias readouts, and its derivative in the
        first: `(bias, d bias / d t)`."""
        c = self.bias.coefficients
        dt = t - T_REF
        value = sum(c[p] * dt ** p for p in range(self.bias.order + 1)) + lin
        slope = sum(p * c[p] * dt ** (p - 1) for p in range(1, self.bias.order + 1))
        return value, slope

    def _fit_evaluate(self, d, y, b, jacobian: bool = True):
        """The fit's residuals at `d` by the blocked simulation (`_sensitivity.run_primal`):
        `(r_y (units, times, sensors), r_b (units, times) or None, r_prior (k,))` in noise
        stds, `y` and `b` with a leading units axis (the units share `d`, so one
        simulation). With `jacobian`, also their Jacobians in `d`, `(J_y (times, sensors,
        k), J_b (times, k) or None)` (the same for every unit), by forward sensitivities
        (`_sensitivity.run_tangents`; `jax.jvp` only on the small maps): equal to
        `jax.jacfwd` of `_residuals` to float64 roundoff."""
        import jax
        import jax.numpy as jnp

        from ..dynamics._sensitivity import run_primal, run_tangents

        u = self.inputs_cal
        T, p = y.shape[1:]
        k = d.shape[0]
        std = jnp.asarray(self.sensor_std)
        if jacobian:
            small = jax.vmap(lambda v: jax.jvp(self._fit_maps, (d,), (v,)),
                             out_axes=(None, 0))(jnp.eye(k, dtype=d.dtype))
            # materialized before use: not fused into (and recomputed by) the large passes
            (maps, z0), (dmaps, dz0) = jax.lax.optimization_barrier(small)
        else:
            maps, z0 = self._fit_maps(d)
        out, w = run_primal(maps, z0, u)
        out = out[:T]
        mean, W = self.prior
        r_prior = jnp.asarray(W) @ (d - jnp.asarray(mean))
        r_y = (y - out[None, :, :p]) / std[None, None, :]
        if jacobian:
            dout = run_tangents(maps, dmaps, dz0, w)[:T]  # (times, outputs, k)
            J_y = dout[:, :p] / -std[None, :, None]
        if not self.fit_bias:
            return (r_y, None, r_prior) + (((J_y, None),) if jacobian else ())
        bias, slope = self._fit_bias(out[:, p], out[:, p + 1])
        r_b = (b - bias[None]) / self.bias_noise
        if not jacobian:
            return r_y, r_b, r_prior
        J_b = (slope[:, None] * dout[:, p] + dout[:, p + 1]) / -self.bias_noise
        return r_y, r_b, r_prior, (J_y, J_b)

    def fit(self, y, b, steps: bool = False, start=None):
        """MAP fit of one unit's log-deviations to its calibration run (see the module
        docstring): `y` (times, sensors) °C, `b` (times,) bias units; pooled over units
        when both have a leading units axis `(units, times, ...)`.

        A trust-region Gauss-Newton from the prior mean (or `start`, (k,)): the exact
        step within a sphere of radius `Δ` in the log-deviations (`_trust_region_step`;
        `Δ` starts at `INITIAL_RADIUS`, halves towards a step whose gain ratio is below
        1/4 and doubles after one above 3/4 that reached it), each trial point by the
        simulation alone, the Jacobian (forward sensitivities, `_fit_evaluate`) only at
        accepted points. It stops, per unit, where the Gauss-Newton step is shorter than
        `STEP_TOLERANCE` posterior stds (`sqrt(sᵀ H s)`, `H = JᵀJ`; it converges
        linearly there, by a factor of 0.01 to 0.1 per step, so the estimate is then
        about that close to the minimum), or after `iterations + POLISH_STEPS` steps
        taken (or three times as many trials). Steps under `ROUNDOFF_STEP` posterior
        stds are taken without a cost test (the cost comparison is at roundoff there).
        A `lax.while_loop` with a `lax.cond`: unbatched (`lax.map`, as `compute_chunk`
        runs it) each unit does its own work; under `jax.vmap` the loop runs until the
        batch's last unit is done and both branches of the cond are evaluated.

        **Returns:** `(logdev, log_std, rms)`: the estimate (k,), its posterior std (k,)
        from the Gauss-Newton Hessian at the estimate, and the RMS of the data residuals
        (noise stds) there; with `steps`, also the number of trials and of Jacobians
        (the steps taken, plus the first).
        """
        import jax
        import jax.numpy as jnp

        if self.prior is None:
            raise ValueError("`Study.fit` needs a study with a prior (`Study(prior=...)`).")
        mean = jnp.asarray(self.prior[0])
        W = jnp.asarray(self.prior[1])
        ys, bs = (y, b) if y.ndim == 3 else (y[None], b[None])
        M = ys.shape[0]
        k = mean.shape[0]

        def costs(r_y, r_b, r_p):
            c_data = jnp.sum(r_y ** 2) + (0.0 if r_b is None else jnp.sum(r_b ** 2))
            return c_data + r_p @ r_p, c_data

        def evaluate(d):
            """`(cost, Jᵀr, JᵀJ, data cost)` at `d` (cost: the sum of squared residuals)."""
            r_y, r_b, r_p, (J_y, J_b) = self._fit_evaluate(d, ys, bs)
            # one (rows, k) matrix: a single Gram product (twice as fast as one per part)
            Z, R = J_y, jnp.sum(r_y, axis=0)
            if r_b is not None:
                Z = jnp.concatenate([Z, J_b[:, None]], axis=1)
                R = jnp.concatenate([R, jnp.sum(r_b, axis=0)[:, None]], axis=1)
            Z = Z.reshape(-1, k)
            H = M * (Z.T @ Z) + W.T @ W
            g = Z.T @ R.reshape(-1) + W.T @ r_p
            c, c_data = costs(r_y, r_b, r_p)
            return c, g, H, c_data

        max_steps = self.iterations + POLISH_STEPS

        def converged(current):
            """The Gauss-Newton step from here is under `STEP_TOLERANCE` posterior stds."""
            _, g, H, _ = current
            return g @ jnp.linalg.solve(H, g) < STEP_TOLERANCE ** 2

        def cond(carry):
            return ~carry[2]

        def body(carry):
            i, n_jac, _, d, radius, current = carry
            c, g, H, _ = current
            step, lam = _trust_region_step(H, g, radius)
            c_new = costs(*self._fit_evaluate(d + step, ys, bs, jacobian=False))[0]
            sHs = step @ H @ step
            length = jnp.sqrt(step @ step)
            predicted = -(2.0 * g @ step + sHs)
            rho = (c - c_new) / jnp.where(predicted > 0, predicted, 1.0)
            tiny = jnp.sqrt(sHs) < ROUNDOFF_STEP
            ok = jnp.isfinite(c_new) & ((c_new < c) | tiny)
            grow = jnp.where((lam > 0) & (tiny | (rho > 0.75)), RADIUS_GROWTH * radius, radius)
            radius = jnp.where(~tiny & ~(rho >= 0.25), 0.5 * length, grow)  # ~: NaN too
            d_new = jnp.where(ok, d + step, d)
            current = jax.lax.cond(ok, evaluate, lambda _: current, d_new)
            n_jac = n_jac + ok.astype(n_jac.dtype)
            done = converged(current) | (n_jac > max_steps) | (i + 1 >= 3 * max_steps)
            return i + 1, n_jac, done, d_new, radius, current

        d0 = mean if start is None else jnp.asarray(start, mean.dtype)
        first = evaluate(d0)
        carry = (jnp.asarray(0), jnp.asarray(1), converged(first), d0,
                 jnp.asarray(INITIAL_RADIUS, d0.dtype), first)
        n, n_jac, _, d, _, (_, _, H, c_data) = jax.lax.while_loop(cond, body, carry)
        std = jnp.sqrt(jnp.diag(jnp.linalg.inv(H)))
        n_data = M * ys.shape[1] * (ys.shape[2] + (1 if self.fit_bias else 0))
        rms = jnp.sqrt(c_data / n_data)
        return (d, std, rms, n, n_jac) if steps else (d, std, rms)

    def fit_units(self, logdev, units, seed, steps: bool = False):
        """Each unit's calibration run (`calibration_data`) and fit (`fit`), for
        log-deviations (units, k) and unit indices (units,): one unit after another
        (`lax.map`), so that each fit stops at its own convergence and does the work of
        its own trials (under `jax.vmap` the batch would iterate until its slowest unit
        is done, evaluating every Jacobian branch)."""
        import jax

        def one(args):
            d, u = args
            return self.fit(*self.calibration_data(d, u, seed), steps=steps)

        return jax.lax.map(one, (logdev, units))

    def unit_metrics(self, logdev, unit, seed, nominal, batch=None, fitted=None):
        """Per-unit metrics (a dict of scalars) for one unit: `nominal` (and `batch`) are
        `(system, disc, gain)` of the nominal (and batch) model; `fitted`, the unit's
        `fit_units` result `(logdev, log_std, rms, trials, jacobians)` (default: fitted
        here)."""
        import jax
        import jax.numpy as jnp

        from ..observer._observer import Observer, run_observer

        u = self.inputs
        system, disc, gain = self.observer_of(self.unit_network(logdev))
        x = self._simulate(system, disc, u)
        key = self._keys(unit, seed)[0]
        noise = jax.random.normal(key, (x.shape[0], disc.C.shape[0]), x.dtype)
        y = x @ disc.C.T + u @ disc.D.T + noise * jnp.asarray(self.noise)[None, :]
        true_bias = self._bias(system, x, u)
        x_step = self._simulate(system, disc, self.inputs_step)
        models = [("nominal", nominal), ("own", (system, disc, gain))]
        out = {}
        if batch is not None:
            models.append(("batch", batch))
        if self.trim is not None:
            for method in ("trim_step", "trim_sweep"):
                theta = self.trim_factors(logdev, unit, seed, method)
                models.append((method, self.observer_of(self.unit_network(
                    self.trim["map"] @ theta))))
                out[f"{method}_log_factors"] = theta
        if self.prior is not None:
            if fitted is None:
                fitted = self.fit(*self.calibration_data(logdev, unit, seed), steps=True)
            d_fit, d_std, rms, _, jacobians = fitted
            models.append(("fitted", self.observer_of(self.unit_network(d_fit))))
            out["fitted_log_deviation"] = d_fit
            out["fitted_log_std"] = d_std
            out["fit_param_rms"] = jnp.sqrt(jnp.mean((d_fit - logdev) ** 2))
            out["fit_rms"] = rms
            out["fit_steps"] = jacobians - 1
        for label, (sys_o, disc_o, gain_o) in models:
            est = run_observer(Observer(disc_o, gain_o), u, y, sys_o.steady_state(u[0])).states
            dT = est[:, self.bias.temperature] - x[:, self.bias.temperature]
            db = self._bias(sys_o, est, u) - true_bias
            out[f"{label}_temp_rms"] = jnp.sqrt(jnp.mean(dT ** 2))
            out[f"{label}_temp_peak"] = jnp.max(jnp.abs(dT))
            out[f"{label}_bias_rms"] = jnp.sqrt(jnp.mean(db ** 2))
            out[f"{label}_bias_peak"] = jnp.max(jnp.abs(db))
            # the secondary state's offset: its mean error over the last tenth (a dwell)
            out[f"{label}_temp_offset"] = jnp.abs(jnp.mean(dT[-max(1, dT.shape[0] // 10):]))
            # its overshoot over the true trajectory after a STEP_K chamber step (noise
            # free), % of the step
            est_s = run_observer(Observer(disc_o, gain_o), self.inputs_step,
                                 x_step @ disc.C.T + self.inputs_step @ disc.D.T,
                                 sys_o.steady_state(self.inputs_step[0])).states
            over = est_s[:, self.bias.temperature] - x_step[:, self.bias.temperature]
            out[f"{label}_step_overshoot"] = 100.0 * jnp.maximum(jnp.max(over), 0.0) / STEP_K
            out[f"{label}_phase_loss"] = self._phase_loss(disc, disc_o, gain_o)
        out["true_bias_span"] = jnp.max(true_bias) - jnp.min(true_bias)
        return out

    def _phase_loss(self, disc, disc_o, gain_o):
        """|phase| (degrees) of the estimated bias-node temperature against the unit's true
        one, for a chamber sinusoid of period `PHASE_PERIOD_S` in steady state: the
        unit's response `X = (z I − Φ)⁻¹ (B0 + z B1) e`, the observer's `X̂` from
        `(I − K Φₘ/z) X̂ = K (B0ₘ/z + B1ₘ) e + L (C X + D e − Dₘ e)`, `K = I − L Cₘ`,
        `z = exp(iω dt)` (traceable). The phase margin a loop closed on the estimate loses
        at that frequency."""
        import jax.numpy as jnp

        topo = self.network.topology
        j = topo.boundary_inputs[0]
        m = disc.B0.shape[1]
        e = jnp.zeros(m).at[j].set(1.0).astype(jnp.complex128)
        z = jnp.exp(1j * 2.0 * jnp.pi * self.dt / PHASE_PERIOD_S)
        n = disc.Phi.shape[0]
        eye = jnp.eye(n, dtype=jnp.complex128)
        X = jnp.linalg.solve(z * eye - disc.Phi, (disc.B0 + z * disc.B1) @ e)
        Y = disc.C @ X + disc.D @ e
        K = eye - gain_o @ disc_o.C
        Xh = jnp.linalg.solve(eye - K @ disc_o.Phi / z,
                              K @ ((disc_o.B0 / z + disc_o.B1) @ e) + gain_o @ (Y - disc_o.D @ e))
        b = self.bias.temperature
        return jnp.abs(jnp.angle(Xh[b] / X[b])) * 180.0 / jnp.pi

    def set_batch_model(self, logdev: np.ndarray, units: np.ndarray, seed: int):
        """Fit the batch model: one parameter set, the MAP fit pooled over the calibration
        runs of the sample `units` (log-deviations `logdev`, (M, k)); the `batch` method
        then uses it. Runs unsharded on the default device (the same on every process).

        **Returns:** the batch model's log-deviations (k,)."""
        import jax
        import jax.numpy as jnp

        def program(prior, logdev, units, seed):
            study = self._with_arrays(prior, None)
            y, b = jax.vmap(lambda d, u: study.calibration_data(d, u, seed))(logdev, units)
            return study.fit(y, b)[0]

        d = self._shared("batch", program)(
            self._prior_arrays(), jnp.asarray(logdev), jnp.asarray(units, dtype=jnp.uint32),
            jnp.asarray(seed, dtype=jnp.uint32))
        self.batch_logdev = np.asarray(d)
        return self.batch_logdev

    # -- compiled programs shared between studies -----------------------------------

    def _structure(self) -> str:
        """Everything a study's programs depend on except the prior's and the batch
        model's values (passed as arguments): studies with equal structures (the presets
        of a procurement study, say) share one compiled program."""
        return repr((self.spec, self.names, sorted(self.profile.items()),
                     sorted(self.calibration.items()), self.bias, self.bias_noise,
                     self.noise.tolist(), self.iterations, self.fit_bias,
                     self.prior is None, self.batch_logdev is None))

    def _shared(self, kind: str, program, mesh=None):
        """`jax.jit(program)`, or the one compiled before for a study of this structure
        (`program` must take the prior's and the batch model's arrays as arguments, and
        use `self` only for its structure)."""
        import jax

        key = (kind, self._structure(), mesh)
        if key not in _PROGRAMS:
            if len(_PROGRAMS) >= _MAX_PROGRAMS:
                _PROGRAMS.pop(next(iter(_PROGRAMS)))
            _PROGRAMS[key] = jax.jit(program)
        return _PROGRAMS[key]

    def _prior_arrays(self):
        """The prior's `(mean, W)` as arrays, or None."""
        import jax.numpy as jnp

        return None if self.prior is None else tuple(jnp.asarray(a) for a in self.prior)

    def _with_arrays(self, prior, batch_logdev):
        """A copy of the study with the prior's `(mean, W)` and the batch model's
        log-deviations replaced (by tracers, inside a shared program)."""
        study = copy.copy(self)
        study.prior, study.batch_logdev = prior, batch_logdev
        return study

    def compute_chunk(self, logdev: np.ndarray, units: np.ndarray, seed: int, mesh=None
                      ) -> dict[str, np.ndarray]:
        """Metrics of a chunk of units, (units, k) log-deviations and their indices, the
        units axis sharded over `mesh`'s devices."""
        import jax
        import jax.numpy as jnp

        from jax.sharding import PartitionSpec as P

        from ._sharding import padded_size, replicate, shard_units, units_mesh

        mesh = units_mesh() if mesh is None else mesh

        def program(prior, batch_d, logdev, units, seed):
            study = self._with_arrays(prior, batch_d)
            # the fits one unit after another on each device's slice of the units
            fit_units = jax.shard_map(lambda d, u, s: study.fit_units(d, u, s, steps=True),
                                      mesh=mesh, in_specs=(P("units"), P("units"), P()),
                                      out_specs=P("units"), check_vma=False)
            nominal = study.observer_of(study.network)
            batch = None if batch_d is None else study.observer_of(study.unit_network(batch_d))
            fitted = None if prior is None else fit_units(logdev, units, seed)
            return jax.vmap(lambda d, u, f: study.unit_metrics(d, u, seed, nominal, batch,
                                                               f))(logdev, units, fitted)

        n = len(units)
        size = padded_size(n, mesh)
        logdev_p, units_p = logdev, units
        if size > n:  # pad with copies of the last unit; their results are dropped
            logdev_p = np.concatenate([logdev, np.repeat(logdev[-1:], size - n, axis=0)])
            units_p = np.concatenate([units, np.repeat(units[-1:], size - n)])
        args = shard_units((jnp.asarray(logdev_p), jnp.asarray(units_p, dtype=jnp.uint32)),
                           mesh)
        seed_arr = replicate(jnp.asarray(seed, dtype=jnp.uint32), mesh)
        batch_d = None if self.batch_logdev is None else jnp.asarray(self.batch_logdev)
        prior, batch_d = replicate((self._prior_arrays(), batch_d), mesh)
        out = self._shared("chunk", program, mesh)(prior, batch_d, *args, seed_arr)
        return {k: np.asarray(v)[:n] for k, v in out.items()}


def _trust_region_step(H, g, radius, newton_steps: int = 30):
    """The minimizer `s` of `2 gᵀs + sᵀ H s` over `|s| <= radius` (`H` positive
    definite), and its multiplier `λ >= 0` (`(H + λ I) s = -g`; 0 when the Gauss-Newton
    step lies inside): by the eigendecomposition of `H` and Newton's method on
    `1/|s(λ)| - 1/radius` from `λ = 0` (Moré and Sorensen; monotone from below, a fixed
    number of steps so that it vmaps)."""
    import jax
    import jax.numpy as jnp

    lam_h, V = jnp.linalg.eigh(H)
    a2 = (V.T @ g) ** 2

    def newton(_, lam):
        norm2 = jnp.sum(a2 / (lam_h + lam) ** 2)
        norm = jnp.sqrt(norm2)
        return jnp.maximum(lam + (norm / radius - 1.0) * norm2 / jnp.sum(
            a2 / (lam_h + lam) ** 3), 0.0)

    inside = jnp.sum(a2 / lam_h ** 2) <= radius ** 2
    lam = jnp.where(inside, 0.0, jax.lax.fori_loop(0, newton_steps, newton,
                                                   jnp.zeros((), H.dtype)))
    return -V @ ((V.T @ g) / (lam_h + lam)), lam
