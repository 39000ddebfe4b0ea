"""`fit`: recovery of known parameters from synthetic runs, the reported evidence, bad input.

Truths, all independent of the code under test:

- the data are simulated here by a NumPy exact-hold recurrence (`scipy.linalg.expm` of the
  augmented matrix, `helpers.np_simulate`) from model files read with `tomllib`, with
  white sensor noise (and, for the Kalman likelihood, process noise drawn with a
  `quad_vec` Van Loan covariance) from fixed seeds: the true parameters, initial states
  and noise stds are known;
- `-log L`, the ML noise std, RMSE, fit % and the information criteria are recomputed
  here with NumPy from the returned predictions and the formulas of spec §2;
- the likelihood at the true parameters (NumPy) bounds the fitted one: a fit at the
  global optimum has `0 <= nll_truth - nll_fit`, and `2 (nll_truth - nll_fit)` is
  chi-square with (number of identifiable parameters) degrees of freedom.

The scenario `rtd2h` (helpers) is configs/rtd2.toml with a measured heater and a second
sensor, two runs of 600 samples at 1 s and 400 at 2 s, the core's initial temperature
estimated per run. Monte-Carlo over 48 seeds (outside the suite) gave z-scores
`(fitted - true)/std` with spread 0.9-1.1 for every parameter, so the reported standard
errors are honest and a 2-std check fails about 5 % of seeds per parameter; the seeds
here are fixed.
"""

import math
import warnings

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import thermojax.fitting._output_error as output_error_module
import thermojax.fitting._problem as problem_module
from thermojax import InputError, read_telemetry, write_telemetry
from thermojax.measurements._data import Experiment
from thermojax.fitting._fit import fit
from thermojax.fitting._problem import _check_finite

from helpers import (CONFIGS, RTD2H_CORE_OFFSET, RTD2H_NAMES, RTD2H_Q, RTD2H_TEXT, RTD2H_TRUTH,
                     imu6_fit, model_matrices, np_simulate, np_steady, rtd2h_experiments, rtd2h_inputs,
                     rtd2h_kalman_fit, rtd2h_oe_fit, rtd2h_spec, text_matrices)

IMU6_TRUTH = {
    "nodes.housing.capacitance": 14.20, "nodes.bulkhead.capacitance": 6.85,
    "nodes.pcb.capacitance": 2.10, "nodes.asic.capacitance": 0.08,
    "links.housing-bulkhead.conductance": 0.5, "links.bulkhead-pcb.conductance": 0.1,
    "links.pcb-asic.conductance": 0.02, "links.pcb-mems.conductance": 0.01,
    "links.asic-mems.conductance": 0.005, "boundaries.housing-T_chamber.conductance": 0.08,
}


@pytest.fixture(scope="module")
def oe():
    return rtd2h_oe_fit()


@pytest.fixture(scope="module")
def kalman():
    return rtd2h_kalman_fit()


def within(p: dict, true: float, k: float = 2.0) -> bool:
    return p["std"] is not None and abs(p["value"] - true) <= k * p["std"]


def gaussian_nll(residuals: list[np.ndarray], sigma: np.ndarray) -> float:
    """Spec §2 output error: Σ_j [N_j/2 log(2π σ_j²) + SSR_j/(2σ_j²)] over measured cells."""
    r = np.concatenate(residuals)
    ok = np.isfinite(r)
    n, ssr = ok.sum(axis=0), (np.where(ok, r, 0.0) ** 2).sum(axis=0)
    return float(np.sum(0.5 * n * np.log(2 * np.pi * sigma ** 2) + 0.5 * ssr / sigma ** 2))


# ---------------------------------------------------------------------------------------------
# Output error on rtd2h: two runs, different lengths and sample periods


def test_output_error_recovers_parameters(oe):
    """Every capacitance and conductance within two reported standard errors of the truth."""
    result = oe["result"]
    assert result.converged and result.identifiability.ok
    for name, true in RTD2H_TRUTH.items():
        p = result.parameters[name]
        assert p["free"] and within(p, true), (name, p, true)
        assert p["std"] < 0.05 * true  # and they are determined (a few % here)


def test_each_run_has_its_own_initial_state(oe):
    """Parameters shared, one estimated core temperature per run: +3 and -2 °C off the
    steady state, recovered within two standard errors."""
    result = oe["result"]
    for r, (_, _, _, x0, _) in enumerate(oe["truth"]):
        p = result.parameters[f"runs.{r}.nodes.core.initial"]
        assert within(p, x0[1]), (r, p, x0)
    assert RTD2H_CORE_OFFSET[0] != RTD2H_CORE_OFFSET[1]


def test_predictions_track_the_noise_free_truth(oe):
    """The free-run predictions of each run (its own length) follow the noise-free true
    outputs far closer than the sensor noise."""
    mm = text_matrices(RTD2H_TEXT)
    for pred, (ts, U, _, x0, _) in zip(oe["result"].predictions, oe["truth"]):
        assert pred.shape == (len(ts), 2)
        _, y_true = np_simulate(mm["A"], mm["B"], mm["Cy"], x0, U, ts[1] - ts[0], mm["holds"])
        err = np.sqrt(np.mean((pred - y_true) ** 2, axis=0))
        assert np.all(err < 0.2 * mm["noise"]), err  # parameter error only: ~0.1 x noise


def test_noise_std_estimate(oe):
    """The estimated T_core noise std is the truth (0.01 °C) within 2 std and a few %;
    its std is σ/√(2N) (ML, N counted here)."""
    result, experiments = oe["result"], oe["experiments"]
    p = result.parameters["sensors.T_core.noise"]
    n = sum(int(np.isfinite(e.outputs[:, 0]).sum()) for e in experiments)
    assert p["std"] == pytest.approx(p["value"] / math.sqrt(2 * n), rel=1e-9)
    assert within(p, 0.01)
    assert p["value"] == pytest.approx(0.01, rel=0.05)  # 2 std = 4.5 % with N = 1000


def test_fixed_parameters_stay_fixed(oe):
    """The fixed T_sheath noise (0.02 °C) and heater gain (1) keep their values, have no std,
    and stay fixed in the fitted model; the free ones stay free."""
    result = oe["result"]
    for name, value in [("sensors.T_sheath.noise", 0.02), ("heat_inputs.sheath-P_heater.gain", 1.0)]:
        p = result.parameters[name]
        assert p == {"value": pytest.approx(value, rel=1e-14), "std": None, "free": False}
    spec = result.spec
    assert spec.sensors[1].noise.fixed and spec.sensors[1].noise.value == pytest.approx(0.02,
                                                                                       rel=1e-14)
    assert spec.heat_inputs[0].gain.fixed and spec.heat_inputs[0].gain.value == pytest.approx(1.0)
    assert not spec.nodes[0].capacitance.fixed and not spec.sensors[0].noise.fixed
    assert set(result.free_names) == set(RTD2H_TRUTH) | {"runs.0.nodes.core.initial",
                                                        "runs.1.nodes.core.initial"}


def test_nll_is_the_gaussian_formula(oe):
    """`nll` equals the spec's Gaussian formula on the returned residuals, with each column's
    std as reported; the estimated one is the ML value sqrt(SSR/N) of those residuals."""
    result, experiments = oe["result"], oe["experiments"]
    res = [e.outputs - p for e, p in zip(experiments, result.predictions)]
    r = np.concatenate(res)[:, 0]
    assert result.parameters["sensors.T_core.noise"]["value"] == pytest.approx(
        np.sqrt(np.mean(r ** 2)), rel=1e-9)  # ML std, same residuals: roundoff
    sigma = np.array([result.parameters["sensors.T_core.noise"]["value"], 0.02])
    assert result.nll == pytest.approx(gaussian_nll(res, sigma), rel=1e-10)


def test_rmse_and_fit_percent(oe):
    """Pooled and per-run RMSE and fit % (MATLAB `compare`) recomputed with NumPy."""
    result, experiments = oe["result"], oe["experiments"]
    y = np.concatenate([e.outputs for e in experiments])
    p = np.concatenate(result.predictions)
    for j, col in enumerate(["T_core", "T_sheath"]):
        e = y[:, j] - p[:, j]
        assert result.rmse[col] == pytest.approx(np.sqrt(np.mean(e ** 2)), rel=1e-12)
        fp = 100 * (1 - np.linalg.norm(e) / np.linalg.norm(y[:, j] - y[:, j].mean()))
        assert result.fit_percent[col] == pytest.approx(fp, rel=1e-12)
        for run, exp, pred in zip(result.per_run, experiments, result.predictions):
            e_r = exp.outputs[:, j] - pred[:, j]
            assert run["rmse"][col] == pytest.approx(np.sqrt(np.mean(e_r ** 2)), rel=1e-12)
    # With parameters this good the residuals are the sensor noise.
    assert result.rmse["T_sheath"] == pytest.approx(0.02, rel=0.1)


def test_information_criteria(oe):
    """aic = 2k + 2 nll and bic = k ln N + 2 nll, k = 4 physical + 2 initial + 1 noise and
    N the measured scalar samples, counted here."""
    result, experiments = oe["result"], oe["experiments"]
    k, N = 7, sum(int(np.isfinite(e.outputs).sum()) for e in experiments)
    assert (result.n_params, result.n_samples) == (k, N)
    assert result.aic == pytest.approx(2 * k + 2 * result.nll, rel=1e-12)
    assert result.bic == pytest.approx(k * math.log(N) + 2 * result.nll, rel=1e-12)


def test_fit_reaches_the_global_optimum(oe):
    """The likelihood at the true parameters (NumPy, ML noise std for T_core) is no better
    than the fit's, and worse by no more than chance allows: 2Δ ~ chi-square(7)."""
    result = oe["result"]
    mm = text_matrices(RTD2H_TEXT)
    res = []
    for ts, U, Y, x0, _ in oe["truth"]:
        _, y_true = np_simulate(mm["A"], mm["B"], mm["Cy"], x0, U, ts[1] - ts[0], mm["holds"])
        res.append(Y - y_true)
    r0 = np.concatenate(res)[:, 0]
    nll_truth = gaussian_nll(res, np.array([np.sqrt(np.mean(r0 ** 2)), 0.02]))
    delta = nll_truth - result.nll
    assert -1e-6 <= delta <= 0.5 * scipy.stats.chi2.ppf(0.999, 7), delta


def test_multistart_is_at_least_as_good(oe):
    """Three starts (the first the file's values) never end worse than one."""
    one = oe["result"]
    three = fit(rtd2h_spec(), oe["experiments"], n_starts=3, seed=5)
    assert three.nll <= one.nll + 1e-6
    for name, true in RTD2H_TRUTH.items():
        assert within(three.parameters[name], true)


# ---------------------------------------------------------------------------------------------
# Kalman likelihood on data with process noise


@pytest.mark.slow  # compiles the Kalman likelihood, its Hessian and the smoother (~1 min)
def test_kalman_recovers_parameters(kalman):
    """Physics, the T_core noise std and the sheath's process noise within 2 std of the truth
    that simulated the data (process noise 0.004 and 0.002 °C/√s)."""
    result = kalman["result"]
    assert result.likelihood == "kalman" and result.converged
    for name, true in RTD2H_TRUTH.items():
        assert within(result.parameters[name], true), (name, result.parameters[name], true)
    assert within(result.parameters["sensors.T_core.noise"], 0.01)
    assert within(result.parameters["nodes.sheath.process_noise"], RTD2H_Q[0])
    # The core's diffusion (0.002) is under the noise of both sensors at 1-2 s: either
    # flagged (std None) or consistent with the truth.
    p = result.parameters["nodes.core.process_noise"]
    assert p["std"] is None or within(p, RTD2H_Q[1])
    assert result.parameters["sensors.T_sheath.noise"] == {
        "value": pytest.approx(0.02, rel=1e-14), "std": None, "free": False}


@pytest.mark.slow
def test_kalman_smoothed_states(kalman):
    """The RTS-smoothed node temperatures follow the true states of the stochastic
    simulation (both nodes, the core's per-run initial offset included): the errors
    divided by the reported smoothed stds have mean square about 1."""
    result = kalman["result"]
    for (mean, std), (ts, _, _, _, X) in zip(result.smoothed, kalman["truth"]):
        assert mean.shape == std.shape == X.shape == (len(ts), 2)
        z = (mean - X) / std
        # ~1 if mean and std are right; with 400-600 correlated samples per node the
        # sample mean square scatters by ~±0.3 (and the parameters are estimates).
        assert 0.5 < np.mean(z[5:] ** 2) < 2.0, np.mean(z[5:] ** 2, axis=0)
        assert np.all(std > 0) and np.all(std < 0.02)  # never less certain than one reading


def test_max_steps_stops_the_default_solver(oe):
    """`max_steps=1` allows each output-error pass one Jacobian evaluation and no step:
    the fit stays at the file's values and reports that it did not converge."""
    result = fit(rtd2h_spec(), oe["experiments"], max_steps=1)
    assert not result.converged and result.message.startswith("stopped after")
    assert result.n_steps <= 4  # one evaluation per re-weighting pass, at most 4 passes
    for name, value in (("nodes.sheath.capacitance", 0.8), ("nodes.core.capacitance", 0.1),
                        ("boundaries.sheath-T_fluid.conductance", 0.2)):
        assert result.parameters[name]["value"] == pytest.approx(value, rel=1e-12)


@pytest.mark.slow  # compiles an optimistix least-squares solve
def test_max_steps_stops_an_optimistix_solver(oe):
    """`max_steps` reaches a user-supplied optimistix solver: one step is not enough."""
    import optimistix as optx

    result = fit(rtd2h_spec(), oe["experiments"],
                 solver=optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10), max_steps=1)
    assert not result.converged and result.n_steps <= 4


@pytest.mark.slow  # reuses the Kalman compilation of `kalman`
def test_max_steps_stops_the_kalman_solver(kalman):
    """`max_steps=1`: the Kalman stage takes a single Newton step and reports it."""
    result = fit(rtd2h_spec(), kalman["experiments"], likelihood="kalman", max_steps=1)
    assert not result.converged and result.n_steps == 1



@pytest.mark.slow  # reuses the Kalman compilation of `kalman`
def test_an_unconverged_kalman_fit_is_restarted_unless_told_not_to(kalman, monkeypatch):
    """A Kalman fit from the file's values that does not converge is fitted again from
    the output-error fit; with `restart_unconverged=False` it is the answer as it is."""
    import thermojax.fitting._fit as fit_module

    calls = []
    real = fit_module.fit_output_error
    monkeypatch.setattr(fit_module, "fit_output_error",
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    alone = fit(rtd2h_spec(), kalman["experiments"], likelihood="kalman", max_steps=1,
                restart_unconverged=False)
    assert not alone.converged and alone.n_steps == 1 and calls == []
    fit(rtd2h_spec(), kalman["experiments"], likelihood="kalman", max_steps=1)
    assert calls == [1]


# ---------------------------------------------------------------------------------------------
# Six-node IMU, started 3x off


@pytest.mark.slow  # compiles a 6-node fit (~30-60 s on two cores)
def test_imu6_converges_from_three_times_off():
    """Every free C and G started a factor 3 off (alternately up and down) converges:
    every parameter the data determine is within 2 std of the truth; the MEMS die and the
    proof mass (τ ≈ 0.1 s, between 1 s samples) are seen as one mass, whose sum is within
    2 std; the noise stds are the truth within a few %; and the likelihood is at least as
    good as the truth's (NumPy) and no better than chance allows."""
    fitted = imu6_fit()
    result, start = fitted["result"], fitted["start"]
    assert start.nodes[0].capacitance.value == pytest.approx(3 * 14.2)
    assert result.converged
    for name, true in IMU6_TRUTH.items():
        assert within(result.parameters[name], true), (name, result.parameters[name], true)
    mems = result.parameters["nodes.mems.capacitance"]
    pm = result.parameters["nodes.proof_mass.capacitance"]
    assert abs(mems["value"] + pm["value"] - (0.05 + 0.003)) <= 2 * mems["std"]
    for col in ("T_housing", "T_pcb", "T_asic"):
        p = result.parameters[f"sensors.{col}.noise"]
        assert within(p, 0.01) and p["value"] == pytest.approx(0.01, rel=0.04)  # 2 std = 3 %
    # NumPy likelihood at the truth, each sensor's std at its ML value.
    mm = model_matrices(CONFIGS / "imu6.toml")
    res = []
    for ts, U, Y, x0 in fitted["truth"]:
        _, y_true = np_simulate(mm["A"], mm["B"], mm["Cy"], x0, U, ts[1] - ts[0], mm["holds"])
        res.append(Y - y_true)
    r = np.concatenate(res)
    nll_truth = gaussian_nll(res, np.sqrt(np.mean(r ** 2, axis=0)))
    n_ident = sum(p["std"] is not None for p in result.parameters.values() if p["free"])
    delta = nll_truth - result.nll
    assert -0.5 <= delta <= 0.5 * scipy.stats.chi2.ppf(0.999, n_ident), (delta, n_ident)
    # (-0.5: the two pinned proof-mass directions carry < 1 unit of information each.)


# ---------------------------------------------------------------------------------------------
# Bad input


def _all_fixed_text():
    return (RTD2H_TEXT.replace("capacitance = 0.8", "capacitance = { value = 0.8, fixed = true }")
            .replace("capacitance = 0.1", "capacitance = { value = 0.1, fixed = true }")
            .replace("conductance = 0.08333333333333333",
                     "conductance = { value = 0.08333333333333333, fixed = true }")
            .replace("conductance = 0.2", "conductance = { value = 0.2, fixed = true }")
            .replace("initial = 20.0", "initial = { value = 20.0, fixed = true }"))


def test_no_free_parameter():
    with pytest.raises(InputError, match="nothing to fit: every parameter is fixed"):
        fit(rtd2h_spec(_all_fixed_text()), rtd2h_experiments(1))


def test_unknown_likelihood():
    with pytest.raises(InputError, match="unknown likelihood 'ml'"):
        fit(rtd2h_spec(), rtd2h_experiments(1), likelihood="ml")


def test_no_runs():
    with pytest.raises(InputError, match="no runs given"):
        fit(rtd2h_spec(), [])


def _csv(path, ts, U, Y):
    write_telemetry(path, ts, {"T_fluid": U[:, 0], "P_heater": U[:, 1], "T_core": Y[:, 0],
                               "T_sheath": Y[:, 1]})
    return path


def test_run_without_sensor_data_from_file(tmp_path):
    """A CSV whose sensor cells are all empty: InputError naming the file and a column."""
    e = rtd2h_experiments(1)[1]
    path = _csv(tmp_path / "empty_run.csv", e.ts, e.inputs, np.full_like(e.outputs, np.nan))
    with pytest.raises(InputError, match=r"empty_run\.csv.*T_core.*no readings"):
        Experiment.from_telemetry(rtd2h_spec(), read_telemetry(path))


def test_all_nan_sensor_column_from_file(tmp_path):
    e = rtd2h_experiments(1)[1]
    Y = e.outputs.copy()
    Y[:, 1] = np.nan
    path = _csv(tmp_path / "no_sheath.csv", e.ts, e.inputs, Y)
    with pytest.raises(InputError, match=r"no_sheath\.csv.*field 'T_sheath'.*no readings"):
        Experiment.from_telemetry(rtd2h_spec(), read_telemetry(path))


def test_run_without_sensor_data_in_the_api():
    """`fit` itself refuses a run with no measured sample, naming the run and the columns."""
    runs = rtd2h_experiments(1)
    runs[1] = Experiment(runs[1].ts, runs[1].inputs, np.full_like(runs[1].outputs, np.nan),
                         name="chamber_run_7.csv")
    with pytest.raises(InputError, match=r"chamber_run_7\.csv, field 'T_core,T_sheath': no "
                                         "sensor data"):
        fit(rtd2h_spec(), runs)


def test_all_nan_sensor_column_in_the_api():
    runs = rtd2h_experiments(1)
    Y = runs[0].outputs.copy()
    Y[:, 0] = np.nan
    runs[0] = Experiment(runs[0].ts, runs[0].inputs, Y, name="chamber_run_3.csv")
    with pytest.raises(InputError, match=r"chamber_run_3\.csv, field 'T_core'.*no readings"):
        fit(rtd2h_spec(), runs)


def test_short_run_warns(oe):
    """Runs of 3 s and 4 s (600 and 400 samples at 5 and 10 ms) are shorter than the slowest
    time constant (~5.7 s): a UserWarning names each run. (Same shapes and run names as the
    main scenario, so no new compilation.)"""
    mm = text_matrices(RTD2H_TEXT)
    tau = 1 / np.min(-np.linalg.eigvals(mm["A"]).real)
    rng = np.random.default_rng(3)
    runs = []
    for i, (n, dt) in enumerate([(600, 0.005), (400, 0.01)]):
        ts, U = rtd2h_inputs(n, dt, rng)
        _, Y = np_simulate(mm["A"], mm["B"], mm["Cy"], np_steady(mm["A"], mm["B"], U[0]), U, dt,
                           mm["holds"])
        runs.append(Experiment(ts, U, Y + 0.01 * rng.standard_normal(Y.shape),
                               name=RTD2H_NAMES[i]))
        assert ts[-1] < tau
    with pytest.warns(UserWarning) as record:
        fit(rtd2h_spec(), runs)
    messages = [str(w.message) for w in record]
    for name in RTD2H_NAMES:
        assert any(m.startswith(f"{name}: the run lasts") and "shorter than the slowest time "
                   "constant" in m for m in messages), messages


def test_long_runs_do_not_warn(oe):
    """The main scenario raised no warning (filterwarnings = error would have failed it);
    checked explicitly on the cheap part: the run checks."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        problem_module._check_runs(rtd2h_spec(), oe["experiments"])


def test_check_finite_names_the_parameter():
    names = ["nodes.a.capacitance", "links.a-b.conductance", "runs.0.nodes.a.initial"]
    _check_finite(jnp.asarray([0.1, 0.2, 0.3]), jnp.zeros(3), names)  # finite: no error
    with pytest.raises(InputError, match=r"diverged: links\.a-b\.conductance ran away"):
        _check_finite(jnp.asarray([0.1, np.inf, 0.3]), jnp.zeros(3), names)
    with pytest.raises(InputError, match=r"runs\.0\.nodes\.a\.initial"):
        _check_finite(jnp.asarray([0.1, 0.2, np.nan]), jnp.zeros(3), names)


def test_diverging_fit_is_an_input_error(monkeypatch):
    """An optimizer that ends with a non-finite core capacitance (forced by a stand-in
    solver: the real one rejects non-finite steps, so no honest data set makes it diverge)
    surfaces as an InputError naming that parameter, not as NaN results."""
    real = output_error_module._solve_oe

    def runaway(theta, problem, solver, max_steps, estimated=None):
        out = real(theta, problem, solver, 1, estimated)
        return (theta.at[1].set(jnp.inf), *out[1:])

    monkeypatch.setattr(output_error_module, "_solve_oe", runaway)
    with pytest.raises(InputError, match=r"diverged: nodes\.core\.capacitance"):
        fit(rtd2h_spec(), rtd2h_experiments(1))


@pytest.mark.slow  # compiles a second Kalman problem (~40 s)
def test_kalman_with_only_noise_free():
    """A Kalman fit of a model whose physics is all fixed estimates the noise alone (this
    crashed in the output-error warm start with an empty parameter vector)."""
    spec = rtd2h_spec(_all_fixed_text())
    result = fit(spec, rtd2h_experiments(1, process_noise=True), likelihood="kalman")
    assert set(result.free_names) == {"sensors.T_core.noise", "nodes.sheath.process_noise",
                                      "nodes.core.process_noise"}
    for name, true in RTD2H_TRUTH.items():
        assert result.parameters[name]["value"] == pytest.approx(true, rel=1e-12)
    assert within(result.parameters["sensors.T_core.noise"], 0.01)


def test_profile_interval_ends_where_chi_square_rises_by_the_quantile():
    """With one free parameter the profile likelihood is the likelihood itself, so at
    each end of the 95 % interval the chi-square, recomputed here by the NumPy
    simulator, exceeds its minimum by the chi-square(1) quantile 3.84."""
    import dataclasses

    from thermojax import load_model, profile_interval
    from thermojax.model._spec import Parameter

    def fixed(entry, field):
        return dataclasses.replace(entry, **{field: Parameter(getattr(entry, field).value, True)})

    rtd2 = load_model(CONFIGS / "rtd2.toml")  # C 0.8, 0.1 J/K; G_ext 0.2, G 1/12 W/K
    g_true = rtd2.links[0].conductance.value
    spec = rtd2.replace(nodes=tuple(fixed(n, "capacitance") for n in rtd2.nodes),
                        boundaries=tuple(fixed(b, "conductance") for b in rtd2.boundaries),
                        sensors=tuple(fixed(s, "noise") for s in rtd2.sensors))
    ts = np.arange(300.0)
    u = np.interp(ts, [0, 20, 30, 300], [25, 25, 75, 75])[:, None]

    def outputs(g):
        A = np.array([[-(0.2 + g) / 0.8, g / 0.8], [g / 0.1, -g / 0.1]])
        B = np.array([[0.2 / 0.8], [0.0]])
        x0 = np_steady(A, B, u[0])
        return np_simulate(A, B, np.array([[0.0, 1.0]]), x0, u, 1.0, ("foh",))[1]

    y = outputs(g_true) + 0.01 * np.random.default_rng(4).standard_normal((len(ts), 1))
    res = fit(spec, [Experiment(ts, u, y, "step")])
    name = "links.sheath-core.conductance"
    g_hat = res.parameters[name]["value"]

    def chi2(g):
        return float(np.sum((y - outputs(g)) ** 2) / 0.01 ** 2)

    lower, upper = profile_interval(res, name)
    assert lower < g_hat < upper
    for end in (lower, upper):
        assert abs(chi2(end) - chi2(g_hat) - scipy.stats.chi2.ppf(0.95, 1)) < 0.02
