"""The end-of-line trim of one unit: its scale factors (`thermojax.observer.TrimPlan`)
measured from a short test log by output-error least squares, with their uncertainty.

The rest of the model stays nominal: a factor multiplies every parameter of its group,
so the fit has as many unknowns as factors (a production line's few numbers, not a full
identification). Each run starts at the steady state of its first input sample (an
end-of-line test starts soaked).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._errors import InputError
from ..model._network import SCALABLE_LEAVES

#: A factor whose log-std is not below this (a factor of e) is undetermined by the log.
UNDETERMINED_LOG_STD = 1.0


@dataclasses.dataclass(frozen=True)
class TrimEstimate:
    """A unit's factors `values (D,)` with their std `std (D,)` and `correlation (D, D)`
    (the Gauss–Newton covariance scaled by the residual variance), the RMSE per sensor
    (°C) of the nominal and the trimmed model, the samples used, and `converged` (the
    solve converged and every factor's log-std is below `UNDETERMINED_LOG_STD`)."""

    names: tuple[str, ...]
    values: np.ndarray
    std: np.ndarray
    correlation: np.ndarray
    rmse_nominal: np.ndarray
    rmse_trimmed: np.ndarray
    sensors: tuple[str, ...]
    n_samples: int
    converged: bool

    def as_dict(self) -> dict:
        """The JSON form (`trim.json`, docs/observer.md §13; an undetermined std or
        correlation is null, JSON never holds NaN)."""
        from .._json import json_safe

        return json_safe({"factors": [{"name": n, "value": float(v), "std": float(s)}
                            for n, v, s in zip(self.names, self.values, self.std)],
                "correlation": np.asarray(self.correlation, float).tolist(),
                "rmse_nominal_C": dict(zip(self.sensors, map(float, self.rmse_nominal))),
                "rmse_trimmed_C": dict(zip(self.sensors, map(float, self.rmse_trimmed))),
                "samples": int(self.n_samples), "converged": bool(self.converged)})


def _masks(spec, plan):
    """Per network log-field, a `(entries, D)` 0/1 matrix: which factor scales which."""
    keys = {"nodes": [f"nodes.{n.name}.capacitance" for n in spec.nodes],
            "links": [f"links.{k.key}.conductance" for k in spec.links],
            "boundaries": [f"boundaries.{b.key}.conductance" for b in spec.boundaries],
            "heat_inputs": [f"heat_inputs.{h.key}.gain" for h in spec.heat_inputs]}
    out = {}
    for group, names in keys.items():
        M = np.zeros((len(names), len(plan.factors)))
        for d, f in enumerate(plan.factors):
            for i, name in enumerate(names):
                M[i, d] = float(name in f.parameters)
        out[SCALABLE_LEAVES[group][0]] = M
    return out


def estimate_trim(spec, experiments, plan, max_steps: int = 200) -> TrimEstimate:
    """The factors of `plan` that best explain `experiments` (end-of-line logs of one
    unit, `Experiment`s of `spec`'s columns) with the rest of `spec` nominal.

    Least squares in the log-factors (Levenberg–Marquardt), residuals weighted by the
    sensors' noise; std from the Jacobian at the optimum and the residual variance."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    from ..dynamics._simulate import simulate
    from ..model._model import ThermalModel

    model = ThermalModel.from_spec(spec)
    if model.is_nonlinear:
        raise InputError("the trim scales a linear network; this model has nonlinear "
                         "effects.", field="model")
    masks = {k: jnp.asarray(v) for k, v in _masks(spec, plan).items()}
    net = model.network
    offset = jnp.asarray(model.output_offset())
    sigma = jnp.asarray(model.noise)
    runs = [(jnp.asarray(e.inputs), jnp.asarray(e.ts), np.asarray(e.outputs)) for e in
            experiments]
    for e, (_, _, y) in zip(experiments, runs):
        if not np.isfinite(y).any():
            raise InputError("the log has no finite sensor reading.", file=e.name)
    finite = [jnp.asarray(np.isfinite(y)) for _, _, y in runs]
    ys = [jnp.asarray(np.nan_to_num(y)) for _, _, y in runs]
    fields = tuple(masks)

    def network(theta):
        return eqx.tree_at(lambda n: tuple(getattr(n, f) for f in fields), net,
                           tuple(getattr(net, f) + masks[f] @ theta for f in fields))

    def residuals(theta, _):
        nw = network(theta)
        parts = []
        for (u, ts, _), y, ok in zip(runs, ys, finite):
            out = simulate(nw, u, ts).outputs + offset[None, :]
            parts.append(jnp.where(ok, (out - y) / sigma[None, :], 0.0).ravel())
        return jnp.concatenate(parts)

    D = len(plan.factors)
    theta0 = jnp.zeros(D)
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)
    sol = optx.least_squares(residuals, solver, theta0, max_steps=max_steps, throw=False)
    theta = sol.value
    converged = bool(sol.result == optx.RESULTS.successful) and bool(
        jnp.all(jnp.isfinite(theta)))
    r = np.asarray(residuals(theta, None))
    J = np.asarray(jax.jacfwd(residuals)(theta, None))
    n = int(sum(int(np.asarray(ok).sum()) for ok in finite))
    if n <= D:
        raise InputError(f"{n} readings for {D} factors: the log is too short.",
                         file=experiments[0].name)
    s2 = float(r @ r) / (n - D)
    try:
        cov = s2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        cov = np.full((D, D), np.nan)
    std_log = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(std_log, std_log)
    values = np.exp(np.asarray(theta, float))

    def rmse(th):   # per sensor, pooled over the runs, °C
        res = np.asarray(residuals(th, None))
        blocks, start = [], 0
        for _, _, y in runs:
            blocks.append(res[start:start + y.size].reshape(y.shape))
            start += y.size
        err = np.concatenate(blocks) * np.asarray(sigma)
        ok = np.concatenate([np.asarray(f) for f in finite])
        return np.array([np.sqrt(np.mean(err[ok[:, j], j] ** 2)) if ok[:, j].any() else np.nan
                         for j in range(err.shape[1])])

    return TrimEstimate(plan.names, values, values * std_log, corr,
                        rmse(jnp.zeros(D)), rmse(theta), tuple(spec.sensor_columns), n,
                        converged and bool(np.all(std_log < UNDETERMINED_LOG_STD)))


def trim_outputs(spec, experiment, plan, values) -> np.ndarray:
    """The sensor outputs `(times, sensors)` °C of `spec` trimmed by `values (D,)` over
    one `experiment`, from the steady state of its first input sample."""
    from ..dynamics._simulate import simulate
    from ..model._model import ThermalModel

    model = ThermalModel.from_spec(plan.scaled(spec, values))
    out = simulate(model.network, experiment.inputs, experiment.ts).outputs
    return np.asarray(out, float) + np.asarray(model.output_offset(), float)
