"""The missing heat (spec §3a) against heat known because the test generated it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import thermojax as tj
from thermojax import Experiment, parse_model
from thermojax.discovery import missing_heat, unexplained, write_missing_heat

from hidden import generator as g

HORIZON_S = 2400.0


def _fit_at_truth(case_name, runs_idx=(0, 1)):
    """The believed model with its parameters fixed at the truth's (the generator's own
    values: only the hidden heat is missing), but the boundary conductance (a fit needs
    one free parameter) and the noise."""
    case = g.load_case(case_name)
    spec = parse_model(g.dump_toml(case["believed"]))
    fix = lambda p: tj.Parameter(p.value, True)  # noqa: E731
    spec = spec.replace(
        nodes=tuple(dataclasses.replace(n, capacitance=fix(n.capacitance)) for n in spec.nodes),
        links=tuple(dataclasses.replace(k, conductance=fix(k.conductance)) for k in spec.links),
        heat_inputs=tuple(dataclasses.replace(h, gain=fix(h.gain)) for h in spec.heat_inputs))
    runs = g.generate_case(case_name, seed=2, horizon_s=HORIZON_S, runs=list(runs_idx))
    exps = [Experiment(ts, np.stack([c[k] for k in spec.input_columns], 1),
                       np.stack([c[k] for k in spec.sensor_columns], 1)) for ts, c in runs]
    return case, tj.fit(spec, exps)


def test_unrecorded_pulses_come_back_within_their_uncertainty():
    """0.3 W pulses into the unmeasured pcb, recorded by no column: the reconstruction
    puts them at the pcb, correlates with them, and covers them with its 3-std band
    (outside the samples at a pulse's edges, which a random walk cannot follow)."""
    case, res = _fit_at_truth("out_of_vocabulary")
    mh = missing_heat(res)
    assert mh.carriers[0] == "pcb" and mh.log_likelihood_gain > 100
    j = mh.nodes.index("pcb")
    for r, run in enumerate((0, 1)):
        truth = g.run_inputs(case, run, 2, HORIZON_S)[1]["Q_unrecorded"]
        q, s = mh.heat[r][:, j], mh.heat_std[r][:, j]
        assert np.corrcoef(q, truth)[0, 1] > 0.9
        edges = np.convolve(np.abs(np.diff(truth, prepend=truth[0])) > 0, np.ones(121),
                            "same") > 0  # within 60 s of a switch
        inside = np.abs(q - truth) <= 3 * s
        assert inside[~edges].mean() > 0.95, inside[~edges].mean()
        assert np.all(s > 0)
    # No law explains it: `unexplained` (spec §3a) names the pcb and says what it looks like
    entries = unexplained(mh, "step0_missing_heat.csv")
    assert entries[0]["where"] == ["pcb"] and entries[0]["series"] == "step0_missing_heat.csv"
    assert entries[0]["what"].startswith("an unrecorded heat input: pulses")
    assert "record" in entries[0]["advice"]


def test_no_missing_physics_gives_zero_within_uncertainty(tmp_path):
    """The null case (the believed model is the truth): no node's disturbance improves
    BIC, the first no more than any later one (it named the die at +6.7 over a baseline
    that held a constant heat on the housing), so none carries one and the heat is
    0 ± 0; the file holds it as §3a says."""
    case, res = _fit_at_truth("null")
    said = []
    mh = missing_heat(res, say=said.append)
    assert mh.carriers == () and mh.log_likelihood_gain == 0.0 and said == []
    for q, s in zip(mh.heat, mh.heat_std):
        assert not np.any(q) and not np.any(s)
    path = tmp_path / "step0_missing_heat.csv"
    write_missing_heat(mh, path)
    header = path.read_text().splitlines()[0].split(",")
    assert header == ["time_s", "run", *(c for n in ("housing", "pcb", "die")
                                         for c in (f"q_{n}_W", f"q_{n}_W_std"))]
    table = np.loadtxt(path, delimiter=",", skiprows=1)
    assert len(table) == sum(len(t) for t in mh.ts)
    np.testing.assert_array_equal(table[table[:, 1] == 1][:, 0], mh.ts[1])
    np.testing.assert_array_equal(table[table[:, 1] == 0][:, 2:].reshape(-1, 3, 2)[..., 0],
                                  mh.heat[0])


def test_description_on_known_series():
    """The description names pulses, a drift and a period for series built to be each."""
    from thermojax.discovery import describe

    t = np.arange(0.0, 7200.0, 1.0)
    pulses = 0.3 * ((t % 1500) < 300)
    assert describe([t], [pulses]).startswith("pulses: 5 episodes of about 300 s")
    assert describe([t], [1e-4 * t]).startswith("a drift of 0.36 W per hour")
    assert describe([t], [np.sin(2 * np.pi * t / 600)]) == "a periodic component of period 600 s"


def test_an_intensity_whose_filter_fails_is_no_candidate():
    """PRBS1 showed NaN log-likelihoods from 1e-5 up, and `argmax` took the first NaN:
    progress said "log L +nan" and every node was made a carrier. A concave log L with NaN
    above 1e-5 must give its finite maximum; all NaN gives -inf."""
    from thermojax.discovery._missing_heat import GRID, _best_intensity

    class Fake:
        def __init__(self, fail_from):
            self.fail_from = fail_from

        def logliks(self, carriers, s):
            s = np.asarray(s, float)
            ll = -(np.log10(s) + 6.5) ** 2  # the maximum at 10^-6.5
            return np.where(s >= self.fail_from, np.nan, ll)

    s, ll = _best_intensity(Fake(1e-5), [0])
    assert s == pytest.approx(10 ** -6.5, rel=0.2) and ll == pytest.approx(0.0, abs=0.05)
    assert _best_intensity(Fake(GRID.min() / 10), [0])[1] == -np.inf


def test_error_dynamics_of_a_stiff_network_over_a_long_sample():
    """A sensing element of 0.05 s beside a 500 s mass, sampled every 60 s (a building's
    sensor lag at 1-min data): one Van Loan block would hold e^{1200} and cancel into an
    indefinite Q. Against SciPy: `expm` for F, adaptive quadrature of the integral for Q."""
    import jax.numpy as jnp
    import scipy.linalg

    from helpers import np_van_loan
    from thermojax.discovery._missing_heat import _augmented

    C = np.array([500.0, 0.05])                       # J/K: time constants 500 s, 0.05 s
    G = np.array([[-1.0 - 1.0, 1.0], [1.0, -1.0]])    # W/K, the mass also to ambient
    A = G / C[:, None]
    q_x = np.array([1e-3, 0.0])
    sigma = np.array([2e-3 * C[0]])                   # W/√s on the mass
    dt = 60.0
    F, Q = (np.asarray(a) for a in _augmented(jnp.asarray(A), jnp.asarray(C), [0],
                                               jnp.asarray(q_x), jnp.asarray(sigma), dt))
    Ac = np.block([[A, np.array([[1.0 / C[0]], [0.0]])], [np.zeros((1, 3))]])
    Lc = np.diag(np.concatenate([q_x ** 2, sigma ** 2]))
    np.testing.assert_allclose(F, scipy.linalg.expm(Ac * dt), rtol=0, atol=1e-12)
    want = np_van_loan(Ac, Lc, dt)
    np.testing.assert_allclose(Q, want, rtol=1e-8, atol=1e-12 * np.abs(want).max())
    assert np.linalg.eigvalsh(Q).min() > -1e-12 * np.abs(want).max()
