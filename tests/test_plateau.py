"""Fits that stop on a plateau (issue 32, item 4): started 100× or 1000× off in C and G,
a node's time constant falls far outside the data's time scales, its parameters stop
mattering, and Gauss-Newton stops there "converged". `fit` restarts such a node where
the data can see it and keeps the restart when it fits better. The truth is the rtd2h
model that generated the data (a NumPy simulator independent of thermojax).

The first-order check (`fitting._stationarity`) now walks most such starts off their
plateau inside the first fit; the restart is tested here with that walk turned off, as
the defence for what the walk misses."""

from __future__ import annotations

import re
import warnings

import numpy as np
import pytest

import thermojax as tj
from thermojax.fitting import _stationarity, fit
from thermojax.fitting._plateau import FAST, SLOW, invisible_nodes

from helpers import RTD2H_TEXT, RTD2H_TRUTH, rtd2h_experiments


def _started_off(c_factor: float, g_factor: float):
    """rtd2h with every capacitance times `c_factor` and conductance times `g_factor`."""
    text = re.sub(r"capacitance = ([0-9.]+)",
                  lambda m: f"capacitance = {float(m.group(1)) * c_factor}", RTD2H_TEXT)
    text = re.sub(r"^conductance = ([0-9.]+)",
                  lambda m: f"conductance = {float(m.group(1)) * g_factor}", text, flags=re.M)
    return tj.parse_model(text, source="far.toml")


@pytest.fixture
def no_first_order_walk(monkeypatch):
    monkeypatch.setattr(_stationarity, "MAX_ESCAPE_STEPS", 0)


def _fit(spec, **options):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "the run is shorter than the slowest constant"
        return fit(spec, rtd2h_experiments(1), **options)


@pytest.mark.parametrize("c_factor, g_factor, where", [(0.01, 100.0, "far below"),
                                                       (0.001, 1000.0, "far below")])
def test_a_fit_stopped_on_a_plateau_is_restarted_and_finds_the_truth(c_factor, g_factor,
                                                                      where,
                                                                      no_first_order_walk):
    stuck = _fit(_started_off(c_factor, g_factor), restart_plateaus=False)
    assert "nodes.core.capacitance" in stuck.identifiability.unidentifiable_parameters
    assert stuck.parameters["nodes.core.capacitance"]["value"] < 0.05  # truth 0.1
    with warnings.catch_warnings(record=True) as caught:  # this start warns of nothing;
        warnings.simplefilter("always")  # the restart's own start is not the user's
        result = fit(_started_off(c_factor, g_factor), rtd2h_experiments(1))
    assert not [w for w in caught if "starting model" in str(w.message)]
    for name, value in RTD2H_TRUTH.items():
        assert result.parameters[name]["value"] == pytest.approx(value, rel=0.05), name
    assert result.converged
    assert "restarted from a plateau" in result.message and "'core'" in result.message
    assert where in result.message and "--starts" in result.message
    gain = float(re.search(r"fell by ([0-9.e+]+?)\.? ", result.message).group(1))
    assert gain == pytest.approx(stuck.nll - result.nll, rel=1e-3)


def test_the_first_order_walk_alone_leaves_the_plateau_of_a_100x_start():
    result = _fit(_started_off(0.01, 100.0), restart_plateaus=False)
    assert result.converged and result.message == "converged", result.message
    for name, value in RTD2H_TRUTH.items():
        assert result.parameters[name]["value"] == pytest.approx(value, rel=0.05), name


def test_a_fit_from_a_near_start_is_not_restarted():
    result = _fit(tj.parse_model(RTD2H_TEXT, source="rtd2h.toml"))
    assert result.message == "converged"


def test_invisible_nodes_are_those_outside_the_data_time_scales_and_undetermined():
    spec = _started_off(1.0, 1.0)  # sheath tau = 0.8 / (1/12 + 0.2) = 2.82 s, core 1.2 s
    undetermined = {"nodes.core.capacitance", "nodes.sheath.capacitance"}
    assert invisible_nodes(spec, undetermined, 1.0, 600.0) == []
    assert [v.node for v in invisible_nodes(spec, undetermined, 1.2 / FAST * 1.01, 1e4)] == [
        "core"]
    assert [v.node for v in invisible_nodes(spec, undetermined, 1e-3, 1.2 / SLOW * 0.99)
            ] == ["core", "sheath"]
    assert invisible_nodes(spec, set(), 20.0, 600.0) == []  # determined: nothing to do
    (v,) = invisible_nodes(spec, undetermined, 20.0, 600.0)  # 1.2 s < 2 s < 2.82 s
    assert v.node == "core" and v.tau == pytest.approx(1.2) and np.isclose(v.sample_period, 20)
    assert "far below the 20 s sample period" in v.describe()


@pytest.mark.parametrize("nested", [None, -1e9, 1e9])
def test_a_restart_is_told_the_likelihood_the_model_already_reached(nested, monkeypatch,
                                                                     no_first_order_walk):
    """The restart passes `fit` the lower of the first fit's −log L and a nested model's,
    so a Kalman restart whose scoring steps end far above it is not polished
    (`_kalman_fit._within_reach`: on the six-node IMU such a restart took 150 s of polish
    to end 1.3 above the first fit)."""
    from thermojax.fitting import _fit as fit_module

    stuck = _fit(_started_off(0.01, 100.0), restart_plateaus=False)
    seen = {}

    def restart(spec, experiments, **options):
        seen.update(options)
        return stuck
    monkeypatch.setattr(fit_module, "fit", restart)
    fit_module._off_plateau(stuck, rtd2h_experiments(1), lambda _m: None, nested_nll=nested)
    assert seen["nested_nll"] == (stuck.nll if nested is None else min(stuck.nll, nested))
    assert seen["restart_plateaus"] is False
