"""`thermojax rate`: the observer's error against the rate, and an anti-alias filter's
cost. Truths: SciPy's continuous and discrete Riccati solutions on matrices read with
tomllib (`model_matrices`), Butterworth group delays in closed form, and a ramp played
through a separately written simulation of plant, filter and observer."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import thermojax as tj
from thermojax.cli import main
from thermojax.observer._rate import anti_alias_cost, butterworth_group_delay, rate_advice

from helpers import CONFIGS, model_matrices, np_van_loan

RATES = (0.05, 0.2, 1.0, 5.0, 50.0)


def _model():
    return tj.ThermalModel.from_spec(tj.load_model(CONFIGS / "rtd2.toml"))


def _truth():
    m = model_matrices(CONFIGS / "rtd2.toml")
    q = np.where(m["q"] > 0, m["q"], 1e-3)      # docs/observer.md §4: the default q
    return m["A"], m["Cy"], q, m["noise"]


def test_error_converges_to_the_kalman_bucy_limit():
    A, C, q, noise = _truth()
    density = noise ** 2 / 1.0                   # noise std per sample at 1 Hz
    Pc = scipy.linalg.solve_continuous_are(A.T, C.T, np.diag(q ** 2), np.diag(density))
    adv = rate_advice(_model(), rates=RATES)
    worst = int(np.argmax(np.diag(Pc)))
    assert adv.limit_std == pytest.approx(np.sqrt(Pc[worst, worst]), rel=1e-9)
    for row in adv.rows:                         # P⁻ of the discrete filter, from SciPy
        dt = 1.0 / row.rate_hz
        Phi = scipy.linalg.expm(A * dt)
        Qd = np_van_loan(A, np.diag(q ** 2), dt)
        P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, np.diag(density * row.rate_hz))
        assert row.error_std == pytest.approx(np.sqrt(P[worst, worst]), rel=1e-6)
    ratios = [row.error_ratio for row in adv.rows]
    assert all(a >= b for a, b in zip(ratios, ratios[1:]))   # faster is never worse
    assert ratios[-1] == pytest.approx(1.0, abs=2e-3)
    enough = [row for row in adv.rows if row.error_ratio <= 1.1]
    assert adv.recommended_hz == enough[0].rate_hz


@pytest.mark.parametrize("order, factor", [(1, 1.0), (2, np.sqrt(2.0)),
                                           (3, 2.0)])
def test_butterworth_group_delay_in_closed_form(order, factor):
    # τ_g(0) = a1/(a0 ωc): 1, √2, 2 for orders 1, 2, 3
    fc = 3.0
    assert butterworth_group_delay(order, fc) == pytest.approx(factor / (2 * np.pi * fc),
                                                               rel=1e-12)


def test_ramp_error_of_a_filtered_sensor_matches_a_simulation():
    """rtd2 in a 5 °C/min ramp of the fluid, the core sensor behind a first-order
    filter at 0.5 Hz, the Kalman observer at 2 Hz designed without the filter: the
    steady error of the simulation equals the predicted one to a few percent."""
    A, C, q, noise = _truth()
    rate, fc, ramp = 2.0, 0.5, 5.0 / 60.0
    cost = anti_alias_cost(_model(), rate, 1, fc, ramp_C_per_s=ramp)
    # the separately written simulation: plant + filter on a fine grid (exact, FOH by
    # tiny steps), the observer in filter form at `rate`
    B = model_matrices(CONFIGS / "rtd2.toml")["B"]
    wc = 2 * np.pi * fc
    Af = np.block([[A, np.zeros((2, 1))], [wc * C, -wc * np.ones((1, 1))]])
    Bf = np.vstack([B, [[0.0]]])
    h, dt = 0.005, 1.0 / rate
    Ph = scipy.linalg.expm(np.block([[Af, Bf], [np.zeros((1, 4))]]) * h)
    Phi = scipy.linalg.expm(A * dt)
    Gam = np.linalg.solve(A, (Phi - np.eye(2)) @ B)        # ZOH input matrix
    Qd = np_van_loan(A, np.diag(q ** 2), dt)
    R = np.diag(noise ** 2 * rate)
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, R)
    L = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    z = np.array([25.0, 25.0, 25.0])
    x_hat = np.array([25.0, 25.0])
    per = int(round(dt / h))
    errs = []
    for k in range(int(1200 * rate)):
        t0 = k * dt
        u_mid = 25.0 + ramp * (t0 + dt / 2)                # the ramp, held by midpoints
        for i in range(per):
            u = 25.0 + ramp * (t0 + (i + 0.5) * h)
            z = Ph[:3, :3] @ z + Ph[:3, 3] * u
        x_hat = Phi @ x_hat + Gam[:, 0] * u_mid
        x_hat = x_hat + L @ (z[2:] - C @ x_hat)
        errs.append(x_hat - z[:2])
    # without the filter the observer would track the ramp exactly (ZOH of the period's
    # midpoint is exact for a ramp), so the steady error is the filter's
    steady = np.abs(np.mean(errs[-200:], axis=0))
    np.testing.assert_allclose(steady.max(), cost.ramp_error.max(), rtol=0.15)


def test_cli_rate(capsys, tmp_path):
    assert main(["rate", "--model", str(CONFIGS / "rtd2.toml"), "--rates", "0.1,1,10",
                 "--anti-alias", "2", "2", "--rate", "10", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "enough:" in out and "8–15×" in out and "group delay" in out
    assert main(["rate", "--model", str(CONFIGS / "rtd2.toml"), "--sensor", "T_case",
                 "--quiet"]) == 2
    assert "T_case" in capsys.readouterr().err
    assert main(["rate", "--model", str(CONFIGS / "rtd2.toml"), "--anti-alias", "0", "2",
                 "--quiet"]) == 2
