"""What the loop says to expect before a step: the last step's time, and where the effect
it chose made a fit of the model dearer (a nonlinear effect: an extended Kalman filter in
substeps), that step's fitting phases scaled by how much dearer."""

from __future__ import annotations

import pytest

from thermojax.investigation._candidates import Candidate
from thermojax.investigation._investigate import (DEARER, expected_step_seconds,
                                                  refit_cost_ratio)


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
