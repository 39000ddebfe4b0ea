"""A fit as a problem in one flat vector `theta`: the structure, the data and the layout.

`prepare(spec, experiments, ...)` is the first stage of `fit`: it lowers structural
effects into plain entries, checks and pads the runs into a `Dataset`, and builds the
`FitState` template with the mask of its free elements. `theta` holds logs of the
positive parameters (J/K, W/K, noise stds) and initial temperatures in °C. Residual
and loss functions take `(theta, problem)`, `problem` a `_Problem` passed as
optimistix's `args`, so a second fit of the same structure reuses the compilation.
"""

from __future__ import annotations

import dataclasses
import warnings
from dataclasses import dataclass, field

import equinox as eqx
import jax
import numpy as np

from .._errors import InputError
from ..measurements._data import Dataset, Experiment
from ..model._model import ThermalModel, term_effects
from ..model._network import Topology, conductance_matrix, time_constants
from ..model._parameters import FreeIndex, with_free_parameters
from ..model._spec import EFFECT_KINDS, ModelSpec
from ..model.effects import Lowered, lower_effects
from ._bias_residuals import BiasColumns, bias_columns, spec_strains
from ._initial_states import estimated_starts, run_initial_start, with_starts
from ._integration import fewest_substeps, shared_substeps, start_tolerance, with_substeps

LIKELIHOODS = ("output_error", "kalman")


class FitState(eqx.Module):
    """Everything a fit moves: the model, each run's estimated initial temperatures and
    the log relaxation times of the bias channels' viscoelastic effects."""

    model: ThermalModel
    run_initial: jax.Array  # (runs, len(model.initial_nodes)), °C
    bias_log_tau: jax.Array  # (viscoelastic effects,) log s, `_bias_residuals.spec_strains` order


class _Problem(eqx.Module):
    """What the residual and loss functions need besides `theta` (optimistix `args`)."""

    template: FitState
    index: FreeIndex = eqx.field(static=True)
    data: Dataset
    sigma: jax.Array  # (sensors + bias columns,), °C then column units: residual weights
    prior_mean: jax.Array  # (free,)
    prior_weight: jax.Array  # (free,) 1/std of the prior; a huge weight pins a parameter
    bias: BiasColumns | None = None


def make_problem(template: FitState, index: FreeIndex, data: Dataset, sigma, prior_mean,
                 prior_weight=0.0, bias: BiasColumns | None = None) -> _Problem:
    """A `_Problem` whose arrays go to the device from NumPy (no eager XLA programs)."""
    prior_mean = np.asarray(prior_mean, float)
    weight = np.broadcast_to(np.asarray(prior_weight, float), prior_mean.shape)
    return _Problem(template, index, data, *jax.device_put(
        (np.asarray(sigma, float), prior_mean, np.array(weight))), bias)


def _state(theta, problem: _Problem) -> FitState:
    return with_free_parameters(problem.template, problem.index, theta)


def _model_of(theta, problem: _Problem):
    """`(model, run_initial)` at `theta`; with bias columns the model reads out every
    node's temperature after the sensors (`ThermalModel.read_states`)."""
    s = _state(theta, problem)
    if problem.bias is not None:
        return dataclasses.replace(s.model, read_states=True), s.run_initial
    return s.model, s.run_initial


def _prior(theta, problem: _Problem):
    """Weighted prior rows (free,)."""
    return (theta - problem.prior_mean) * problem.prior_weight


@dataclass
class Solution:
    """A solved problem: what `_summary.summarize` turns into a `FitResult`."""

    problem: _Problem  # at the final noise stds, without prior
    theta: np.ndarray  # (free,)
    state: FitState
    names: list[str]  # dotted names of theta's elements (lowered spec)
    information: np.ndarray  # (free, free) Fisher information in theta
    nll: float
    n_steps: int
    converged: bool
    predictions: np.ndarray  # (runs, times, outputs) °C, free run
    # Noise stds estimated outside theta (output error, ML): name -> (value, std) °C.
    noise: dict[str, tuple[float, float]] = field(default_factory=dict)
    n_evaluations: int | None = None  # residual evaluations at trial points
    at_bound: tuple[str, ...] = ()  # free parameters held at zero (a variance's boundary)
    innovations: np.ndarray | None = None  # Kalman: standardized, (runs, times, outputs)
    # The other starts of a multi-start fit: (theta, nll) each (`_twin_optima`).
    alternatives: list = field(default_factory=list)
    # How the optimum was found, in words for the report (`FitResult.method`); "" for the
    # default of the likelihood.
    method: str = ""
    # Words for a direction along which the likelihood still falls (`_stationarity`): the
    # solve stopped short of a stationary point, not converged. "" where none.
    not_stationary: str = ""


def output_error_solution(prep: "Prepared", theta, theta0, sigma, information, nll: float,
                          n_steps: int, converged: bool, predictions, n_evaluations: int,
                          **more) -> Solution:
    """The `Solution` of an output-error solve at `theta` (free,) with the noise stds
    `sigma` (sensors + bias columns,) it ended at: the model carries the sensors' stds,
    each estimated std is reported with its ML std `σ / sqrt(2 N)`; `information` (free,
    free) is `JᵀJ` weighted by `sigma`; `more`: the other fields of `Solution`."""
    sigma = np.asarray(sigma, float)
    state = with_free_parameters(prep.template, prep.index, jax.device_put(np.asarray(theta)))
    p = len(prep.spec.sensors)
    state = FitState(eqx.tree_at(lambda m: m.log_noise, state.model,
                                 jax.device_put(np.log(sigma[:p]))), state.run_initial,
                     state.bias_log_tau)
    n_meas = prep.mask().sum(axis=(0, 1))
    names = ([f"sensors.{c}.noise" for c in prep.spec.sensor_columns]
             + [f"biases.{b.column}.noise" for b in prep.spec.biases])
    noise = {name: (float(sigma[j]), float(sigma[j] / np.sqrt(2 * max(n_meas[j], 1))))
             for j, name in enumerate(names) if not prep.fixed_sigma[j]}
    return Solution(make_problem(prep.template, prep.index, prep.data, sigma, theta0,
                                 bias=prep.bias),
                    np.asarray(theta), state, prep.names, np.asarray(information), float(nll),
                    int(n_steps), bool(converged), np.asarray(predictions), noise,
                    None if n_evaluations is None else int(n_evaluations), **more)


# ---------------------------------------------------------------------------
# Preparation


@dataclass(frozen=True)
class Prepared:
    """A model and its runs made ready to fit (`prepare`)."""

    lowered: Lowered  # the spec as given (`original`) and lowered (`spec`)
    experiments: list[Experiment]  # inputs in the lowered spec's column order
    data: Dataset
    template: FitState  # starting values
    index: FreeIndex  # free elements under output error
    names: list[str]  # their dotted names
    fixed_sigma: np.ndarray  # (sensors + bias columns,) bool: noise std fixed in the file
    bias: BiasColumns | None = None  # the bias columns, None without `[[biases]]`
    bias_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))  # starting stds

    @property
    def spec(self) -> ModelSpec:
        return self.lowered.spec

    @property
    def sigma(self) -> np.ndarray:
        """Starting noise stds (sensors + bias columns,), °C then column units."""
        return np.concatenate([np.exp(np.asarray(self.template.model.log_noise)),
                               self.bias_sigma])

    @property
    def columns(self) -> list[str]:
        """The measured columns the likelihood counts: sensors, then bias columns."""
        return list(self.spec.sensor_columns) + list(self.bias.columns if self.bias else ())

    def mask(self) -> np.ndarray:
        """Where each column was measured, (runs, times, sensors + bias columns)."""
        mask = np.asarray(self.data.mask)
        if self.bias is None:
            return mask
        T = mask.shape[1]
        return np.concatenate([mask, np.asarray(self.bias.mask)[:, :T]], axis=2)

    def free(self, likelihood: str) -> tuple[FreeIndex, list[str]]:
        """The free elements of `template` under `likelihood`, and their dotted names."""
        if likelihood == "output_error":
            return self.index, self.names
        return _free_elements(self.spec, self.template.model, self.data.n_runs, likelihood)


def prepare(spec: ModelSpec, experiments: list[Experiment], likelihood: str,
            holdout: int | tuple | None = None, starts: dict | None = None) -> Prepared:
    """Lower `spec`'s structural effects, check and pad the runs, and lay out `theta`.

    `holdout`: index of a run whose measurements are masked out of the likelihood, or
    `(run, (start, stop))`: a block of samples of that run masked out (its sensor
    readings; a run's start is still estimated from its first readings, so a block at a
    run's start does not move the start to the block's end). `starts`: node -> per-run
    start (°C, (runs,)) replacing the data's for the nodes whose start is estimated (a
    held-out fit starts from the full fit's estimates: `fitting._initial_states`).
    """
    if likelihood not in LIKELIHOODS:
        raise InputError(f"unknown likelihood '{likelihood}'; use one of {list(LIKELIHOODS)}.",
                         field="--likelihood")
    lowered = lower_effects(spec)
    spec = lowered.spec
    _check_shapes(lowered.original, spec, experiments)
    experiments = _reorder_inputs(experiments, lowered.original.input_columns,
                                  spec.input_columns)
    _check_runs(spec, experiments)
    data = dataset(experiments)
    if holdout is not None:
        mask = np.array(data.mask)
        run, span = holdout if isinstance(holdout, tuple) else (holdout, None)
        mask[run, slice(*span) if span is not None else slice(None)] = False
        data = dataclasses.replace(data, mask=jax.device_put(mask))
    estimated = estimated_starts(lowered, experiments, ThermalModel.from_spec)
    starts = {**estimated, **{n: np.asarray(v, float) for n, v in (starts or {}).items()
                              if n in estimated}}
    if starts:
        lowered = lower_effects(with_starts(lowered.original, starts))
        spec = lowered.spec
    model = ThermalModel.from_spec(spec)
    run_initial = run_initial_start(spec, model, starts, data.n_runs)
    template = FitState(model, *jax.device_put((run_initial, _log_taus(spec))))
    index, names = _free_elements(spec, model, data.n_runs, "output_error")
    if not names and likelihood == "output_error":
        raise InputError("nothing to fit: every parameter is fixed. Make at least one "
                         "capacitance, conductance or gain a bare number.", file=spec.source)
    fixed_sigma = np.array([s.noise is not None and s.noise.fixed
                            for s in (*spec.sensors, *spec.biases)], dtype=bool)
    bias = bias_columns(spec, experiments, holdout if not isinstance(holdout, tuple) else None)
    bias_sigma = np.array([_bias_sigma_start(b, j, experiments)
                           for j, b in enumerate(spec.biases)])
    prep = Prepared(lowered, experiments, data, template, index, names, fixed_sigma, bias,
                    bias_sigma)
    # a Kalman fit chooses its own (`_kalman_fit`), and this only before an output-error stage
    return integrated_for_output_error(prep) if likelihood == "output_error" else prep


def integrated_for_output_error(prep: Prepared) -> Prepared:
    """`prep` with a nonlinear model integrated in the fewest ETD2 substeps whose free
    run is accurate at the start values (`_integration`), for an output-error fit."""
    model = prep.template.model
    if not model.is_nonlinear:
        return prep
    substeps, _ = fewest_substeps(prep.template, prep.data, start_tolerance(np.exp(
        np.asarray(model.log_noise))), read_states=prep.bias is not None)
    substeps = shared_substeps(model, substeps)
    return dataclasses.replace(prep, template=with_substeps(prep.template, substeps))


def _log_taus(spec: ModelSpec) -> np.ndarray:
    """Starting log relaxation times (viscoelastic effects,), log s: the file's values,
    else the effect's default."""
    from ..model.effects import KINDS

    default = KINDS["viscoelastic"].initial_parameters(spec, None)["time_constant"]
    return np.log(np.array([s.time_constant.value if s.time_constant is not None else default
                            for s in spec_strains(spec)], float).reshape(-1))


def _bias_sigma_start(bias, j: int, experiments) -> float:
    """A bias column's starting noise std: its file value, else the column's spread (an
    estimated one is replaced by its ML value from the solve's first step on)."""
    if bias.noise is not None:
        return float(bias.noise.value)
    values = np.concatenate([e.biases[:, j] for e in experiments])
    spread = float(np.nanstd(values))
    return spread if spread > 0 else 1.0


def dataset(experiments: list[Experiment]) -> Dataset:
    """The runs padded into a `Dataset`, without names (names would recompile)."""
    return dataclasses.replace(Dataset.from_experiments(experiments), names=())


def template_at(spec: ModelSpec, run_initial, n_runs: int) -> tuple[FitState, FreeIndex]:
    """The output-error template of `spec`'s values with `run_initial` (runs, k) °C."""
    model = ThermalModel.from_spec(spec)
    index, _ = _free_elements(spec, model, n_runs, "output_error")
    return FitState(model, *jax.device_put((np.asarray(run_initial), _log_taus(spec)))), index


def _free_elements(spec: ModelSpec, model: ThermalModel, n_runs: int, likelihood: str):
    """`(FreeIndex, free names)` of a `FitState` under `likelihood`."""
    mask, names = _masks(spec, model, n_runs, likelihood)
    return FreeIndex(mask), names


def _masks(spec: ModelSpec, model: ThermalModel, n_runs: int, likelihood: str):
    """Boolean masks shaped like `FitState` (True = free) and the dotted name of every
    free element."""
    kalman = likelihood == "kalman"
    nodes = spec.node_names
    net_masks = [
        ([not n.capacitance.fixed for n in spec.nodes],
         [f"nodes.{n.name}.capacitance" for n in spec.nodes]),
        ([not k.conductance.fixed for k in spec.links],
         [f"links.{k.key}.conductance" for k in spec.links]),
        ([not b.conductance.fixed for b in spec.boundaries],
         [f"boundaries.{b.key}.conductance" for b in spec.boundaries]),
        ([not h.gain.fixed for h in spec.heat_inputs],
         [f"heat_inputs.{h.key}.gain" for h in spec.heat_inputs]),
        ([kalman and not (s.noise is not None and s.noise.fixed) for s in spec.sensors],
         [f"sensors.{s.column}.noise" for s in spec.sensors]),
        ([kalman and not (n.process_noise is not None and n.process_noise.fixed)
          for n in spec.nodes], [f"nodes.{n.name}.process_noise" for n in spec.nodes]),
        ([False] * len(nodes), [f"nodes.{n}.initial" for n in nodes]),
        ([False] * len(nodes), [f"nodes.{n}.initial_std" for n in nodes]),
    ]
    terms = list(zip(term_effects(spec), model.effect_terms, strict=True))
    net_masks.append((
        [not (p in e.parameters and e.parameters[p].fixed) for e, t in terms
         for p in t.parameters],
        [f"effects.{t.kind}.{'-'.join(e.where)}.{p}" for e, t in terms for p in t.parameters]))
    strains = spec_strains(spec)
    tau_mask = np.array([not kalman and not (s.time_constant is not None
                                             and s.time_constant.fixed) for s in strains],
                        dtype=bool)
    tau_names = [s.parameter for s in strains]
    init_free = [not spec.nodes[i].initial.fixed for i in model.initial_nodes]
    run_mask = np.array([init_free] * n_runs, dtype=bool).reshape(n_runs, len(init_free))
    run_names = [[f"runs.{r}.nodes.{nodes[i]}.initial" for i in model.initial_nodes]
                 for r in range(n_runs)]
    arrays = [np.array(m, dtype=bool) for m, _ in net_masks]
    template_mask = FitState(
        ThermalModel(
            eqx.tree_at(lambda n: (n.log_capacitance, n.log_conductance,
                                   n.log_boundary_conductance, n.log_heat_gain),
                        model.network, tuple(arrays[:4])),
            arrays[4], arrays[5], arrays[6], arrays[7], model.initial_nodes, arrays[8],
            model.effect_terms, jax.tree.map(lambda x: np.zeros(x.shape, bool),
                                             model.effect_sensors),
            added_nodes=model.added_nodes),
        run_mask, tau_mask)
    names = ([nm for _, nms in net_masks for nm in nms] + [nm for row in run_names for nm in row]
             + tau_names)
    flat_mask = np.concatenate([*arrays, run_mask.reshape(-1), tau_mask])
    free_names = [nm for nm, f in zip(names, flat_mask) if f]
    return template_mask, free_names


def _reorder_inputs(experiments, columns, order):
    """Experiments with their input columns rearranged from `columns` to `order` (a
    lowered spec lists the same columns, maybe in another order)."""
    if tuple(columns) == tuple(order):
        return experiments
    idx = [list(columns).index(c) for c in order]
    return [dataclasses.replace(e, inputs=e.inputs[:, idx]) for e in experiments]


def _slowest_time_constant(spec: ModelSpec) -> float:
    """The slowest time constant of `spec`'s network at its file values (s; inf when a
    node has no path to a boundary), computed in NumPy: a fit compiles nothing for it."""
    K = conductance_matrix(Topology.from_spec(spec),
                           np.array([k.conductance.value for k in spec.links], float),
                           np.array([b.conductance.value for b in spec.boundaries], float))
    with np.errstate(divide="ignore"):
        return float(time_constants(np.array([n.capacitance.value for n in spec.nodes]),
                                    K)[-1])


def _check_shapes(original: ModelSpec, lowered: ModelSpec,
                  experiments: list[Experiment]) -> None:
    """Each run holds one input column per input of the model (`original`'s order) and
    one output column per sensor: otherwise the message says which, not a shape error
    deep in the first simulation."""
    for e in experiments:
        for what, got, want in (("input", e.inputs.shape[1], original.input_columns),
                                ("sensor", e.outputs.shape[1], lowered.sensor_columns)):
            if got != len(want):
                raise InputError(f"the run has {got} {what} column(s) but the model reads "
                                 f"{len(want)}: {', '.join(want)} (in this order); build "
                                 f"the Experiment from the model's {what} columns.",
                                 file=e.name, field=f"{what}s")


# What a run shorter than the starting model's slowest time constant is warned of (a
# refit from a start thermojax chose itself filters it out: the user's start is checked).
SHORT_RUN = "shorter than the slowest time constant of the starting model"


def _check_runs(spec: ModelSpec, experiments: list[Experiment]) -> None:
    if not experiments:
        raise InputError("no runs given; pass at least one --data file.", field="--data")
    slowest = _slowest_time_constant(spec)
    for e in experiments:
        measured = np.isfinite(e.outputs)
        if not measured.any():
            raise InputError("no sensor data in this run: every sensor cell is empty or NaN.",
                             file=e.name, field=",".join(spec.sensor_columns))
        for j in np.flatnonzero(~measured.any(axis=0)):
            col = spec.sensor_columns[j] if j < len(spec.sensor_columns) else f"output {j}"
            raise InputError(f"sensor column {col!r} has no readings in this run (every cell is "
                             "empty or nan); drop it from the model or use a run that measured "
                             "it.", file=e.name, field=col)
        duration = e.ts[-1] - e.ts[0]
        if duration < slowest:  # a short test, or a clock in other units than seconds
            warnings.warn(f"{e.name}: the run lasts {duration:.0f} s, {SHORT_RUN} "
                          f"({slowest:.0f} s); the slow parameters will be poorly determined. "
                          "If `time_s` counts minutes or hours, not seconds, convert it: "
                          "the fit would otherwise make every time constant that much too "
                          "short.", stacklevel=4)


# ---------------------------------------------------------------------------
# theta's layout


def _is_log(name: str) -> bool:
    """Whether the optimizer moves this parameter's log (positive parameters)."""
    if name.startswith("effects."):
        parts = name.split(".")
        return parts[-1] in EFFECT_KINDS[parts[1]].positive
    return not name.endswith(".initial")


def _perturbed_starts(theta0, names: list[str], n: int, seed: int) -> list[jax.Array]:
    """`n` starts around `theta0`: log-parameters by a factor e^N(0, 0.5²), initial
    temperatures by N(0, 1) °C."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(max(n, 0)):
        step = np.array([rng.normal(0, 0.5) if _is_log(nm) else rng.normal(0, 1.0)
                         for nm in names])
        out.append(jax.device_put(np.asarray(theta0) + step))
    return out


def _check_finite(theta, theta0, names):
    """Raise an `InputError` naming the parameter that ran away to a non-finite value."""
    theta = np.asarray(theta)
    if np.all(np.isfinite(theta)):
        return
    bad = [nm for nm, t in zip(names, theta) if not np.isfinite(t)]
    jump = np.abs(np.nan_to_num(theta - np.asarray(theta0), nan=np.inf))
    worst = names[int(np.argmax(jump))] if len(names) else "?"
    raise InputError(f"the fit diverged: {', '.join(bad) or worst} ran away to a non-finite "
                     f"value (largest move: {worst}). Check that parameter's starting value and "
                     "units, fix it from design data, or give the data more excitation.")

