"""How finely a fit integrates nonlinear effects (`fitting._integration`), against the
independent truth generator (`tests/hidden/generator.py`: Radau, rtol = atol = 1e-10,
no thermojax import) on the hidden cases' truth models.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
import pytest

from thermojax import Dataset, Experiment, ThermalModel, fit
from thermojax.dynamics._nonlinear import dataset_outputs_nonlinear, etd2_error
from thermojax.fitting._fit_report import fit_report
from thermojax.fitting._integration import (KALMAN_TOLERANCE, SUBSTEP_LADDER,
                                            fewest_kalman_substeps, fewest_substeps,
                                            integration_tolerance)
from thermojax.fitting._likelihood import kalman_nll_in_substeps
from thermojax.fitting._problem import FitState
from thermojax.model.effects import lower_effects

from hidden import generator as g
from test_effects import HORIZON_S, _truth_spec

NONLINEAR_CASES = ["radiation", "conductance_temperature", "capacitance_temperature",
                   "conductance_input"]


def _case(name, noise=False, horizon_s=HORIZON_S):
    """`(spec, data, reference)`: the case's truth model, its first run's inputs and the
    generator's readings (T, sensors)."""
    case = g.load_case(name)
    spec = _truth_spec(case)
    ts, cols = g.generate_case(name, seed=0, horizon_s=horizon_s, noise=noise)[0]
    inputs = g.run_inputs(case, 0, [0], horizon_s)[1]
    u = np.stack([inputs[c] for c in lower_effects(spec).spec.input_columns], 1)
    p = len(spec.sensor_columns)
    data = Dataset.from_experiments([Experiment(ts, u, np.zeros((len(ts), p)))])
    return spec, data, np.stack([cols[c] for c in spec.sensor_columns], 1)


def _true_error(model, substeps, data, reference) -> float:
    y = dataset_outputs_nonlinear(dataclasses.replace(model, etd2_substeps=substeps), data)
    return float(np.max(np.abs(np.asarray(y)[0] - reference)))


@pytest.mark.parametrize("name", NONLINEAR_CASES)
def test_estimated_error_is_the_error_against_the_generator(name):
    """`etd2_error` (the difference from four times as many substeps, times 16/15) is
    the simulation's largest error against the generator, coarse and fine."""
    spec, data, reference = _case(name)
    model = ThermalModel.from_spec(spec)
    for substeps in (1, 4):
        true = _true_error(model, substeps, data, reference)
        estimate = float(etd2_error(model, data, None, jax.device_put(np.asarray(substeps))))
        assert true > 1e-8  # far above the generator's own error
        assert estimate == pytest.approx(true, rel=0.05), (substeps, estimate, true)


@pytest.mark.parametrize("name", ["radiation", "conductance_temperature"])
def test_fewest_substeps_within_tolerance_by_the_generator(name):
    """The chosen count keeps the error against the generator under the tolerance, and
    the next fewer on the ladder does not (a mild radiation exchange: one substep; a
    temperature-dependent conductance at a fast node: more)."""
    spec, data, reference = _case(name)
    model = ThermalModel.from_spec(spec)
    tolerance = integration_tolerance([0.01])  # 1e-4 °C
    state = FitState(model, np.zeros((1, 0)), np.zeros(0))
    substeps, estimate = fewest_substeps(state, data, tolerance)
    assert _true_error(model, substeps, data, reference) <= tolerance
    if substeps > SUBSTEP_LADDER[0]:
        fewer = SUBSTEP_LADDER[SUBSTEP_LADDER.index(substeps) - 1]
        assert _true_error(model, fewer, data, reference) > tolerance
    assert (substeps == 1) == (name == "radiation")


# −log L: a Kalman rule tight enough that the hidden cases' 1 s samples need more than one
# of the filter's fourth-order substeps (at the default 0.05, one is within 2.5e-4 of
# 256 on every case), so that the fits' re-solves in more substeps are exercised.
TIGHT = 1e-4


@pytest.mark.parametrize("name", ["conductance_temperature", "radiation"])
def test_a_kalman_fit_takes_the_substeps_its_likelihood_needs(name, monkeypatch):
    """The Kalman rule's estimate (the difference from four times as many substeps, times
    256/255: the filter's step is fourth order) is −log L's error against the filter
    integrated in 256 substeps (whose steps converge to the generator's readings:
    `test_etdrk4.py`), and the chosen count is the fewest of the ladder within the
    tolerance of it (`TIGHT`: a temperature-dependent conductance then needs more than
    one, a mild radiation exchange still one)."""
    import jax.numpy as jnp

    from thermojax.fitting import _integration

    monkeypatch.setattr(_integration, "KALMAN_TOLERANCE", TIGHT)
    spec, data, reference = _case(name, noise=True)
    data = dataclasses.replace(data, outputs=jnp.asarray(reference)[None])
    model = ThermalModel.from_spec(spec)
    state = FitState(model, np.zeros((1, 0)), np.zeros(0))

    def nll(substeps):
        return float(kalman_nll_in_substeps(model, data, state.run_initial,
                                            jax.device_put(np.asarray(substeps))))

    fine = nll(256)
    for substeps in (1, 2):
        true = abs(nll(substeps) - fine)
        if true > 1e-6:  # above the sum's rounding (~6e-8 on these runs)
            estimate = (256 / 255) * abs(nll(substeps) - nll(4 * substeps))
            assert estimate == pytest.approx(true, rel=0.1)
    chosen, _ = fewest_kalman_substeps(state, data)
    assert abs(nll(chosen) - fine) <= TIGHT
    if chosen > SUBSTEP_LADDER[0]:
        fewer = SUBSTEP_LADDER[SUBSTEP_LADDER.index(chosen) - 1]
        assert abs(nll(fewer) - fine) > TIGHT
    assert (chosen == 1) == (name == "radiation")


@pytest.mark.slow
def test_a_fit_whose_effect_grows_integrates_more_finely():
    """Fitted from the effect's null value (α = 0, where one substep is exact), the
    solution's α needs more: the fit solves again from it with more substeps, and the
    model it returns simulates within the tolerance of the generator at the truth."""
    name = "conductance_temperature"
    case = g.load_case(name)
    truth = _truth_spec(case)
    spec = truth.replace(effects=tuple(
        dataclasses.replace(e, parameters={k: dataclasses.replace(p, value=0.0)
                                           for k, p in e.parameters.items()})
        for e in truth.effects))
    runs = g.generate_case(name, seed=0, horizon_s=HORIZON_S)
    ts, cols = runs[0]
    inputs = [c for c in lower_effects(spec).spec.input_columns]
    u = np.stack([cols[c] for c in inputs], 1)
    y = np.stack([cols[c] for c in spec.sensor_columns], 1)
    said = []
    # a fresh memory of substeps: an earlier fit of this structure in the same worker
    # (whichever test xdist ran before) would otherwise start this one at its count
    from thermojax.fitting._integration import substep_memory

    with substep_memory({}):
        result = fit(spec, [Experiment(ts, u, y)], progress=said.append)
    fitted = result.state.model.etd2_substeps
    assert fitted > 1 and any("solving again" in m for m in said), said
    assert fit_report(result, ["run0.csv"])["etd2_substeps"] == fitted
    _, data, reference = _case(name)
    model = ThermalModel.from_spec(truth)
    assert _true_error(model, fitted, data, reference) <= integration_tolerance([0.01])
    alpha = next(v["value"] for k, v in result.parameters.items() if k.endswith("alpha"))
    true_alpha = next(p.value for e in truth.effects for k, p in e.parameters.items())
    assert alpha == pytest.approx(true_alpha, rel=0.1)


@pytest.mark.slow
def test_a_kalman_fit_whose_effect_grows_integrates_more_finely(monkeypatch):
    """The same under the Kalman likelihood: from α = 0 one substep is exact, the
    solution's α needs more by the likelihood's own rule (at `TIGHT`), and the fit solves
    again from it; the returned model's −log L is within `KALMAN_TOLERANCE` of the filter's in 256
    substeps there, and α is recovered."""
    from thermojax.fitting import _integration
    from thermojax.fitting._integration import substep_memory

    monkeypatch.setattr(_integration, "KALMAN_TOLERANCE", TIGHT)
    name = "conductance_temperature"
    truth = _truth_spec(g.load_case(name))
    spec = truth.replace(effects=tuple(
        dataclasses.replace(e, parameters={k: dataclasses.replace(p, value=0.0)
                                           for k, p in e.parameters.items()})
        for e in truth.effects))
    ts, cols = g.generate_case(name, seed=0, horizon_s=HORIZON_S)[0]
    u = np.stack([cols[c] for c in lower_effects(spec).spec.input_columns], 1)
    y = np.stack([cols[c] for c in spec.sensor_columns], 1)
    said = []
    with substep_memory({}):
        result = fit(spec, [Experiment(ts, u, y)], likelihood="kalman",
                     progress=said.append)
    fitted = result.state.model.etd2_substeps
    assert fitted > 1 and any("solving again" in m for m in said), said
    _assert_converged_at_truth(result, y, truth)


def test_fits_of_one_structure_share_the_most_substeps_any_needed():
    """A structure that needed 8 substeps keeps 8 for its later fits (one compiled
    program); another structure is not affected; the model's values do not matter."""
    from thermojax.fitting import _integration

    strong = ThermalModel.from_spec(_truth_spec(g.load_case("conductance_temperature")))
    mild = ThermalModel.from_spec(_truth_spec(g.load_case("radiation")))
    with _integration.substep_memory({}):
        assert _integration.shared_substeps(strong, 8) == 8
        other_values = jax.tree.map(lambda x: x * 1.1, strong)
        assert _integration.shared_substeps(other_values, 1) == 8
        assert _integration.shared_substeps(mild, 1) == 1
        assert _integration.shared_substeps(strong, 16) == 16
        # Kalman fits keep their own memory; a start's need is used, not remembered
        assert _integration.shared_substeps(strong, 2, kalman=True) == 2
        assert _integration.shared_substeps(strong, 16, kalman=True, remember=False) == 16
        assert _integration.shared_substeps(strong, 1, kalman=True) == 2
        assert _integration.shared_substeps(strong, 1) == 16


@pytest.mark.parametrize("cpus", [1, 4])
def test_fits_side_by_side_start_from_one_memory_and_keep_the_most(monkeypatch, cpus):
    """Fits run side by side each see the memory as it was before any ran (so their
    answers do not depend on threads), and the most each needed is kept after."""
    import os

    from thermojax.fitting import _integration
    from thermojax.fitting._side_by_side import side_by_side

    monkeypatch.setattr(os, "cpu_count", lambda: cpus)
    strong = ThermalModel.from_spec(_truth_spec(g.load_case("conductance_temperature")))
    mild = ThermalModel.from_spec(_truth_spec(g.load_case("radiation")))

    def fit_needing(model, substeps):
        return lambda: _integration.shared_substeps(model, substeps)

    with _integration.substep_memory({}):
        _integration.shared_substeps(mild, 2)
        got = side_by_side([fit_needing(strong, 4), fit_needing(strong, 2),
                            fit_needing(mild, 1), fit_needing(strong, 1)])
        assert got == [4, 2, 2, 1]
        assert _integration.shared_substeps(strong, 1) == 4
        assert _integration.shared_substeps(mild, 1) == 2
        with pytest.raises(ValueError, match="second"):  # raised after all finished
            side_by_side([fit_needing(strong, 8), lambda: int("second"),
                          fit_needing(mild, 16)])
        assert _integration.shared_substeps(mild, 1) == 16


@pytest.mark.slow
def test_a_kalman_fit_started_far_from_the_data_starts_coarse(monkeypatch):
    """A start whose filter needs 8 substeps (α three times the truth, at `TIGHT`) is
    solved first in `START_SUBSTEPS` (a solve in 8 costs twice as much a call); the
    solution's own need decides the rest: the returned −log L is within `KALMAN_TOLERANCE` of the
    filter's in 256 substeps, and α is recovered."""
    import jax.numpy as jnp

    from thermojax.fitting import _integration, _kalman_fit

    monkeypatch.setattr(_integration, "KALMAN_TOLERANCE", TIGHT)
    name = "conductance_temperature"
    truth = _truth_spec(g.load_case(name))
    spec = truth.replace(effects=tuple(
        dataclasses.replace(e, parameters={k: dataclasses.replace(p, value=3 * p.value)
                                           for k, p in e.parameters.items()})
        for e in truth.effects))
    _, data, reference = _case(name, noise=True)
    data = dataclasses.replace(data, outputs=jnp.asarray(reference)[None])
    start = FitState(ThermalModel.from_spec(spec), np.zeros((1, 0)), np.zeros(0))
    assert fewest_kalman_substeps(start, data)[0] > _kalman_fit.START_SUBSTEPS
    solved_in = []
    solve = _kalman_fit._fit_kalman_from

    def spy(prep, template, *args, **kwargs):
        solved_in.append(template.model.etd2_substeps)
        return solve(prep, template, *args, **kwargs)

    monkeypatch.setattr(_kalman_fit, "_fit_kalman_from", spy)
    result, y = _kalman_fit_of_case(name, spec)
    assert solved_in[0] == _kalman_fit.START_SUBSTEPS
    _assert_converged_at_truth(result, y, truth)


@pytest.mark.slow
def test_a_kalman_fit_polishes_only_in_the_substeps_it_returns(monkeypatch):
    """A solve whose end (after its boundary check) needs more substeps than it was made
    in is not polished there (`_Unpolished`): it is solved again in more, and the polish
    runs in the count the solution is returned in. Started in one substep (the truth's
    filter needs more), the fit still ends within `KALMAN_TOLERANCE` of the filter in
    256 substeps, α recovered (the rule at `TIGHT`)."""
    from thermojax.fitting import _integration, _kalman_fit

    monkeypatch.setattr(_integration, "KALMAN_TOLERANCE", TIGHT)
    name = "conductance_temperature"
    truth = _truth_spec(g.load_case(name))
    _, data, reference = _case(name, noise=True)
    start = FitState(ThermalModel.from_spec(truth), np.zeros((1, 0)), np.zeros(0))
    assert fewest_kalman_substeps(start, data)[0] > 1
    solved_in, polished_in = [], []
    solve, polish = _kalman_fit._fit_kalman_from, _kalman_fit._polish

    def solve_spy(prep, template, *args, **kwargs):
        solved_in.append(template.model.etd2_substeps)
        return solve(prep, template, *args, **kwargs)

    def polish_spy(theta, problem, *args, **kwargs):
        polished_in.append(problem.template.model.etd2_substeps)
        return polish(theta, problem, *args, **kwargs)

    monkeypatch.setattr(_kalman_fit, "START_SUBSTEPS", 1)
    monkeypatch.setattr(_kalman_fit, "_fit_kalman_from", solve_spy)
    monkeypatch.setattr(_kalman_fit, "_polish", polish_spy)
    result, y = _kalman_fit_of_case(name, truth)
    assert solved_in[0] == 1 and len(solved_in) > 1 and polished_in
    assert set(polished_in) == {solved_in[-1]} == {result.state.model.etd2_substeps}
    _assert_converged_at_truth(result, y, truth)


def _kalman_fit_of_case(name: str, spec):
    """`(Kalman fit of spec, readings (T, sensors))` on generated case `name`'s noisy run,
    with no substeps remembered from earlier fits."""
    from thermojax.fitting._integration import substep_memory

    ts, cols = g.generate_case(name, seed=0, horizon_s=HORIZON_S, noise=True)[0]
    u = np.stack([cols[c] for c in lower_effects(spec).spec.input_columns], 1)
    y = np.stack([cols[c] for c in spec.sensor_columns], 1)
    with substep_memory({}):
        return fit(spec, [Experiment(ts, u, y)], likelihood="kalman"), y


def _assert_converged_at_truth(result, y, truth):
    """The Kalman fit `result` of readings `y` (T, sensors): its −log L within
    `KALMAN_TOLERANCE` of the filter's in 256 substeps at its solution, and the truth's α
    recovered."""
    import jax.numpy as jnp

    data = dataclasses.replace(result.problem.data, outputs=jnp.asarray(y)[None])
    fine = float(kalman_nll_in_substeps(result.state.model, data, result.state.run_initial,
                                        jax.device_put(np.asarray(256))))
    assert abs(result.nll - fine) <= KALMAN_TOLERANCE
    alpha = next(v["value"] for k, v in result.parameters.items() if k.endswith("alpha"))
    true_alpha = next(p.value for e in truth.effects for k, p in e.parameters.items())
    assert alpha == pytest.approx(true_alpha, rel=0.1)
