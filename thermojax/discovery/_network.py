"""A learned heat term where the library has no form: a small `equinox` network in the
model's right-hand side, trained on the measurements through the model's own dynamics,
then distilled into the library form that best matches it (docs/formats.md §3a,
docs/extensions.md).

The fitted model is held; the network adds a heat flow (W) into one node,

    C_a dT_a/dt = (the fitted network's terms) + q_net(features),

a function of that node's temperature, its neighbours' (nodes or boundary columns) and
the recorded columns that are not sensors. It starts as a regression on the node's
missing heat (`missing_heat`, over the smoothed temperatures), or from zero heat where
that start fits worse through the dynamics than none; then Levenberg–Marquardt
(`optimistix`) trains it on the same weighted output error as a fit, simulated by the
model's ETD2 integrator (`dynamics._nonlinear`: the linear part exact, the network's
heat linear in time over each substep), so its gradients go through the exact
discretization. The network's heat along its own trajectory is then regressed on every
library term at the node (`LIBRARY`) at its trial shapes; the best match by R² is the
proposal, an `expression` effect the caller adds and refits like any other candidate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ._library import LearnedLaw, column_scales, learned_places
from ._missing_heat import missing_heat
from ..dynamics._nonlinear import initial_state_nonlinear, readings, simulate_run_nonlinear
from ..model._expression import evaluate_numpy, parse, resolve
from ..model._spec import Effect
from ..model._system import LinearSystem


class NetworkHeat(eqx.Module):
    """A fitted `ThermalModel` plus an MLP heat flow into node `node` (W); shaped like
    the model where the ETD2 integrator reads it. Inputs `u` are the model's inputs
    followed by the extra columns; `features` picks (and `scale` standardizes) the
    network's arguments from `[x, u]`."""

    base: eqx.Module
    mlp: eqx.nn.MLP
    centre: jax.Array
    scale: jax.Array
    heat_scale: float = eqx.field(static=True)
    node: int = eqx.field(static=True)
    features: tuple[int, ...] = eqx.field(static=True)

    @property
    def etd2_substeps(self):
        return self.base.etd2_substeps

    def heat(self, x, u):
        """The network's heat flow into `node` (W)."""
        z = (jnp.concatenate([x, u])[np.array(self.features)] - self.centre) / self.scale
        return self.heat_scale * self.mlp(z)[0]

    def nonlinear_rate(self, system, x, u):
        rate = self.base.nonlinear_rate(system, x, u)
        return rate.at[self.node].add(self.heat(x, u) / system.capacitance[self.node])

    def initial_state(self, system, u0, run_initial=None, steady_state=None, solve=None):
        return self.base.initial_state(system, u0, run_initial, steady_state, solve)


@dataclass(frozen=True)
class Distilled:
    """One library term fitted to the network's heat: the law, where, its coefficient
    `c` and shape values, and R² of the match."""

    law: LearnedLaw
    where: tuple[str, ...]
    c: float
    shape: tuple[float, ...]
    r2: float

    def effect(self) -> Effect:
        """The `expression` effect of this proposal, ready to add to the model."""
        return self.law.effect(self.where, self.c, self.shape)


@dataclass(frozen=True)
class NetworkLaw:
    """What `learn_network_heat` returns: RMSE (°C) per sensor before the network, with
    it as regressed on the missing heat, and after its training through the dynamics; the network's heat (W) per run along its trajectory, and the library
    terms ranked by how well they match it (`distilled[0]` the proposal)."""

    node: str
    rmse_before: dict[str, float]
    rmse_regressed: dict[str, float]  # the start: the network regressed on the missing heat
    rmse_after: dict[str, float]
    heat: list[np.ndarray]
    distilled: list[Distilled]
    model: NetworkHeat = field(repr=False)


def _padded(system: LinearSystem, n_extra: int) -> LinearSystem:
    """`system` with `n_extra` more inputs that enter no node (the network reads them)."""
    n, p = system.A.shape[0], system.C.shape[0]
    return LinearSystem(system.A, jnp.concatenate([system.B, jnp.zeros((n, n_extra))], 1),
                        system.C, jnp.concatenate([system.D, jnp.zeros((p, n_extra))], 1),
                        holds=(*system.holds, *("foh",) * n_extra),
                        capacitance=system.capacitance)


@eqx.filter_jit  # one program per model type (held model, with network), not per call
def _simulate(model, system, runs, run_initial):
    """Readings (runs, times, sensors) and states of every run (lists of arrays)."""
    def one(ts, u, r0):
        x0 = initial_state_nonlinear(model, system, u[0], r0)
        x = simulate_run_nonlinear(model, system, ts, u, x0)
        base = model.base if isinstance(model, NetworkHeat) else model
        return readings(base, x), x
    return [one(ts, u, r0) for (ts, u, _, _), r0 in zip(runs, run_initial)]


def learn_network_heat(result, runs: list[tuple[np.ndarray, dict[str, np.ndarray]]],
                       node: str, *, width: int = 8, depth: int = 2,
                       max_steps: int = 100, trajectory_steps: int = 50, seed: int = 0,
                       missing=None) -> NetworkLaw:
    """Train a heat network at `node` of a fitted model and distil it.

    **Arguments:**

    - `result`: a `FitResult` of a model without bias channels.
    - `runs`: the fitted runs, in the fit's order, as `(ts (s), columns)`: every input
      and sensor column of the model, plus any other recorded column the network may
      read (`air_speed`, a fan command).
    - `node`: the node the missing heat flows into.
    - `width`, `depth`: the MLP's hidden layers (tanh).
    - `max_steps`: Levenberg–Marquardt iterations of the regression on the missing heat;
      `trajectory_steps` those of the training through the dynamics that follows (0:
      none, the regression alone).
    - `missing`: the fitted model's `MissingHeat` when already at hand over every node
      (the loop's); else reconstructed here.

    **Returns:** a `NetworkLaw`.
    """
    spec = result.lowered_spec
    base = result.model
    nodes = list(spec.node_names)
    if node not in nodes:
        raise ValueError(f"node {node!r} is not in the model (nodes: {nodes}).")
    if result.biases:
        raise ValueError("learn_network_heat takes a model without bias channels.")
    inputs, sensors = list(spec.input_columns), list(spec.sensor_columns)
    for i, (_, cols) in enumerate(runs):
        lacking = [c for c in inputs + sensors if c not in cols]
        if lacking:
            raise ValueError(f"run {i} lacks the model's column(s) {lacking}; pass the "
                             "fitted runs with every input and sensor column.")
    extras = sorted(set(runs[0][1]) - set(inputs) - set(sensors))
    columns = inputs + extras
    system = _padded(base.linear_system(), len(extras))
    data = []
    for ts, cols in runs:
        u = jnp.asarray(np.stack([np.asarray(cols[c], float) for c in columns], 1))
        y = np.stack([np.asarray(cols[c], float) for c in sensors], 1)
        data.append((jnp.asarray(ts, float), u, jnp.asarray(np.nan_to_num(y)),
                     jnp.asarray(np.isfinite(y))))
    run_initial = list(result.state.run_initial)
    sigma = jnp.asarray([result.parameters[f"sensors.{c}.noise"]["value"] for c in sensors])

    # the network's arguments: the node, its conduction neighbours (nodes or boundary
    # columns), then every other recorded non-sensor column
    from ..model.effects._base import conduction_paths
    near = {b for a, b in conduction_paths(spec) if a == node} | {
        a for a, b in conduction_paths(spec) if b == node}
    names = nodes + columns
    picked = [node] + sorted(near) + [c for c in columns if c not in near]
    features = tuple(names.index(n) for n in picked)
    before = _simulate(base, system, data, run_initial)
    # a start: the network regressed on the missing heat at the node (Kalman-smoothed,
    # `missing_heat`), over the smoothed temperatures; the trajectory fit refines it
    mh = missing if missing is not None and missing.nodes == tuple(nodes) else \
        missing_heat(result, nodes=tuple(nodes))
    at = nodes.index(node)
    target = np.concatenate([h[:, at] for h in mh.heat])
    if not np.any(target):
        raise ValueError(f"no missing heat at node {node!r}: the model explains the data "
                         "there (or another node carries it); nothing to learn.")
    smooth = np.concatenate([np.concatenate([x, np.asarray(u)[:len(x)]], 1)
                             for x, (_, u, _, _) in zip(mh.temperatures, data)])[:, features]
    centre, spread = smooth.mean(0), smooth.std(0)
    spread = np.where(spread > 0, spread, 1.0)
    heat_scale = float(np.std(target))
    target_std = np.concatenate([h[:, at] for h in mh.heat_std])
    target_std = np.maximum(target_std, 0.1 * np.median(target_std) + 1e-12)

    mlp = eqx.nn.MLP(len(features), 1, width, depth, activation=jnp.tanh,
                     key=jax.random.PRNGKey(seed))
    z = jnp.asarray((smooth - centre) / spread)

    weights, layout = eqx.partition(mlp, eqx.is_inexact_array)

    def regression_errors(weights, _):
        net = eqx.combine(weights, layout)
        return (heat_scale * jax.vmap(net)(z)[:, 0] - target) / target_std

    weights = optx.least_squares(eqx.filter_jit(regression_errors),
                                 optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6), weights,
                                 max_steps=max_steps, throw=False).value
    mlp = eqx.combine(weights, layout)
    model = NetworkHeat(base, mlp, jnp.asarray(centre), jnp.asarray(spread), heat_scale,
                        at, features)
    regressed = _simulate(model, system, data, run_initial)
    params, static = eqx.partition(model, eqx.is_inexact_array)

    def with_mlp(mlp_params):
        return eqx.combine(eqx.tree_at(lambda t: t.mlp, params, mlp_params), static)

    def errors_of(sims):
        return jnp.concatenate([jnp.where(mask, (y - r) / sigma[None, :], 0.0).ravel()
                                for (r, _), (_, _, y, mask) in zip(sims, data)])

    def weighted_errors(mlp_params, _):
        return errors_of(_simulate(with_mlp(mlp_params), system, data, run_initial))

    start = params.mlp
    if float(jnp.sum(errors_of(regressed) ** 2)) > float(jnp.sum(errors_of(before) ** 2)):
        # the regressed network, fed back through the dynamics, does worse than no heat
        # (it extrapolates off the smoothed states): train from zero heat instead
        start = eqx.tree_at(lambda m: (m.layers[-1].weight, m.layers[-1].bias), start,
                            (jnp.zeros_like(start.layers[-1].weight),
                             jnp.zeros_like(start.layers[-1].bias)))
    sol = optx.least_squares(eqx.filter_jit(weighted_errors),
                             optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6),
                             start, max_steps=trajectory_steps, throw=False,
                             options={"jac": "fwd"}) if trajectory_steps else None
    model = with_mlp(sol.value) if sol is not None else model
    after = _simulate(model, system, data, run_initial)

    def rmse(sims):
        out = {}
        for j, c in enumerate(sensors):
            e = np.concatenate([np.asarray(y[:, j] - r[:, j])[np.asarray(m[:, j])]
                                for (r, _), (_, _, y, m) in zip(sims, data)])
            out[c] = float(np.sqrt(np.mean(e ** 2)))
        return out

    heat_fn = jax.jit(jax.vmap(model.heat))
    heats = [np.asarray(heat_fn(x, u)) for (_, x), (_, u, _, _) in zip(after, data)]
    values = np.concatenate([np.concatenate([np.asarray(x), np.asarray(u)], 1)
                             for (_, x), (_, u, _, _) in zip(after, data)])
    powers = {h.input: "power" for h in spec.heat_inputs}
    distilled = _distil(np.concatenate(heats), values, names, spec,
                        {**{c: "other" for c in extras}, **powers}, node)
    return NetworkLaw(node, rmse(before), rmse(regressed), rmse(after), heats, distilled,
                      model)


def _distil(q, values, names, spec, columns, node) -> list[Distilled]:
    """Every library term at `node` fitted to the heat `q` (samples,) over the states
    and columns `values` (samples, names): at each of its trial shapes (as the score test
    tries them) its coefficient by linear least squares; per term the best shape, ranked
    by R². The refit of the chosen term frees its shape."""
    total = float(np.sum((q - q.mean()) ** 2)) or 1.0
    out = []
    scales = column_scales({c: values[:, names.index(c)] for c in columns if c in names})
    for law, where in learned_places(spec, columns, scales):
        if where[0] != node:
            continue
        eff = law.effect(where, 1.0)
        tree = resolve(parse(eff.expression), names, [], list(eff.parameters))
        best = None
        for shape in law.term.trials or ((),):
            f = evaluate_numpy(tree, values, values[:, :0], [1.0, *shape])
            if not np.all(np.isfinite(f)) or not np.any(f):
                continue
            c = float(f @ q / (f @ f))
            r2 = 1.0 - float(np.sum((c * f - q) ** 2)) / total
            if best is None or r2 > best.r2:
                best = Distilled(law, tuple(where), c, tuple(float(v) for v in shape), r2)
        if best is not None:
            out.append(best)
    return sorted(out, key=lambda d: -d.r2)
