"""The Kalman likelihood (`kalman_run`, `kalman_nll`) and the RTS smoother against NumPy.

The reference is the continuous-discrete Kalman filter of `helpers.np_kalman`, plain
NumPy from the definition in formats spec §2 ("Likelihood"):

- matrices from the TOML file read by `tomllib` (`helpers.model_matrices`), never
  through `ThermalNetwork`;
- exact sampling by `scipy.linalg.expm` of the augmented matrix (FOH and ZOH);
- `Qd = ∫ e^{As} Qc e^{Aᵀs} ds` by `scipy.integrate.quad_vec` (Van Loan's integral);
- update before predict, every measured sample included (the first one too),
  `log L = Σ_k −½ (log det(2π S_k) + e_kᵀ S_k⁻¹ e_k)` over the measured rows only;
- the textbook covariance update `P − K S Kᵀ` (thermojax writes it as `P − UᵀU`,
  `U = L⁻¹ C P`: the same matrix in exact arithmetic).

The RTS smoother reference is the textbook backward pass. The information criteria
of a Kalman fit are checked against the formulas of spec §2 with `n_params` and `N`
counted by hand.
"""

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import thermojax as tj
from thermojax.measurements._data import Dataset, Experiment
from thermojax.fitting._kalman_fit import standardized_innovations
from thermojax.fitting._likelihood import kalman_nll, kalman_run, rts_smoother
from thermojax.model._model import ThermalModel

from helpers import (CONFIGS, model_matrices, np_kalman, np_simulate, np_steady, np_van_loan,
                     rtd2h_kalman_fit)

# float64 throughout; the reference's quad_vec Van Loan integral is good to ~1e-12
# relative, and the two filters differ only by roundoff in a few hundred steps.
RTOL = 1e-9


# ---------------------------------------------------------------------------------------------
# The independent reference


def np_rts(ref):
    """Textbook Rauch-Tung-Striebel backward pass over `np_kalman`'s output."""
    Phi = ref["Phi"]
    m_s, P_s = ref["m_filt"].copy(), ref["P_filt"].copy()
    for k in range(len(m_s) - 2, -1, -1):
        G = ref["P_filt"][k] @ Phi.T @ np.linalg.inv(ref["P_pred"][k + 1])
        m_s[k] = ref["m_filt"][k] + G @ (m_s[k + 1] - ref["m_pred"][k + 1])
        P_s[k] = ref["P_filt"][k] + G @ (P_s[k + 1] - ref["P_pred"][k + 1]) @ G.T
    return m_s, np.sqrt(np.diagonal(P_s, axis1=1, axis2=2))


# ---------------------------------------------------------------------------------------------
# Models and data


def imu6_text(q=0.002, hold="zoh", initial=None, initial_std=None):
    """configs/imu6.toml with process noise on every node, the power's hold, and optionally
    an initial temperature (a TOML value, e.g. "{ value = 30.0, fixed = true }") and an
    initial std on the housing."""
    text = (CONFIGS / "imu6.toml").read_text().replace('hold = "zoh"', f'hold = "{hold}"')
    lines = []
    for line in text.splitlines():
        lines.append(line)
        if line.startswith("capacitance = "):
            lines.append(f"process_noise = {q}")
        if line == 'name = "housing"':
            if initial is not None:
                lines.append(f"initial = {initial}")
            if initial_std is not None:
                lines.append(f"initial_std = {initial_std}")
    return "\n".join(lines) + "\n"


RTD2_TEXT = """
name = "rtd2q"
[[nodes]]
name = "sheath"
capacitance = 0.8
process_noise = 0.003
initial_std = 0.3
[[nodes]]
name = "core"
capacitance = 0.1
process_noise = 0.001
[[links]]
between = ["sheath", "core"]
conductance = 0.08333333333333333
[[boundaries]]
node = "sheath"
input = "T_fluid"
conductance = 0.2
[[sensors]]
node = "core"
column = "T_core"
noise = 0.01
"""


def load(tmp_path, text, name="model.toml"):
    """(spec, ThermalModel, reference matrices) of a model file written from `text`."""
    path = tmp_path / name
    path.write_text(text)
    spec = tj.load_model(path)
    return spec, ThermalModel.from_spec(spec), model_matrices(path)


def chamber_inputs(mm, n, dt, seed):
    """A chamber ramp plus a random heater square wave (for models with a power input)."""
    rng = np.random.default_rng(seed)
    ts = dt * np.arange(n)
    cols = []
    for name in mm["input_names"]:
        if name.startswith("T_"):
            cols.append(22.0 + 8.0 * np.sin(2 * np.pi * ts / 240.0) + 0.01 * ts)
        else:
            cols.append(np.repeat(0.2 * rng.integers(0, 2, n // 7 + 1), 7)[:n])
    return ts, np.stack(cols, axis=1)


def noisy_outputs(mm, U, dt, x0, seed, q_scale=1.0):
    """Outputs of an independent stochastic NumPy simulation, with sensor noise."""
    rng = np.random.default_rng(seed)
    Qd = np_van_loan(mm["A"], np.diag((q_scale * mm["q"]) ** 2), dt)
    _, Y = np_simulate(mm["A"], mm["B"], mm["Cy"], x0, U, dt, mm["holds"], Qd=Qd, rng=rng)
    return Y + rng.standard_normal(Y.shape) * mm["noise"]


def run_filter(model, ts, U, Y, run_initial=None):
    """thermojax's filter on one run (NaN cells -> mask False, value 0, as `Dataset` does)."""
    mask = np.isfinite(Y)
    return kalman_run(model, jnp.asarray(ts), jnp.asarray(U), jnp.asarray(np.where(mask, Y, 0.0)),
                      jnp.asarray(mask), None if run_initial is None else jnp.asarray(run_initial))


def assert_filter_matches(kf, ref):
    assert float(kf.nll) == pytest.approx(ref["nll"], rel=RTOL)
    for key in ("m_filt", "m_pred"):  # °C, ~20: roundoff only
        np.testing.assert_allclose(np.asarray(getattr(kf, key)), ref[key], rtol=RTOL, atol=1e-9)
    for key in ("P_filt", "P_pred"):  # covariances: relative to their own scale
        scale = np.max(np.abs(ref[key]))
        np.testing.assert_allclose(np.asarray(getattr(kf, key)), ref[key], rtol=1e-7,
                                   atol=1e-9 * scale)
    np.testing.assert_allclose(np.asarray(kf.innovations), ref["innovations"], rtol=1e-7,
                               atol=1e-9)  # residuals of ~1e-2 °C: 1e-9 °C is roundoff
    np.testing.assert_allclose(np.asarray(kf.innovation_std), ref["innovation_std"], rtol=1e-8,
                               atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Tests


def test_reference_filter_is_the_gaussian_likelihood(tmp_path):
    """Sanity of the reference itself: with Qd = 0 and a nearly exact initial state, the
    Kalman log-likelihood is the Gaussian density of the output-error residuals."""
    text = RTD2_TEXT.replace("process_noise = 0.003", "process_noise = 0.0").replace(
        "process_noise = 0.001", "process_noise = 0.0").replace("initial_std = 0.3",
                                                                "initial_std = 1e-9")
    text = text.replace('name = "core"\ncapacitance = 0.1', 'name = "core"\ncapacitance = 0.1\n'
                        'initial_std = 1e-9')
    _, _, mm = load(tmp_path, text)
    ts, U = chamber_inputs(mm, 200, 1.0, seed=0)
    x0 = np_steady(mm["A"], mm["B"], U[0])
    _, Y0 = np_simulate(mm["A"], mm["B"], mm["Cy"], x0, U, 1.0, mm["holds"])
    Y = Y0 + np.random.default_rng(1).standard_normal(Y0.shape) * 0.01
    ref = np_kalman(mm, U, Y, 1.0, x0)
    e = (Y - Y0)[:, 0]
    gauss = 0.5 * np.sum(np.log(2 * np.pi * 0.01 ** 2) + e ** 2 / 0.01 ** 2)
    assert ref["nll"] == pytest.approx(gauss, rel=1e-9)  # P stays ~1e-18: exact to roundoff


@pytest.mark.parametrize("dt", [1.0, 2.0])
def test_rtd2_filter_matches_numpy(tmp_path, dt):
    """One sensor, FOH chamber input, steady initial state, a few dropped samples."""
    _, model, mm = load(tmp_path, RTD2_TEXT)
    ts, U = chamber_inputs(mm, 300, dt, seed=2)
    x0 = np_steady(mm["A"], mm["B"], U[0])
    Y = noisy_outputs(mm, U, dt, x0 + 0.05, seed=3)
    Y[[0, 17, 18, 19, 150, 299]] = np.nan  # first and last sample dropped too
    assert_filter_matches(run_filter(model, ts, U, Y), np_kalman(mm, U, Y, dt, x0))


@pytest.mark.parametrize("hold", ["zoh", "foh"])
def test_imu6_three_sensors_partial_missing(tmp_path, hold):
    """Six nodes, three sensors; rows with one, two or all three sensors dropped; the heater
    power held as ZOH or FOH; the housing's initial temperature and std given."""
    text = imu6_text(q=0.002, hold=hold, initial="{ value = 30.0, fixed = true }",
                     initial_std=0.5)
    _, model, mm = load(tmp_path, text)
    ts, U = chamber_inputs(mm, 400, 1.0, seed=4)
    x0 = np_steady(mm["A"], mm["B"], U[0])
    x0[mm["names"].index("housing")] = 30.0
    Y = noisy_outputs(mm, U, 1.0, x0, seed=5)
    rng = np.random.default_rng(6)
    Y[rng.random(Y.shape) < 0.2] = np.nan  # ~20 % per sensor, independently
    Y[[0, 50, 51, 300]] = np.nan  # whole rows, the first included
    Y[1, :2] = np.nan
    assert np.isnan(Y).all(axis=1).sum() >= 4 and (np.isnan(Y).sum(axis=1) == 1).sum() > 50
    kf = run_filter(model, ts, U, Y)
    ref = np_kalman(mm, U, Y, 1.0, x0)
    assert_filter_matches(kf, ref)
    # A dropped row adds nothing: its innovation and innovation std are reported as zero.
    assert np.all(np.asarray(kf.innovations)[np.isnan(Y)] == 0.0)


def test_holds_change_the_likelihood(tmp_path):
    """Guard for the hold test above: ZOH and FOH give different filters on this data (so
    matching the reference in both cases checks both discretizations)."""
    _, m_zoh, mm = load(tmp_path, imu6_text(hold="zoh"), "zoh.toml")
    _, m_foh, _ = load(tmp_path, imu6_text(hold="foh"), "foh.toml")
    ts, U = chamber_inputs(mm, 100, 1.0, seed=4)
    Y = noisy_outputs(mm, U, 1.0, np_steady(mm["A"], mm["B"], U[0]), seed=5)
    a, b = float(run_filter(m_zoh, ts, U, Y).nll), float(run_filter(m_foh, ts, U, Y).nll)
    assert abs(a - b) > 1.0


def test_estimated_initial_per_run(tmp_path):
    """A bare `initial` is a per-run estimate: `run_initial` replaces it as the initial mean."""
    text = RTD2_TEXT.replace("initial_std = 0.3", "initial = 25.0\ninitial_std = 0.3")
    spec, model, mm = load(tmp_path, text)
    assert model.initial_nodes == (0,)
    ts, U = chamber_inputs(mm, 200, 1.0, seed=7)
    x0 = np_steady(mm["A"], mm["B"], U[0])
    x0[0] = 18.5
    Y = noisy_outputs(mm, U, 1.0, x0, seed=8)
    kf = run_filter(model, ts, U, Y, run_initial=np.array([18.5]))
    assert_filter_matches(kf, np_kalman(mm, U, Y, 1.0, x0))
    # Without run_initial the model's own value (25 °C) is the mean.
    x0_file = x0.copy()
    x0_file[0] = 25.0
    assert float(run_filter(model, ts, U, Y).nll) == pytest.approx(
        np_kalman(mm, U, Y, 1.0, x0_file)["nll"], rel=RTOL)


def test_kalman_nll_sums_runs_of_different_length_and_period(tmp_path):
    """`kalman_nll` over a padded `Dataset`: runs of 250 samples at 1 s and 180 at 2 s, each
    with its own initial temperature; padding must add nothing."""
    text = imu6_text(q=0.001, initial="21.0", initial_std=0.4)
    _, model, mm = load(tmp_path, text)
    i_h = mm["names"].index("housing")
    experiments, total = [], 0.0
    for n, dt, seed, t0 in [(250, 1.0, 10, 23.0), (180, 2.0, 11, 19.0)]:
        ts, U = chamber_inputs(mm, n, dt, seed)
        x0 = np_steady(mm["A"], mm["B"], U[0])
        x0[i_h] = t0
        Y = noisy_outputs(mm, U, dt, x0, seed + 100)
        Y[np.random.default_rng(seed).random(Y.shape) < 0.1] = np.nan
        experiments.append(Experiment(ts, U, Y, name=f"run{dt:g}"))
        total += np_kalman(mm, U, Y, dt, x0)["nll"]
    data = Dataset.from_experiments(experiments)
    got = float(kalman_nll(model, data, jnp.asarray([[23.0], [19.0]])))
    assert got == pytest.approx(total, rel=RTOL)


def test_rts_smoother_matches_numpy(tmp_path):
    """Smoothed means and stds of every node (sensed or not) against the textbook pass."""
    _, model, mm = load(tmp_path, imu6_text(q=0.003))
    ts, U = chamber_inputs(mm, 200, 2.0, seed=12)
    x0 = np_steady(mm["A"], mm["B"], U[0])
    Y = noisy_outputs(mm, U, 2.0, x0, seed=13)
    Y[np.random.default_rng(14).random(Y.shape) < 0.15] = np.nan
    kf = run_filter(model, ts, U, Y)
    ref = np_kalman(mm, U, Y, 2.0, x0)
    m_s, s_s = rts_smoother(model, jnp.asarray(ts), kf)
    m_ref, s_ref = np_rts(ref)
    np.testing.assert_allclose(np.asarray(m_s), m_ref, rtol=1e-9, atol=1e-8)  # °C roundoff
    np.testing.assert_allclose(np.asarray(s_s), s_ref, rtol=1e-6, atol=1e-10)  # via P⁻¹
    # The smoother never knows less than the filter.
    s_f = np.sqrt(np.diagonal(ref["P_filt"], axis1=1, axis2=2))
    assert np.all(np.asarray(s_s) <= s_f * (1 + 1e-9))


# ---------------------------------------------------------------------------------------------
# Information criteria of a Kalman fit (spec §2)


@pytest.fixture(scope="module")
def kalman_fit():
    return rtd2h_kalman_fit()


@pytest.mark.slow  # the Kalman fit compiles its likelihood, Hessian and smoother (~1 min)
def test_kalman_fit_information_criteria(kalman_fit):
    """aic = 2 n_params + 2 nll, bic = n_params ln N + 2 nll; n_params and N counted by hand:
    4 conductances and capacitances, 1 estimated sensor noise (T_sheath's is fixed), 2
    process noises, 2 per-run initial core temperatures; N = measured scalar samples."""
    result, experiments = kalman_fit["result"], kalman_fit["experiments"]
    n_params = 4 + 1 + 2 + 2
    N = sum(int(np.isfinite(e.outputs).sum()) for e in experiments)
    assert result.n_params == n_params
    assert result.n_samples == N
    assert result.aic == pytest.approx(2 * n_params + 2 * result.nll, rel=1e-12)
    assert result.bic == pytest.approx(n_params * math.log(N) + 2 * result.nll, rel=1e-12)


@pytest.mark.slow
def test_kalman_fit_nll_is_the_filter_likelihood(kalman_fit, tmp_path):
    """The reported -log L equals the NumPy filter run at the fitted values (read back from
    the fitted model file with tomllib; the per-run initial core temperatures from the
    report): the nll is the Kalman likelihood, without the prior. The estimated process
    noise must be in the file although the model file left it out."""
    result, experiments = kalman_fit["result"], kalman_fit["experiments"]
    path = tmp_path / "fitted.toml"
    tj.save_model(result.spec, path)
    mm = model_matrices(path)
    fitted_q = np.array([result.parameters[f"nodes.{n}.process_noise"]["value"]
                         for n in mm["names"]])
    np.testing.assert_allclose(mm["q"], fitted_q, rtol=1e-12)  # written to the file
    total = sum(ref["nll"] for ref in _numpy_filters(result, experiments, mm))
    assert result.nll == pytest.approx(total, rel=1e-9)  # roundoff; same definition


def _numpy_filters(result, experiments, mm):
    """The NumPy filter's output per run at the fitted values (`mm` from the fitted file)."""
    refs = []
    for r, e in enumerate(experiments):
        x0 = np_steady(mm["A"], mm["B"], e.inputs[0])
        x0[1] = result.parameters[f"runs.{r}.nodes.core.initial"]["value"]
        refs.append(np_kalman(mm, e.inputs, e.outputs, e.dt, x0))
    return refs


@pytest.mark.slow
def test_standardized_innovations_are_the_filters(kalman_fit, tmp_path):
    """The whiteness evidence of a Kalman fit (`standardized_innovations`, from the fit's
    last scoring call) is the NumPy filter's innovations over their std at the fitted
    values, NaN where nothing was measured."""
    result, experiments = kalman_fit["result"], kalman_fit["experiments"]
    path = tmp_path / "fitted.toml"
    tj.save_model(result.spec, path)
    got = standardized_innovations(result)
    for e, g, ref in zip(experiments, got, _numpy_filters(result, experiments,
                                                          model_matrices(path))):
        measured = np.isfinite(e.outputs)
        assert g.shape == e.outputs.shape and np.array_equal(np.isfinite(g), measured)
        want = ref["innovations"][measured] / ref["innovation_std"][measured]
        np.testing.assert_allclose(g[measured], want, rtol=1e-6, atol=1e-8)


@pytest.mark.slow
def test_cheap_and_optimized_scoring_programs_agree(kalman_fit):
    """A linear model's scoring program compiled without LLVM's optimizations (cheap
    calls: samples × states² at most `CHEAP_SCORING`) returns what the optimized one
    does, to rounding; the dispatch takes it for this small two-run model and not for
    the same model on runs too long, nor for a nonlinear model."""
    from types import SimpleNamespace

    import jax

    from thermojax.fitting import _kalman_fit as kf

    problem = kalman_fit["result"].problem
    theta = jax.device_put(np.asarray(kalman_fit["result"].theta))
    cheap, optimized = (kf._scoring_cheap(theta, problem),
                        kf._scoring_optimized(theta, problem))
    for a, b in zip(cheap, optimized):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=1e-12)
    model = problem.template.model
    n = model.network.topology.n_nodes
    assert not model.is_nonlinear and np.size(problem.data.ts) * n * n <= kf.CHEAP_SCORING
    assert kf._cheap_calls(problem)

    def like(samples, nonlinear=False):  # the problem's model on runs of `samples`
        stand_in = SimpleNamespace(network=model.network, is_nonlinear=nonlinear)
        return SimpleNamespace(template=SimpleNamespace(model=stand_in),
                               data=SimpleNamespace(ts=np.zeros((1, samples))))
    most = kf.CHEAP_SCORING // (n * n)
    assert kf._cheap_calls(like(most)) and not kf._cheap_calls(like(most + 1))
    assert not kf._cheap_calls(like(10, nonlinear=True))


@pytest.mark.slow
def test_scoring_gradient_and_information_from_their_definitions(kalman_fit):
    """The scoring program's gradient and Fisher information (`_value_grad_information`,
    forward derivatives and two matrix products) at a point off the optimum, against
    central differences in the free parameters: the gradient of its own −log L (the
    NumPy filter's value: the tests above), and the information summed in NumPy from its
    definition, `I = Σ_k ∂eᵀS⁻¹∂e + ½ tr(S⁻¹∂S S⁻¹∂S)`, with the innovations `e_k` and
    their covariances `S_k` of `kalman_run` differenced."""
    import equinox as eqx
    import jax

    from thermojax.fitting._kalman_fit import _value_grad_information
    from thermojax.fitting._likelihood import kalman_runs
    from thermojax.fitting._problem import _state

    result = kalman_fit["result"]
    problem = result.problem
    theta = np.asarray(result.theta) + 0.05 * np.sin(np.arange(result.theta.size) + 1.0)
    _, g, info, _ = (np.asarray(a) for a in _value_grad_information(jax.device_put(theta),
                                                                     problem))

    @eqx.filter_jit
    def filtered(t):
        s = _state(t, problem)
        return kalman_runs(s.model, problem.data, s.run_initial,
                           lambda ts, kf: (kf.nll, kf.innovations, kf.innovation_cov))

    h = 1e-5
    plus, minus = [], []
    for i in range(theta.size):
        step = np.zeros(theta.size)
        step[i] = h
        plus.append([np.asarray(a, float) for a in filtered(jax.device_put(theta + step))])
        minus.append([np.asarray(a, float) for a in filtered(jax.device_put(theta - step))])
    g_fd = np.array([(p[0].sum() - m[0].sum()) / (2 * h) for p, m in zip(plus, minus)])
    de = np.stack([(p[1] - m[1]) / (2 * h) for p, m in zip(plus, minus)])  # (q, runs, T, p)
    dS = np.stack([(p[2] - m[2]) / (2 * h) for p, m in zip(plus, minus)])
    _, _, S = (np.asarray(a, float) for a in filtered(jax.device_put(theta)))
    Sinv = np.linalg.inv(S)
    info_ref = np.zeros((theta.size, theta.size))
    for q in range(theta.size):
        for w in range(theta.size):
            info_ref[q, w] = (np.einsum("rti,rtij,rtj->", de[q], Sinv, de[w])
                              + 0.5 * np.einsum("rtij,rtjk,rtkl,rtli->", Sinv, dS[q], Sinv,
                                                dS[w]))
    np.testing.assert_allclose(g, g_fd, rtol=1e-5, atol=1e-5 * np.abs(g_fd).max())
    np.testing.assert_allclose(info, info_ref, rtol=1e-5, atol=1e-6 * np.abs(info_ref).max())


@pytest.mark.parametrize("chunked", [False, True])
@pytest.mark.parametrize("process_noise", ["file", "zero"])
def test_settled_covariances_are_reused_and_the_likelihood_and_its_gradient_stay_exact(
        tmp_path, monkeypatch, process_noise, chunked):
    """A linear filter's covariances settle; thermojax then reuses them (skipping the
    Riccati recursion) until a sample is missing. On a long run with a dropped sample and
    a dropped block after the settling, the filter still matches the NumPy reference, and
    the derivatives of −log L in the log noise stds (which act only through the
    covariances) match central differences of the reference. Without process noise the
    covariances decay towards zero and never settle relative to themselves: they settle
    on the sensor variance's scale. Both ways of running it: sample by sample (short runs)
    and in chunks (long runs; here the 1,500 samples, not a multiple of the chunk)."""
    import jax

    from thermojax.fitting import _likelihood

    monkeypatch.setattr(_likelihood, "_CHUNKED_FROM", 0 if chunked else 10 ** 9)

    text = RTD2_TEXT  # a 40 s sheath without process noise: its variance decays slowly
    if process_noise == "zero":
        text = text.replace("process_noise = 0.003", "process_noise = 0.0").replace(
            "process_noise = 0.001", "process_noise = 0.0").replace("capacitance = 0.8",
                                                                    "capacitance = 8.0")
    _, model, mm = load(tmp_path, text)
    n, dt = 1500, 1.0
    ts, U = chamber_inputs(mm, n, dt, seed=20)
    x0 = np_steady(mm["A"], mm["B"], U[0])
    Y = noisy_outputs(mm, U, dt, x0 + 0.05, seed=21)
    Y[[700, 1100, 1101, 1102, 1103]] = np.nan
    assert_filter_matches(run_filter(model, ts, U, Y), np_kalman(mm, U, Y, dt, x0))

    # The recursion runs while the covariances settle and after each gap: a fraction of
    # the samples. Counted by a host callback inside the recursion's branch.
    calls = []
    real = _likelihood._update

    def counted(*args):
        jax.debug.callback(lambda: calls.append(1))
        return real(*args)

    _likelihood._update = counted
    try:
        jax.block_until_ready(run_filter(model, ts, U, Y).nll)
    finally:
        _likelihood._update = real
    # (a rule relative to P alone ran the recursion at 1406 of the 1500 samples)
    assert 0 < len(calls) < (n // 3 if process_noise == "file" else n // 2), len(calls)

    mask = np.isfinite(Y)
    args = (jnp.asarray(ts), jnp.asarray(U), jnp.asarray(np.where(mask, Y, 0.0)),
            jnp.asarray(mask))

    def nll_at(log_noise, log_q):
        m = eqx.tree_at(lambda m: (m.log_noise, m.log_process_noise), model,
                        (log_noise, log_q))
        return kalman_run(m, *args).nll

    grads = jax.grad(nll_at, argnums=(0, 1))(model.log_noise, model.log_process_noise)
    h = 1e-5
    for key, got in (("noise", grads[0]), ("q", grads[1])):
        for j in range(len(mm[key])):
            up, down = dict(mm), dict(mm)
            up[key] = mm[key] * np.where(np.arange(len(mm[key])) == j, np.exp(h), 1.0)
            down[key] = mm[key] * np.where(np.arange(len(mm[key])) == j, np.exp(-h), 1.0)
            fd = (np_kalman(up, U, Y, dt, x0)["nll"] - np_kalman(down, U, Y, dt, x0)["nll"]) / (
                2 * h)
            # central differences of ~1e3 with h = 1e-5: good to ~1e-6 relative
            assert float(got[j]) == pytest.approx(fd, rel=1e-5, abs=1e-4), (key, j)
