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
   compensated with the observer of its fitted model. The fit is a damped Gauss-Newton
   (Levenberg-Marquardt) with a fixed number of iterations from the nominal model,
   exact Jacobians by `jax.jacfwd` through the simulation; the population is its
   Gaussian prior on the log-deviations (mean, covariance), so directions the data do
   not determine stay at the prior. Traceable, so it vmaps: one compiled program
   fits every unit of a chunk;
5. **batch** (when the study has a batch model, `fit.batch_units > 0`): one parameter
   set for every unit, the same MAP fit pooled over the calibration runs of a sample of
   units (batch-level default matrices fitted to a sample), compensated like nominal.

Per unit and method: RMS and peak error of the estimated temperature of the bias
channel's node (K) and of the compensated bias (the channel's units). The report gives
their percentiles, the fraction of units within the bias specification, and a
sensitivity ranking (least-squares regression of the nominal method's peak bias error
on the standardized log-deviations of the varied parameters, with the correlations).

The fitted method's per-unit extras: `fitted_log_deviation` and `fitted_log_std`
(units, parameters: the MAP estimate and its posterior std from the last Gauss-Newton
Hessian), `fit_param_rms` (RMS of fitted minus true log-deviation, over the varied
parameters) and `fit_rms` (RMS of the calibration residuals in noise stds; about 1 when
the fit converged).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .._errors import InputError

T_REF = 25.0  # °C: centre of the bias polynomials (docs/formats.md §4)
METHODS = {"nominal": "nominal model (batch-level default observer)",
           "batch": "batch model fitted to a sample of units (batch-level calibration)",
           "fitted": "unit's own identified model (per-unit calibration)",
           "own": "unit's own true model (ideal per-unit calibration bound)"}
METRICS = ("temp_rms", "temp_peak", "bias_rms", "bias_peak")
POLISH_STEPS = 3  # undamped Gauss-Newton steps after the Levenberg-Marquardt iterations
_LEAVES = {"nodes": ("log_capacitance", "capacitance"), "links": ("log_conductance", "conductance"),
           "boundaries": ("log_boundary_conductance", "conductance"),
           "heat_inputs": ("log_heat_gain", "gain")}


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
    - `iterations`: Levenberg-Marquardt iterations of each fit.
    - `fit_bias`: fit the measured bias column too (known coefficients).
    """

    def __init__(self, spec, names, profile: dict, bias: str | None = None,
                 sensor_noise: bool = True, file: str | None = None, prior=None,
                 calibration: dict | None = None, iterations: int = 20,
                 fit_bias: bool = True):
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
            if group not in _LEAVES or what != _LEAVES[group][1] or key not in keys[group]:
                raise InputError(f"the study can vary capacitances, conductances and heat "
                                 f"gains only, not {name!r}.", file=file,
                                 field="population.spreads")
            self.slots.append((_LEAVES[group][0], keys[group].index(key)))
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
        # the fit: prior, iterations, which columns
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
        self._program = None

    @property
    def methods(self) -> dict[str, str]:
        """The methods this study computes (keys of `METHODS`, in its order)."""
        on = {"nominal": True, "own": True, "fitted": self.prior is not None,
              "batch": self.batch_logdev is not None}
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

    def _n_rows(self, y) -> int:
        """Rows of the fit's residual vector for readings `y` (pooled: one prior)."""
        bias_rows = int(np.prod(y.shape[:-1])) if self.fit_bias else 0
        return int(np.prod(y.shape)) + bias_rows + len(self.names)

    def fit(self, y, b):
        """MAP fit of one unit's log-deviations to its calibration run (see the module
        docstring): `y` (times, sensors) °C, `b` (times,) bias units; pooled over units
        when both have a leading units axis `(units, times, ...)`.

        **Returns:** `(logdev, log_std, rms)`: the estimate (k,), its posterior std (k,)
        from the Gauss-Newton Hessian at the estimate, and the RMS of the data residuals
        (noise stds).
        """
        import jax
        import jax.numpy as jnp

        if self.prior is None:
            raise ValueError("`Study.fit` needs a study with a prior (`Study(prior=...)`).")
        mean = jnp.asarray(self.prior[0])
        pooled = y.ndim == 3

        def residuals(d):
            if pooled:
                r_data, r_prior = jax.vmap(lambda yy, bb: self._residuals(d, yy, bb))(y, b)
                r = jnp.concatenate([r_data.ravel(), r_prior[0]])
            else:
                r_data, r_prior = self._residuals(d, y, b)
                r = jnp.concatenate([r_data, r_prior])
            return r, r

        def cost(d):
            r = residuals(d)[0]
            return r @ r

        k = mean.shape[0]

        n_lm = self.iterations

        def body(i, carry):
            # Levenberg-Marquardt with Nielsen's damping update (gain ratio rho) for the
            # first `iterations` steps. Then POLISH_STEPS undamped Gauss-Newton steps:
            # the accept test compares costs, so it stops within about sqrt(eps)·std of
            # the minimum along flat directions; Gauss-Newton steps solve the normal
            # equations there (linear convergence, a factor of about 0.05 per step at
            # noise-level residuals), locating it to roundoff. Each is taken when it is
            # small against the posterior std (the quadratic region), as it is on
            # convergence. One Jacobian site for both (compile time).
            d, lam, nu, c, _, _ = carry
            J, r = jax.jacfwd(residuals, has_aux=True)(d)
            H = J.T @ J
            g = J.T @ r
            lm = i < n_lm
            step = -jnp.linalg.solve(H + jnp.where(lm, lam, 0.0) * jnp.diag(jnp.diag(H)), g)
            c_new = cost(d + step)
            predicted = -(2.0 * g @ step + step @ H @ step)
            rho = (c - c_new) / jnp.where(predicted > 0, predicted, 1.0)
            std = jnp.sqrt(jnp.diag(jnp.linalg.inv(H)))
            ok = jnp.where(lm, c_new < c, jnp.max(jnp.abs(step) / std) < 0.5)
            shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
            return (jnp.where(ok, d + step, d), jnp.where(ok, lam * shrink, lam * nu),
                    jnp.where(ok, 2.0, 2.0 * nu), jnp.where(ok, c_new, c), std, r)

        d0 = mean
        carry = (d0, jnp.asarray(1e-3, d0.dtype), jnp.asarray(2.0, d0.dtype), cost(d0),
                 jnp.zeros(k, d0.dtype), jnp.zeros(self._n_rows(y), d0.dtype))
        # std and r: at the last point where the Jacobian was taken (one polish step
        # before the estimate, to roundoff the same point)
        d, _, _, _, std, r = jax.lax.fori_loop(0, n_lm + POLISH_STEPS, body, carry)
        n_data = r.shape[0] - k
        rms = jnp.sqrt(jnp.sum(r[:n_data] ** 2) / n_data)
        return d, std, rms

    def unit_metrics(self, logdev, unit, seed, nominal, batch=None):
        """Per-unit metrics (a dict of scalars) for one unit: `nominal` (and `batch`) are
        `(system, disc, gain)` of the nominal (and batch) model."""
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
        models = [("nominal", nominal), ("own", (system, disc, gain))]
        out = {}
        if batch is not None:
            models.append(("batch", batch))
        if self.prior is not None:
            y_cal, b_cal = self.calibration_data(logdev, unit, seed)
            d_fit, d_std, rms = self.fit(y_cal, b_cal)
            models.append(("fitted", self.observer_of(self.unit_network(d_fit))))
            out["fitted_log_deviation"] = d_fit
            out["fitted_log_std"] = d_std
            out["fit_param_rms"] = jnp.sqrt(jnp.mean((d_fit - logdev) ** 2))
            out["fit_rms"] = rms
        for label, (sys_o, disc_o, gain_o) in models:
            est = run_observer(Observer(disc_o, gain_o), u, y, sys_o.steady_state(u[0])).states
            dT = est[:, self.bias.temperature] - x[:, self.bias.temperature]
            db = self._bias(sys_o, est, u) - true_bias
            out[f"{label}_temp_rms"] = jnp.sqrt(jnp.mean(dT ** 2))
            out[f"{label}_temp_peak"] = jnp.max(jnp.abs(dT))
            out[f"{label}_bias_rms"] = jnp.sqrt(jnp.mean(db ** 2))
            out[f"{label}_bias_peak"] = jnp.max(jnp.abs(db))
        out["true_bias_span"] = jnp.max(true_bias) - jnp.min(true_bias)
        return out

    def set_batch_model(self, logdev: np.ndarray, units: np.ndarray, seed: int):
        """Fit the batch model: one parameter set, the MAP fit pooled over the calibration
        runs of the sample `units` (log-deviations `logdev`, (M, k)); the `batch` method
        then uses it. Runs unsharded on the default device (the same on every process).

        **Returns:** the batch model's log-deviations (k,)."""
        import jax
        import jax.numpy as jnp

        def program(logdev, units, seed):
            y, b = jax.vmap(lambda d, u: self.calibration_data(d, u, seed))(logdev, units)
            return self.fit(y, b)[0]

        d = jax.jit(program)(jnp.asarray(logdev), jnp.asarray(units, dtype=jnp.uint32),
                             jnp.asarray(seed, dtype=jnp.uint32))
        self.batch_logdev = np.asarray(d)
        self._program = None
        return self.batch_logdev

    def compute_chunk(self, logdev: np.ndarray, units: np.ndarray, seed: int, mesh=None
                      ) -> dict[str, np.ndarray]:
        """Metrics of a chunk of units, (units, k) log-deviations and their indices, the
        units axis sharded over `mesh`'s devices."""
        import jax
        import jax.numpy as jnp

        from ._sharding import padded_size, replicate, shard_units, units_mesh

        mesh = units_mesh() if mesh is None else mesh
        if self._program is None:
            nominal_net = self.network
            batch_d = self.batch_logdev

            def program(logdev, units, seed):
                nominal = self.observer_of(nominal_net)
                batch = (None if batch_d is None else
                         self.observer_of(self.unit_network(jnp.asarray(batch_d))))
                return jax.vmap(lambda d, u: self.unit_metrics(d, u, seed, nominal, batch))(
                    logdev, units)

            self._program = jax.jit(program)
        n = len(units)
        size = padded_size(n, mesh)
        logdev_p, units_p = logdev, units
        if size > n:  # pad with copies of the last unit; their results are dropped
            logdev_p = np.concatenate([logdev, np.repeat(logdev[-1:], size - n, axis=0)])
            units_p = np.concatenate([units, np.repeat(units[-1:], size - n)])
        args = shard_units((jnp.asarray(logdev_p), jnp.asarray(units_p, dtype=jnp.uint32)),
                           mesh)
        seed_arr = replicate(jnp.asarray(seed, dtype=jnp.uint32), mesh)
        out = self._program(*args, seed_arr)
        return {k: np.asarray(v)[:n] for k, v in out.items()}


def kalman_gain_doubling(Phi, C, Qd, R, iterations: int = 48):
    """Filter-form steady-state Kalman gain `L = P Cᵀ (C P Cᵀ + R)⁻¹`, with `P` the
    predicted covariance of the DARE `P = Φ P Φᵀ − Φ P Cᵀ (C P Cᵀ + R)⁻¹ C P Φᵀ + Qd`,
    by the structured doubling algorithm (fixed iteration count: traceable, vmaps;
    convergence is quadratic, 48 doublings cover 2^48 steps of the recursion). Agrees
    with `steady_state_kalman` (SciPy's `solve_discrete_are`) to roundoff."""
    import jax
    import jax.numpy as jnp

    n = Phi.shape[0]
    I = jnp.eye(n, dtype=Phi.dtype)
    A0 = Phi.T
    G0 = C.T @ jnp.linalg.solve(R, C)
    H0 = 0.5 * (Qd + Qd.T)

    def body(_, carry):
        A, G, H = carry
        W = I + G @ H
        WA = jnp.linalg.solve(W, A)
        WG = jnp.linalg.solve(W, G)
        A_new = A @ WA
        G_new = G + A @ WG @ A.T
        H_new = H + A.T @ H @ WA
        return A_new, 0.5 * (G_new + G_new.T), 0.5 * (H_new + H_new.T)

    _, _, P = jax.lax.fori_loop(0, iterations, body, (A0, G0, H0))
    S = C @ P @ C.T + R
    return jnp.linalg.solve(S, C @ P).T


# -- the report -------------------------------------------------------------------------

PERCENTILES = (50, 90, 95, 99)


def summarize(results: dict[str, np.ndarray], names, logdev: np.ndarray, spec_limit: float,
              bias_units: str) -> dict:
    """Percentiles, fraction within the bias specification, sensitivity ranking, and the
    per-unit fit's parameter errors (for the methods present in `results`)."""
    methods = {m: label for m, label in METHODS.items() if f"{m}_bias_peak" in results}
    out = {"n_units": int(len(results["unit"])), "bias_limit": spec_limit,
           "bias_units": bias_units, "methods": methods, "percentiles": {},
           "fraction_within_bias_spec": {}}
    for m in methods:
        out["percentiles"][m] = {
            k: {**{f"p{p}": float(np.percentile(results[f"{m}_{k}"], p)) for p in PERCENTILES},
                "max": float(np.max(results[f"{m}_{k}"])),
                "mean": float(np.mean(results[f"{m}_{k}"]))} for k in METRICS}
        out["fraction_within_bias_spec"][m] = float(np.mean(results[f"{m}_bias_peak"]
                                                            <= spec_limit))
    out["sensitivity"] = sensitivity(results["nominal_bias_peak"], names, logdev)
    if "fitted_log_deviation" in results:
        err = results["fitted_log_deviation"] - logdev
        z = err / results["fitted_log_std"]
        out["fit"] = {
            "fit_rms_median": float(np.median(results["fit_rms"])),
            "parameters": [{"parameter": n, "prior_std": float(np.std(logdev[:, j])),
                            "error_rms": float(np.sqrt(np.mean(err[:, j] ** 2))),
                            "posterior_std_median": float(np.median(
                                results["fitted_log_std"][:, j])),
                            "z_rms": float(np.sqrt(np.mean(z[:, j] ** 2)))}
                           for j, n in enumerate(names)]}
    return out


def sensitivity(error: np.ndarray, names, logdev: np.ndarray) -> list[dict]:
    """Rank the varied parameters by how much of the error's spread each explains:
    standardized least-squares coefficients of `error` on the log-deviations (per
    standard deviation of the parameter, in the error's units), with each one's
    correlation; ranked by |coefficient|."""
    if logdev.shape[1] == 0 or len(error) < 3:
        return []
    X = logdev - logdev.mean(axis=0)
    sd = X.std(axis=0)
    keep = sd > 0
    Z = X[:, keep] / sd[keep]
    e = error - error.mean()
    coef, *_ = np.linalg.lstsq(Z, e, rcond=None)
    rows = []
    kept = [n for n, k in zip(names, keep) if k]
    for j, name in enumerate(kept):
        denom = np.std(Z[:, j]) * np.std(e)
        r = float(np.mean(Z[:, j] * e) / denom) if denom > 0 else 0.0
        rows.append({"parameter": name, "coefficient_per_sd": float(coef[j]),
                     "correlation": r})
    rows.sort(key=lambda r: -abs(r["coefficient_per_sd"]))
    return rows
