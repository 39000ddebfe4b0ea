"""Twin optima are reported as non-identifiable (`fitting._twin_optima`).

The rule is checked on an identifiability report built by hand (a capacitance at 0.240 ±
0.0007 J/K, a conductance at 2.0 ± 0.01 W/K) against other starts whose values and
likelihoods are set here: the expected verdicts follow from the definition (a start
within 1 in −log L, more than 5 stds away), not from the code."""

from __future__ import annotations

import numpy as np

from thermojax.fitting._identifiability import Identifiability
from thermojax.fitting._twin_optima import with_twin_optima

NAMES = ["nodes.a.capacitance", "links.a-b.conductance", "runs.0.nodes.a.initial"]
THETA = np.array([np.log(0.240), np.log(2.0), 25.0])
STDS = np.array([0.0007 / 0.240, 0.01 / 2.0, 0.5])  # theta units: log std, °C


def _ident():
    return Identifiability(np.diag(STDS ** 2), 10.0, [], set(), STDS.copy())


def test_a_start_as_good_elsewhere_makes_the_parameter_unidentifiable():
    other = np.array([np.log(0.80), np.log(2.001), 40.0])  # the initial moves too: ignored
    got = with_twin_optima(_ident(), NAMES, THETA, -100.0, [(other, -99.6)])
    assert got.unidentifiable_parameters == {"nodes.a.capacitance"}
    assert np.isinf(got.stds[0]) and np.isfinite(got.stds[1])
    (d,) = got.directions
    assert d["cause"] == "twin optimum" and "0.24 against 0.8" in d["message"]


def test_a_worse_or_nearby_start_changes_nothing():
    worse = np.array([np.log(0.80), np.log(2.0), 25.0])
    near = np.array([np.log(0.2401), np.log(2.02), 25.0])  # 0.6 and 2 stds: the same optimum
    for other, nll in ((worse, -98.5), (near, -100.0)):
        got = with_twin_optima(_ident(), NAMES, THETA, -100.0, [(other, nll)])
        assert got.ok and not got.unidentifiable_parameters
