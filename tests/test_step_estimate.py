"""What the loop says to expect before a step: the last step's time, and where the effect
it chose made a fit of the model dearer (a nonlinear effect: an extended Kalman filter in
substeps), that step's fitting phases scaled by how much dearer."""

from __future__ import annotations

import pytest

from thermojax.investigation._candidates import Candidate
from thermojax.investigation._step_estimate import (DEARER, NONLINEAR_REFIT_COST, RefitCosts,
                                                    duration_text, expected_step_seconds,
                                                    refit_cost_ratio, refit_forecast)


def _refitted(kind, seconds, fits):
    c = Candidate(kind=kind, where=("a",), score=10.0, p_value=0.01, method="refit")
    c.refit_seconds, c.refit_fits = seconds, fits
    return c


def test_cost_ratio_is_seconds_per_fit_of_the_chosen_over_the_steps_average():
    linear = _refitted("extra_node", 30.0, 3)          # 10 s a fit
    lag = _refitted("sensor_lag", 10.0, 2)              # 5 s a fit
    nonlinear = _refitted("capacitance_temperature", 60.0, 2)  # 30 s a fit
    unscored = Candidate(kind="sensor_gain", where=("y",), score=1.0, p_value=0.5)
    cands = [linear, lag, nonlinear, unscored]
    # the step's average: 100 s over 7 fits
    assert refit_cost_ratio(nonlinear, cands) == pytest.approx(30.0 / (100.0 / 7))
    assert refit_cost_ratio(lag, cands) == pytest.approx(5.0 / (100.0 / 7))
    assert refit_cost_ratio(unscored, cands) == 1.0  # not refitted: nothing measured


def test_expected_time_scales_the_fitting_phases_only():
    last = {"wall_time_s": 148.0, "phase_times_s": {
        "refits": 99.0, "held-out folds": 45.0, "score tests": 4.0, "compilation": 4.0}}
    # 2.1x dearer fits: refits and folds (144 s) become 302.4 s, the rest stays (4 s)
    assert expected_step_seconds(last, 2.1) == pytest.approx(148.0 + 1.1 * 144.0)
    # a cheaper chosen fit does not promise a shorter step: the others still refit
    assert expected_step_seconds(last, 0.5) == pytest.approx(148.0)
    assert expected_step_seconds({"wall_time_s": 20.0}, 3.0) == pytest.approx(20.0)
    assert DEARER > 1.0


def test_refit_costs_split_linear_and_nonlinear_refits():
    mass = _refitted("extra_node", 30.0, 3)
    lag = _refitted("sensor_lag", 10.0, 2)
    warm = _refitted("capacitance_temperature", 60.0, 2)
    unscored = Candidate(kind="sensor_gain", where=("y",), score=1.0, p_value=0.5)
    costs = RefitCosts.measured([mass, lag, warm, unscored], 50.0, model_nonlinear=False)
    assert costs.wall == 50.0 and costs.fitting == pytest.approx(100.0)
    assert costs.linear == pytest.approx(20.0) and costs.nonlinear == pytest.approx(60.0)
    # on a nonlinear model every refit is of a nonlinear model
    costs = RefitCosts.measured([mass, lag, warm], 50.0, model_nonlinear=True)
    assert costs.linear is None and costs.nonlinear == pytest.approx(100.0 / 3)
    assert RefitCosts.measured([unscored], 50.0, False) is None
    assert RefitCosts.measured([mass], 0.0, False) is None


def test_forecast_once_scored_foresees_the_first_nonlinear_refits():
    first_linear = [Candidate("extra_node", ("a",), 9.0, 0.0) for _ in range(3)]
    warm = [Candidate(k, ("a",), 9.0, 0.0) for k in ("capacitance_temperature", "radiation")]
    # the last step: three linear candidates, 10 s of fitting each, 15 s of wall time
    last = RefitCosts(wall=15.0, linear=10.0, nonlinear=None, fitting=30.0)
    said = refit_forecast(last, [first_linear[0]] + warm, model_nonlinear=False)
    # one linear (10 s) and two nonlinear (4 x 10 s) refits, at 15 s of wall per 30 s
    expect = (10.0 + 2 * NONLINEAR_REFIT_COST * 10.0) * 15.0 / 30.0
    assert said is not None and f"about {expect:.0f} s or more" in said
    assert "2 of the 3 refits" in said and "4.0× a linear refit" in said
    # a nonlinear refit measured at the last step is used as measured
    measured = RefitCosts(wall=15.0, linear=10.0, nonlinear=25.0, fitting=35.0)
    said = refit_forecast(measured, warm, model_nonlinear=False)
    assert f"about {2 * 25.0 * 15.0 / 35.0:.0f} s" in said and "2.5× a linear" in said
    # nothing to say: only linear refits, a nonlinear model (the step's estimate
    # before it holds), nothing measured, or no dearer than the last step
    assert refit_forecast(last, first_linear, False) is None
    assert refit_forecast(last, warm, True) is None
    assert refit_forecast(None, warm, False) is None
    cheap = RefitCosts(wall=15.0, linear=1.0, nonlinear=None, fitting=30.0)
    assert refit_forecast(cheap, warm, False) is None  # 4 s expected: not dearer


def test_duration_text_picks_its_unit():
    assert duration_text(40.4) == "40 s"
    assert duration_text(420.0) == "7 min"
    assert duration_text(5400.0) == "1.5 h"
