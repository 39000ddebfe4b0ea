"""Bias channels (spec §4): exact strain recursion, least-squares/τ recovery, LR scores, files.

Truths are independent of `thermojax.fitting._bias`: node temperatures are analytic
piecewise-linear ramps, the strain comes from `scipy.integrate.solve_ivp` stretch by
stretch between the ramps' knots, and one test uses the hidden-effect generator.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.integrate
import scipy.signal

from thermojax._errors import InputError
from thermojax.dynamics._lag import first_order_lag
from thermojax.fitting._bias import (BiasFit, bias_parameters, bias_to_spec, fit_bias,
                                     viscoelastic_candidate)
from thermojax.model._model_file import dump_model, parse_model
from thermojax.model._spec import Bias, Effect, Parameter

NODES = ["case", "die"]
COLUMN = "gyro_x_dph"


def ramp(ts, knots_t, knots_T):
    """Piecewise-linear temperature (°C) through the knots, and its exact slope (K/s),
    the mean of both one-sided slopes at a knot (what a central difference gives)."""
    slopes = np.concatenate([[0.0], np.diff(knots_T) / np.diff(knots_t), [0.0]])
    left = slopes[np.searchsorted(knots_t, ts, side="left")]
    right = slopes[np.searchsorted(knots_t, ts, side="right")]
    return np.interp(ts, knots_t, knots_T), 0.5 * (left + right)


def ivp_strain(ts, knots_t, knots_T, tau):
    """ε of dε/dt = (T − ε)/τ, ε(0) = T(0), integrated knot to knot (T linear in
    between; knots are sample times), DOP853 at rtol = atol = 1e-12."""
    eps = np.empty(ts.size)
    eps[0] = knots_T[0]
    for t0, t1, T0, T1 in zip(knots_t[:-1], knots_t[1:], knots_T[:-1], knots_T[1:]):
        inside = (ts > t0) & (ts <= t1)
        s = (T1 - T0) / (t1 - t0)
        sol = scipy.integrate.solve_ivp(lambda t, e: (T0 + s * (t - t0) - e) / tau, (t0, t1),
                                        [eps[ts == t0][0]], method="DOP853", t_eval=ts[inside],
                                        rtol=1e-12, atol=1e-12)
        eps[inside] = sol.y[0]
    return eps


# Two chamber-like runs, 1 Hz: die ramps 25 ↔ 85 °C at 5 °C/min (run 0) and up at
# 10 °C/min, down at 2 °C/min (run 1); the case follows on its own knots.
RUNS = [
    dict(die=([0, 1800, 2520, 4320, 5040, 6840], [25, 25, 85, 85, 25, 25]),
         case=([0, 1700, 2600, 4200, 5200, 6840], [24, 24, 80, 80, 26, 26])),
    dict(die=([0, 1200, 1560, 3360, 4860, 6600], [25, 25, 85, 85, 35, 35]),
         case=([0, 1300, 1700, 3300, 5000, 6600], [25, 25, 82, 82, 36, 36])),
]
TRUTH = dict(poly=[0.5, 0.03, 5e-4, -2e-6], gradient=0.2, rate=3.0, tau=600.0, k=0.01,
             sigma=0.02)


def make_data(k=TRUTH["k"], seed=0, missing=0.05):
    """Per run (ts, node temps (T, 2), y with NaN drops) and exact rates (T, 2)."""
    rng = np.random.default_rng(seed)
    runs, rates = [], []
    for run in RUNS:
        ts = np.arange(run["die"][0][-1] + 1, dtype=float)
        cols = [ramp(ts, np.array(run[n][0], float), np.array(run[n][1], float)) for n in NODES]
        temps = np.column_stack([T for T, _ in cols])
        dT = np.column_stack([r for _, r in cols])
        die = temps[:, 1]
        eps = ivp_strain(ts, np.array(run["die"][0], float), np.array(run["die"][1], float),
                         TRUTH["tau"])
        y = sum(c * (die - 25) ** p for p, c in enumerate(TRUTH["poly"]))
        y = y + TRUTH["gradient"] * (temps[:, 0] - die) + TRUTH["rate"] * dT[:, 1]
        y = y + k * (die - eps) + TRUTH["sigma"] * rng.standard_normal(ts.size)
        y[rng.random(ts.size) < missing] = np.nan
        runs.append((ts, temps, y))
        rates.append(dT)
    return runs, rates


BIAS = Bias(COLUMN, "die", order=3, gradients=(("case", "die"),), rates=("die",))
VISCO = Effect("viscoelastic", ("die", COLUMN),
               {"time_constant": Parameter(100.0), "k": Parameter(0.0)})


@pytest.mark.parametrize("tau", [3.0, 600.0, 5e4])
@pytest.mark.parametrize("jitter", [False, True])
def test_strain_matches_ivp(tau, jitter):
    rng = np.random.default_rng(1)
    ts = np.arange(0.0, 3001.0, 2.0)
    if jitter:  # irregular steps: the per-step branch
        ts = ts + np.concatenate([[0.0], rng.uniform(-0.4, 0.4, ts.size - 1)])
    knots_t = np.array([ts[0], ts[200], ts[380], ts[900], ts[1100], ts[-1]])
    knots_T = np.array([25.0, 25.0, 85.0, 70.0, 10.0, 10.0])
    T, _ = ramp(ts, knots_t, knots_T)
    got = first_order_lag(T, np.diff(ts), tau)  # the strain of `_bias`
    want = ivp_strain(ts, knots_t, knots_T, tau)
    # FOH recursion exact for piecewise-linear T; DOP853 at 1e-12 and float64 roundoff only
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-8)



def ramp_response(ts, slope, tau):
    """Lag of `x = slope·t` from rest at t = 0: `y = slope·τ·(u − 1 + e^{−u})`, u = t/τ,
    summed as its series `Σ_{k≥2} (−u)^k / k!` (no cancellation; u ≤ 1e-2 here)."""
    u = ts / tau
    return slope * tau * sum((-u) ** k / math.factorial(k) for k in range(2, 12))


@pytest.mark.parametrize("jitter", [False, True])
def test_lag_keeps_its_digits_when_dt_is_tiny_against_tau(jitter):
    tau, slope = 1e6, 0.5  # s, K/s: dt/τ = 1e-6
    ts = np.arange(2001.0)
    if jitter:  # irregular steps: the per-step branch
        ts = ts + np.concatenate([[0.0], np.random.default_rng(2).uniform(-0.3, 0.3, 2000)])
    want = ramp_response(ts, slope, tau)
    got = first_order_lag(slope * ts, np.diff(ts), tau)
    # series to 1e-40; what is left is 1 − β and β − a rounded (≈ 1e-16 / (dt/2τ)), ~3e-10
    np.testing.assert_allclose(got[1:], want[1:], rtol=1e-8, atol=0)
    assert got[0] == 0.0  # at rest at the first sample
    if not jitter:  # the form β = (τ/dt)(1 − a) loses four more digits here
        a = math.exp(-1.0 / tau)
        c = tau * (1 - a)
        naive = scipy.signal.lfilter([1 - c, c - a], [1.0, -a], slope * ts)
        assert np.max(np.abs(naive[1:] / want[1:] - 1)) > 1e-6


def test_lag_filters_every_column_along_time():
    rng = np.random.default_rng(3)
    x = np.cumsum(rng.standard_normal((500, 3)), axis=0)
    got = first_order_lag(x, 2.0, 30.0)
    for j in range(3):  # the same filter column by column (uniform and per-step branches)
        np.testing.assert_array_equal(got[:, j], first_order_lag(x[:, j], 2.0, 30.0))
        steps = np.full(499, 2.0)
        steps[::2] += 1e-6  # jitter far below a sample: the recursion branch
        np.testing.assert_allclose(first_order_lag(x[:, j], steps, 30.0), got[:, j],
                                   rtol=0, atol=1e-5)  # steps differ by 1e-6 s only
    assert first_order_lag(x[:1], 2.0, 30.0).shape == (1, 3)


def test_fit_recovers_truth():
    runs, rates = make_data()
    fit = fit_bias(BIAS, [VISCO], runs, NODES, node_rates=rates)
    assert fit.names == ["poly0", "poly1", "poly2", "poly3", "gradient.case-die", "rate.die",
                         "viscoelastic.die.k"]
    truth = np.array([*TRUTH["poly"], TRUTH["gradient"], TRUTH["rate"], TRUTH["k"]])
    z = (fit.coefficients - truth) / fit.std
    assert np.all(np.abs(z) < 3), z  # recovered within 3 reported std
    tau, tau_std = fit.time_constants["viscoelastic.die"]
    assert abs(tau - TRUTH["tau"]) < 3 * tau_std and tau_std < 0.1 * tau, (tau, tau_std)
    n = sum(int(np.isfinite(r).sum()) for r in fit.residuals)
    assert abs(fit.sigma - TRUTH["sigma"]) < 3 * TRUTH["sigma"] / math.sqrt(2 * n)
    assert fit.n_params == 7 + 1 + 1
    # nll is the Gaussian −log L of the reported residuals at the reported σ
    r = np.concatenate([x[np.isfinite(x)] for x in fit.residuals])
    nll = 0.5 * np.sum(r ** 2) / fit.sigma ** 2 + r.size * math.log(fit.sigma)
    nll += 0.5 * r.size * math.log(2 * math.pi)
    assert fit.nll == pytest.approx(nll, rel=1e-12)  # same formula, roundoff only
    assert fit.rmse == pytest.approx(math.sqrt(np.mean(r ** 2)), rel=1e-12)
    for (ts, _, y), pred, res in zip(runs, fit.predictions, fit.residuals):
        assert pred.shape == ts.shape
        np.testing.assert_array_equal(np.isnan(res), np.isnan(y))


def test_default_rates_and_fixed_parameters():
    runs, rates = make_data()
    # np.gradient reproduces the exact slopes of ramps on the sample grid (roundoff only)
    for (ts, temps, _), dT in zip(runs, rates):
        np.testing.assert_allclose(np.gradient(temps, ts, axis=0), dT, atol=1e-12)
    fixed = Effect("viscoelastic", ("die", COLUMN),
                   {"time_constant": Parameter(600.0, True), "k": Parameter(0.01, True)})
    bias = Bias(COLUMN, "die", order=3, gradients=(("case", "die"),), rates=("die",),
                noise=Parameter(0.02, True))
    fit = fit_bias(bias, [fixed], runs, NODES)
    assert fit.time_constants["viscoelastic.die"] == (600.0, None)
    assert fit.coefficients[-1] == 0.01 and np.isnan(fit.std[-1])
    assert fit.sigma == 0.02 and fit.n_params == 6
    params = bias_parameters(fit)
    assert params[f"effects.viscoelastic.die-{COLUMN}.time_constant"] == \
        {"value": 600.0, "std": None, "free": False}
    assert params[f"effects.viscoelastic.die-{COLUMN}.k"]["free"] is False
    assert params[f"biases.{COLUMN}.noise"] == {"value": 0.02, "std": None, "free": False}
    truth = np.array([*TRUTH["poly"], TRUTH["gradient"], TRUTH["rate"]])
    assert np.all(np.abs(fit.coefficients[:6] - truth) < 3 * fit.std[:6])


def test_candidate_likelihood_ratio():
    runs, rates = make_data()
    fit, lr = viscoelastic_candidate(BIAS, [], runs, NODES, "die", node_rates=rates)
    assert lr > 1000, lr  # a 0.5 deg/h hysteresis loop against 0.02 deg/h noise
    tau, tau_std = fit.time_constants["viscoelastic.die"]
    assert abs(tau - TRUTH["tau"]) < 3 * tau_std
    null_runs, null_rates = make_data(k=0.0, seed=3)
    _, lr0 = viscoelastic_candidate(BIAS, [], null_runs, NODES, "die", node_rates=null_rates)
    assert -1e-6 < lr0 < 10, lr0  # nested model: never worse; no effect: small


def test_generator_case():
    """The hidden-effect generator's viscoelastic truth (smooth node temperatures)."""
    sys.path.insert(0, str(Path(__file__).parent))
    from hidden import generator as g

    case = g.load_case("viscoelastic")
    runs = []
    for i in (0, 1):
        ts, inputs = g.run_inputs(case, i, seed=0)
        out, (X, names) = g.simulate_truth(case["truth"], ts, inputs,
                                           np.random.default_rng([0, i]), return_states=True)
        runs.append((ts, X[:, :3], out[COLUMN]))
    bias = Bias(COLUMN, "die", order=3)
    fit = fit_bias(bias, [Effect("viscoelastic", ("die", COLUMN),
                                 {"time_constant": Parameter(100.0), "k": Parameter(0.0)})],
                   runs, names[:3])
    tau, tau_std = fit.time_constants["viscoelastic.die"]
    truth = np.array([0.5, 0.03, 5e-4, 0.0, 0.01])
    assert np.all(np.abs(fit.coefficients - truth) < 3 * fit.std)
    assert abs(tau - 600.0) < 3 * tau_std


def test_spec_round_trip():
    runs, rates = make_data()
    fit = fit_bias(BIAS, [VISCO], runs, NODES, node_rates=rates)
    other = Effect("sensor_offset", ("T_die",), {"offset": Parameter(0.1)})
    bias, effects = bias_to_spec(BIAS, [other, VISCO], fit)
    assert bias.coefficients == tuple(float(c) for c in fit.coefficients[:6])
    assert bias.noise == Parameter(fit.sigma, False)
    assert effects[0] is other
    assert effects[1].parameters == {
        "time_constant": Parameter(fit.time_constants["viscoelastic.die"][0], False),
        "k": Parameter(float(fit.coefficients[6]), False)}
    params = bias_parameters(fit)
    assert set(params) == {f"biases.{COLUMN}.{n}" for n in fit.names[:6]} | {
        f"biases.{COLUMN}.noise", f"effects.viscoelastic.die-{COLUMN}.k",
        f"effects.viscoelastic.die-{COLUMN}.time_constant"}
    assert all(p["free"] and p["std"] > 0 for p in params.values())
    # model file: coefficients written and read back exactly
    spec = parse_model(MODEL)
    spec = spec.replace(biases=(bias,), effects=tuple(effects[1:]))
    back = parse_model(dump_model(spec))
    assert back.biases == (bias,) and back.effects == spec.effects


MODEL = """\
name = "gyro"

[[nodes]]
name = "case"
capacitance = 20.0

[[nodes]]
name = "die"
capacitance = 0.3

[[links]]
between = ["case", "die"]
conductance = 0.06

[[boundaries]]
node = "case"
input = "T_chamber"
conductance = 0.1

[[sensors]]
node = "die"
column = "T_die"

[[biases]]
column = "gyro_x_dph"
temperature = "die"
order = 1
rates = ["die"]
"""


def test_model_file_coefficients():
    spec = parse_model(MODEL + "coefficients = [0.5, 3e-2, -1]\n")
    assert spec.biases[0].coefficients == (0.5, 0.03, -1.0)
    assert parse_model(MODEL).biases[0].coefficients is None
    assert parse_model(dump_model(spec)) == spec
    with pytest.raises(InputError, match=r"line 24, field 'biases\[0\].coefficients': "
                                         r"coefficients needs 3 numbers"):
        parse_model(MODEL + "coefficients = [0.5, 0.03]\n")
    with pytest.raises(InputError, match=r"line 24, field 'biases\[0\].coefficients': "
                                         r"expected a finite number, got 'x'"):
        parse_model(MODEL + "coefficients = [0.5, 'x', 1.0]\n")
    with pytest.raises(InputError, match=r"coefficients is a list of numbers, got 0.5"):
        parse_model(MODEL + "coefficients = 0.5\n")


def test_bad_input():
    runs, _ = make_data()
    ts, temps, y = runs[1]
    bad = [runs[0], (ts, temps, np.full_like(y, np.nan))]
    with pytest.raises(InputError, match=r"field 'gyro_x_dph'.*bias column 'gyro_x_dph' has no "
                                         r"measured sample in run 1"):
        fit_bias(BIAS, [VISCO], bad, NODES)
    few = [(ts[:20], temps[:20], np.where(np.arange(20) < 5, 1.0, np.nan))]
    with pytest.raises(InputError, match=r"'gyro_x_dph' has 5 measured sample\(s\) but 9 "
                                         r"parameters to fit"):
        fit_bias(BIAS, [VISCO], few, NODES)
    with pytest.raises(ValueError, match=r"needs node 'die', but node_names are \['a', 'b'\]"):
        fit_bias(BIAS, [], runs, ["a", "b"])


def test_unidentifiable_coefficient_has_no_std():
    runs, _ = make_data()
    # a gradient between a node and itself is identically zero: no information
    bias = Bias(COLUMN, "die", order=1, gradients=(("die", "die"),))
    fit = fit_bias(bias, [], runs, NODES)
    assert np.isnan(fit.std[2]) and np.all(np.isfinite(fit.std[:2]))
    assert bias_parameters(fit)[f"biases.{COLUMN}.gradient.die-die"]["std"] is None
    assert isinstance(fit, BiasFit)


def test_prony_series_names_and_round_trip():
    """Two viscoelastic terms on one node and column: a Prony series, the second named
    with `#2` in reports, written back term by term and read again unchanged."""
    from thermojax.model._parameters_by_name import spec_parameters

    text = f"""
name = "prony"
[[nodes]]
name = "case"
capacitance = 10.0
[[nodes]]
name = "die"
capacitance = 1.0
[[links]]
between = ["case", "die"]
conductance = 0.5
[[boundaries]]
node = "case"
input = "T_chamber"
conductance = 0.2
[[sensors]]
node = "case"
column = "T_case"
[[biases]]
column = "{COLUMN}"
temperature = "die"
order = 1
[[effects]]
kind = "viscoelastic"
where = ["die", "{COLUMN}"]
time_constant = 300.0
k = 0.1
[[effects]]
kind = "viscoelastic"
where = ["die", "{COLUMN}"]
time_constant = {{ value = 3000.0, fixed = true }}
k = 0.2
"""
    spec = parse_model(text, "prony.toml")
    names = spec_parameters(spec)
    base = f"effects.viscoelastic.die-{COLUMN}"
    assert names[f"{base}.time_constant"].value == 300.0
    assert names[f"{base}#2.time_constant"].value == 3000.0
    assert names[f"{base}#2.time_constant"].fixed
    # a fit of both terms (data from the ramps above, second τ held) writes each back
    runs, rates = make_data()
    effects = list(spec.effects)
    fit = fit_bias(spec.biases[0], effects, runs, NODES, node_rates=rates)
    assert list(fit.time_constants) == ["viscoelastic.die", "viscoelastic.die#2"]
    assert fit.time_constants["viscoelastic.die#2"] == (3000.0, None)
    params = bias_parameters(fit)
    assert {f"{base}.k", f"{base}#2.k", f"{base}.time_constant",
            f"{base}#2.time_constant"} <= set(params)
    bias, new_effects = bias_to_spec(spec.biases[0], effects, fit)
    ks = [e.parameters["k"].value for e in new_effects]
    assert ks == [pytest.approx(v) for v in (params[f"{base}.k"]["value"],
                                             params[f"{base}#2.k"]["value"])]
    again = parse_model(dump_model(spec.replace(biases=(bias,), effects=tuple(new_effects))),
                        "again.toml")
    assert [e.parameters for e in again.effects] == [e.parameters for e in new_effects]
