"""The Fisher information of a model's free parameters for a given input profile.

Under output error with white sensor noise of std `σ_j` (°C) the Fisher information of
the free parameters `θ` (logs of positive parameters, initial temperatures in °C, the
fit's own layout) is

    F = Σ_k Σ_j J_kj J_kjᵀ / σ_j²,     J_kj = ∂y_j(t_k) / ∂θ,

with `y` the free-run readings. `J` comes from the fit's exact forward sensitivities
(`dynamics._sensitivity`): the blocked maps and their tangents depend only on `θ`, the
sample period and the start, and are computed once; the readings and their tangents are
then linear in the inputs, and JAX differentiates `F` through them in the inputs. The
initial temperatures the fit estimates are nuisance parameters: they are kept in `F`,
and marginalized out where a criterion or a std is taken (`marginal_information`), as
the fit's own stds marginalize them.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._errors import InputError
from ..dynamics._sensitivity import dataset_maps, run_primal, run_tangents
from ..measurements._data import Experiment
from ..model._parameters import free_parameters, with_free_parameters
from ..model._spec import ModelSpec


@dataclass(frozen=True)
class InformationProblem:
    """A model linearized at its file's values over a sample grid with a fixed start.

    **Arguments:** (built by `information_problem`)

    - `spec`: the model as lowered for fitting.
    - `names`: dotted names of the free parameters, (P,).
    - `sigma`: sensor noise stds, °C, (sensors,).
    - `n_times`: samples of the profile.
    - `maps`, `z0`, `dmaps`, `dz0`, `doffset`: the blocked maps and their tangents.
    - `theta`: the free parameters' values, (P,).
    - `chamber`: per input column (the lowered model's order), True where it is a
      boundary (the chamber temperature drives it), False for a heat input (the power).
    """

    spec: ModelSpec
    names: tuple[str, ...]
    sigma: np.ndarray
    n_times: int
    theta: np.ndarray
    maps: tuple
    z0: jax.Array
    dmaps: tuple
    dz0: jax.Array
    doffset: jax.Array
    chamber: tuple[bool, ...]
    # lowered name -> (effect parameter's name, scale, power): value = scale * lowered ** power
    renames: dict = dataclasses.field(default_factory=dict)

    @property
    def judged(self) -> list[str]:
        """The judged parameters' names as a model file and `fit`'s report give them (an
        effect's parameter by its own name, not its lowered entry's)."""
        return [self.renames.get(n, (n,))[0] for n, nui in zip(self.names, self.nuisance)
                if not nui]

    def inputs(self, temperature, power):
        """The input matrix (times, inputs) of a chamber temperature (times,), °C, and
        a power (times,), W: every boundary column sees the chamber, every heat input the
        power (as `simulate` drives a model with a profile)."""
        return jnp.stack([temperature if c else power for c in self.chamber], axis=1)

    @property
    def nuisance(self) -> np.ndarray:
        """True for the initial temperatures (marginalized out), (P,)."""
        return np.array([n.endswith(".initial") for n in self.names])

    def jacobian(self, inputs):
        """Reading sensitivities `∂y/∂θ` (times, sensors, P) for `inputs` (times, inputs)
        in the model's input order, whose first sample is the problem's start."""
        maps = jax.tree.map(lambda a: a[0], self.maps)
        dmaps = jax.tree.map(lambda a: a[0], self.dmaps)
        _, w = run_primal(maps, self.z0[0], inputs)
        J = run_tangents(maps, dmaps, self.dz0[0], w)
        return J[:self.n_times] + self.doffset.T[None]

    def information(self, inputs):
        """`F` (P, P) for `inputs` (times, inputs)."""
        J = self.jacobian(inputs) / jnp.asarray(self.sigma)[None, :, None]
        J = J.reshape(-1, J.shape[-1])
        return J.T @ J


@dataclass(frozen=True)
class Prepared:
    """A model made ready for profiles on a sample grid with a fixed start: the fit's own
    layout (`fitting._problem.prepare`) of a run at rest.

    - `spec`: the model as lowered for fitting; `names`: its free parameters' dotted names.
    - `template`, `index`: the fit's state and its free elements; `theta`: their values.
    - `data`: the run (inputs held at the start; replaced by each profile's).
    - `sigma`: sensor noise stds, °C; `chamber`: per input column, True for a boundary.
    """

    spec: ModelSpec
    names: tuple[str, ...]
    template: object
    index: object
    theta: np.ndarray
    data: object
    sigma: np.ndarray
    chamber: tuple[bool, ...]
    renames: dict = dataclasses.field(default_factory=dict)

    def inputs(self, temperature, power):
        """The input matrix (times, inputs) of a chamber temperature and a power (times,)."""
        return jnp.stack([temperature if c else power for c in self.chamber], axis=1)

    def readings(self, theta, inputs):
        """Free-run readings (times, sensors), °C, at parameters `theta` (P,) for `inputs`
        (times, inputs) whose first sample is the start."""
        from ..dynamics._sensitivity import dataset_outputs

        state = with_free_parameters(self.template, self.index, theta)
        data = dataclasses.replace(self.data, inputs=inputs[None].astype(theta.dtype))
        return dataset_outputs(state.model, data, state.run_initial)[0]


def prepare_profiles(spec: ModelSpec, ts: np.ndarray, start_c: float, start_power_w: float,
                     noise: float | None = None) -> Prepared:
    """`spec` made ready for profiles sampled at `ts` (s, uniform) whose first sample has
    the chamber at `start_c` (°C) and the power at `start_power_w` (W), the unit at rest.

    `noise`: one std for every sensor, °C; default each sensor's `noise` (0.01 °C unset).
    Models with nonlinear effects or bias channels are refused (the design is of the
    linear thermal model's readings).
    """
    from ..dynamics._as_written import simulate_as_written
    from ..fitting._problem import prepare

    if not spec.sensors:
        raise InputError("the model has no sensors, so no profile can tell its parameters; "
                         "add a [[sensors]] table.", file=spec.source, field="sensors")
    if spec.biases:
        raise InputError("experiment design reads the temperature sensors only; remove the "
                         "[[biases]] tables, or design with a copy of the model without them.",
                         file=spec.source, field="biases")
    ts = np.asarray(ts, float)
    boundary, heat = set(spec.boundary_columns), set(spec.heat_columns)
    for c in spec.input_columns:
        if c not in boundary and c not in heat:
            raise InputError(f"the input column {c!r} is neither a boundary's nor a heat "
                             "input's; a chamber profile cannot drive it.", file=spec.source,
                             field=c)
    u0 = np.array([start_c if c in boundary else start_power_w for c in spec.input_columns])
    steady = np.repeat(u0[None, :], 2, axis=0)
    y0 = np.asarray(simulate_as_written(spec, ts[:2], steady).outputs)[0]
    exp = Experiment(ts, np.repeat(u0[None, :], len(ts), axis=0),
                     np.repeat(y0[None, :], len(ts), axis=0), name="design")
    with warnings.catch_warnings():
        # a profile shorter than the slowest time constant is the design's own question
        warnings.filterwarnings("ignore", message=".*shorter than the slowest time constant")
        prep = prepare(spec, [exp], "output_error")
    if prep.template.model.is_nonlinear:
        raise InputError("the model has nonlinear effects; experiment design works on linear "
                         "models (links, boundaries, heat inputs and the linear effects).",
                         file=spec.source, field="effects")
    if noise is None:
        sigma = np.array([s.noise.value if s.noise is not None else 0.01
                          for s in prep.spec.sensors], float)
    else:
        sigma = np.full(len(prep.spec.sensors), float(noise))
    lowered_boundary = set(prep.spec.boundary_columns)
    chamber = tuple(c in lowered_boundary for c in prep.spec.input_columns)
    theta = np.asarray(free_parameters(prep.template, prep.index))
    return Prepared(prep.spec, tuple(prep.names), prep.template, prep.index, theta, prep.data,
                    sigma, chamber, prep.lowered.renames())


def information_problem(spec: ModelSpec, ts: np.ndarray, start_c: float, start_power_w: float,
                        noise: float | None = None) -> InformationProblem:
    """`prepare_profiles`, linearized at the model file's values: an `InformationProblem`."""
    p = prepare_profiles(spec, ts, start_c, start_power_w, noise)
    (maps, z0, offset), (dmaps, dz0, doffset) = _tangent_maps(jnp.asarray(p.theta), p.template,
                                                              p.index, p.data)
    return InformationProblem(p.spec, p.names, p.sigma, len(ts), p.theta, maps, z0, dmaps, dz0,
                              doffset, p.chamber, p.renames)


def _tangent_maps(theta, template, index, data):
    @jax.jit
    def go(theta, template, data):
        def maps_of(t):
            state = with_free_parameters(template, index, t)
            return (dataset_maps(state.model, data, state.run_initial),
                    state.model.output_offset())

        primal, tangent = jax.vmap(lambda v: jax.jvp(maps_of, (theta,), (v,)),
                                   out_axes=(None, (1, 0)))(
            jnp.eye(theta.shape[0], dtype=theta.dtype))
        ((maps, z0), offset), ((dmaps, dz0), doffset) = primal, tangent
        return (maps, z0, offset), (dmaps, dz0, doffset)

    return go(jnp.asarray(theta), template, data)


def marginal_information(F, nuisance: np.ndarray):
    """The information of the non-nuisance parameters with the nuisance ones (initial
    temperatures) estimated too: the Schur complement `F_ll − F_ln F_nn⁻¹ F_nl`."""
    keep, nui = np.flatnonzero(~nuisance), np.flatnonzero(nuisance)
    F_ll = F[jnp.ix_(keep, keep)]
    if nui.size == 0:
        return F_ll
    F_ln = F[jnp.ix_(keep, nui)]
    F_nn = F[jnp.ix_(nui, nui)]
    # scaled so a weakly excited start does not spoil the solve
    d = jnp.sqrt(jnp.clip(jnp.diag(F_nn), 1e-300))
    S = F_nn / (d[:, None] * d[None, :]) + 1e-12 * jnp.eye(nui.size)
    X = jnp.linalg.solve(S, (F_ln / d[None, :]).T)
    return F_ll - (F_ln / d[None, :]) @ X


def predicted_stds(F: np.ndarray, problem: InformationProblem
                   ) -> tuple[dict[str, float | None], list[str]]:
    """Each judged parameter's predicted std, in the fit's units (relative for logs of
    positive parameters), by the fit's own identifiability analysis (None where a
    direction is not determined), by the names `fit` reports; and that analysis's
    messages saying what is undetermined and why."""
    from ..fitting._identifiability import identifiability

    ident = identifiability(np.asarray(F), list(problem.names), problem.spec)
    out = {}
    for n, s, nui in zip(problem.names, ident.stds, problem.nuisance):
        if nui:
            continue
        target, _, power = problem.renames.get(n, (n, 1.0, 1.0))
        out[target] = float(abs(power) * s) if np.isfinite(s) else None
    return out, [m for m in ident.messages if ".initial " not in m]
