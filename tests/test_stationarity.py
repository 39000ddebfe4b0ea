"""A fit is converged only where the first-order conditions hold: a direction the
truncated solver left out but along which the likelihood still falls is walked out of,
and one that remains makes the fit "not converged", by name."""

from __future__ import annotations

import importlib
import json

import numpy as np

from helpers import run_cli
from thermojax.fitting import _stationarity
from thermojax.fitting._stationarity import GAIN, escape, violations

NAMES = ["strong", "weak"]


def _linear_problem():
    """r(θ) = A θ − b: the first parameter seen with singular value 30, the second with
    0.5 (below the solver's 1: left out); b from θ* = (0.3, −2) plus unit noise."""
    rng = np.random.default_rng(0)
    n = 400
    q, _ = np.linalg.qr(rng.normal(size=(n, 2)))
    A = q * np.array([30.0, 0.5])
    theta_star = np.array([0.3, -2.0])
    b = A @ theta_star + rng.normal(size=n)
    return A, b


def _cost(A, b, theta):
    return 0.5 * float(np.sum((A @ theta - b) ** 2))


def test_the_least_squares_solution_has_no_violation_and_a_far_point_names_the_weak_one():
    A, b = _linear_problem()
    best = np.linalg.lstsq(A, b, rcond=None)[0]
    assert violations(A, A @ best - b, NAMES) == []
    # on the strong parameter's optimum but 15 units along the weak one: its gradient is
    # 15 * 0.5 = 7.5 of its standard deviations, z² 56, below the 100 required
    off = best + np.array([0.0, 15.0])
    assert violations(A, A @ off - b, NAMES) == []
    far = best + np.array([0.0, 40.0])  # z = 20
    found = violations(A, A @ far - b, NAMES)
    assert [f.leading for f in found] == ["weak"]
    z = 40.0 * 0.5
    assert abs(np.sqrt(found[0].z2) - z) < 1.5, found[0].z2  # the noise's projection: O(1)
    # the predicted gain of the capped step is the exact decrease (the problem is linear)
    step = found[0].step
    assert abs(np.max(np.abs(step)) - 1.0) < 1e-12  # capped at max_step
    exact = _cost(A, b, far) - _cost(A, b, far + step)
    assert abs(found[0].gain - exact) < 1e-9 * exact and exact > GAIN


def test_escape_walks_the_weak_direction_down_to_where_the_gradient_is_noise():
    A, b = _linear_problem()
    best = np.linalg.lstsq(A, b, rcond=None)[0]
    far = best + np.array([0.0, 40.0])

    def at(theta):
        r = A @ theta - b
        return 0.5 * float(r @ r), A, r

    theta, taken = escape(far, at, NAMES)
    assert 0 < taken <= _stationarity.MAX_ESCAPE_STEPS
    # it moved only where the gradient was significant: the strong parameter stays
    assert abs(theta[0] - far[0]) < 1e-6
    # and it stopped where the weak direction's score is no longer beyond 10 std
    remaining = (A[:, 1] @ (A @ theta - b)) / np.linalg.norm(A[:, 1])
    assert remaining ** 2 <= _stationarity.SCORE_Z2 + 1e-9 or taken == _stationarity.MAX_ESCAPE_STEPS
    assert _cost(A, b, theta) < _cost(A, b, far) - 100  # ½ 0.5² (40² − 20²) = 150


CHAIN = "thermojax/data/chain3.toml"


def _chamber_log(tmp_path, capsys):
    """The three-node module through a chamber power step, 5 s samples, with noise."""
    csv = tmp_path / "log.csv"
    rc, _, err = run_cli(capsys, "simulate", "--model", CHAIN, "--profile", "power_step",
                         "--dt", "5", "--noise", "--out", csv, "--quiet")
    assert rc == 0, err
    return csv


def _with_boundary(tmp_path, conductance):
    with open(CHAIN) as f:
        text = f.read()
    assert "conductance = 0.12\n" in text
    path = tmp_path / f"g{conductance}.toml"
    path.write_text(text.replace("conductance = 0.12\n", f"conductance = {conductance}\n"))
    return path


def _fit(capsys, model, csv, out):
    rc, stdout, err = run_cli(capsys, "fit", "--model", model, "--data", csv, "--out", out)
    assert rc == 0, err
    return json.loads((out / "report.json").read_text()), stdout + err


def test_a_start_1000x_off_reaches_the_optimum_of_the_true_start(tmp_path, capsys):
    csv = _chamber_log(tmp_path, capsys)
    truth, _ = _fit(capsys, _with_boundary(tmp_path, 0.12), csv, tmp_path / "truth")
    far, said = _fit(capsys, _with_boundary(tmp_path, 120.0), csv, tmp_path / "far")
    assert "the likelihood still falls along boundaries.housing-T_chamber.conductance" in said
    assert far["converged"] is True
    assert abs(far["nll"] - truth["nll"]) < 0.05, (far["nll"], truth["nll"])
    g = far["parameters"]["boundaries.housing-T_chamber.conductance"]
    assert abs(g["value"] - 0.12) < 3 * g["std"], g


def test_a_fit_left_short_of_stationarity_is_not_converged_and_says_where(
        tmp_path, capsys, monkeypatch):
    csv = _chamber_log(tmp_path, capsys)
    monkeypatch.setattr(_stationarity, "MAX_ESCAPE_STEPS", 0)  # no walk out of it,
    fit_module = importlib.import_module("thermojax.fitting._fit")
    monkeypatch.setattr(fit_module, "invisible_nodes", lambda *a: [])  # nor a plateau restart
    far, said = _fit(capsys, _with_boundary(tmp_path, 120.0), csv, tmp_path / "far")
    assert far["converged"] is False, (far["message"], said)
    assert far["message"].startswith("not converged: the likelihood still falls along "
                                     "boundaries.housing-T_chamber.conductance"), far["message"]
    assert "not converged" in (tmp_path / "far" / "report.md").read_text()
