"""`export --reconstruct COLUMN`: lag compensation in the artifact, the reference and the
C. Truths: the Kalman gain of the augmented model from SciPy (its own expm, Van Loan and
`solve_discrete_are`), a fluid step simulated by `scipy.signal.lsim`, and the NumPy
reference for the C builds (bit for bit)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import thermojax as tj
import thermojax.reference as ref
from thermojax.cli import main
from thermojax.observer._compensate import compensate

from helpers import CONFIGS, model_matrices, np_van_loan
from test_export import compile_artifact, run_c

MODEL = str(CONFIGS / "rtd2.toml")
RATE = 10.0


@pytest.fixture(scope="module")
def chosen(tmp_path_factory):
    """The documented workflow: `compensate` on a log chooses the input noise by maximum
    likelihood; `export --reconstruct` takes it."""
    ts, fluid, y = _step()
    log = tmp_path_factory.mktemp("log") / "step.csv"
    tj.write_telemetry(log, ts, {"T_core": y[:, 0]})
    return compensate(tj.load_model(MODEL), tj.read_telemetry(log), "T_fluid")


@pytest.fixture(scope="module")
def artifact(tmp_path_factory, chosen):
    out = tmp_path_factory.mktemp("rc") / "obs"
    assert main(["export", "--model", MODEL, "--rate", str(RATE), "--out", str(out),
                 "--reconstruct", "T_fluid", "--input-noise", repr(chosen.input_noise),
                 "--fixed", "q16.16", "--quiet"]) == 0
    return out


def _augmented(q_input):
    m = model_matrices(CONFIGS / "rtd2.toml")
    n = m["A"].shape[0]
    A = np.block([[m["A"], m["B"][:, :1]], [np.zeros((1, n + 1))]])
    C = np.hstack([m["Cy"], np.zeros((1, 1))])
    q = np.where(m["q"] > 0, m["q"], 1e-3)   # docs/observer.md §4: the default q
    return A, C, np.append(q, q_input), m["noise"]


def test_gain_is_the_kalman_gain_of_the_augmented_model(artifact, chosen):
    meta = json.loads((artifact / "observer.json").read_text())
    assert [s["name"] for s in meta["states"]] == ["sheath", "core", "T_fluid"]
    assert meta["inputs"] == [] and meta["reconstruct"]["state_index"] == 2
    assert meta["reconstruct"]["input_noise_C_per_sqrt_s"] == chosen.input_noise
    A, C, q, noise = _augmented(chosen.input_noise)
    dt = 1.0 / RATE
    Phi = scipy.linalg.expm(A * dt)
    Qd = np_van_loan(A, np.diag(q ** 2), dt)
    R = np.diag(noise ** 2)
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, R)   # predicted covariance
    L = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    art = ref.load_observer(artifact)
    np.testing.assert_allclose(art.system.Phi, Phi, rtol=0, atol=1e-13)
    np.testing.assert_allclose(art.system.L, L, rtol=1e-7, atol=1e-12)


def _step(seconds=400.0, seed=0):
    """The fluid stepping 25 -> 80 °C at 50 s; the core sensor with 0.01 °C noise."""
    dt = 1.0 / RATE
    ts = dt * np.arange(int(seconds / dt) + 1)
    fluid = np.where(ts < 50.0, 25.0, 80.0)
    m = model_matrices(CONFIGS / "rtd2.toml")
    x0 = np.linalg.solve(m["A"], -m["B"][:, 0] * 25.0)
    _, y, _ = scipy.signal.lsim((m["A"], m["B"], m["Cy"], np.zeros((1, 1))), fluid, ts,
                                X0=x0, interp=False)
    reading = np.asarray(y).reshape(-1) + 0.01 * np.random.default_rng(seed).standard_normal(ts.size)
    return ts, fluid, reading[:, None]


def _lag63(ts, signal):
    """Seconds from the step (50 s) until `signal` first passes 63 % of 25 -> 80 °C."""
    return float(ts[np.argmax(signal >= 25.0 + 0.632 * 55.0)] - 50.0)


def test_reconstructed_fluid_leads_the_sensor(artifact, chosen):
    ts, fluid, y = _step()
    art = ref.load_observer(artifact)
    x0 = np.full(3, y[0, 0])   # at rest at the first reading, as `compensate` starts
    run = art.float_observer().run(x0, np.zeros((ts.size, 0)), y)
    est = run.states[:, 2]
    # the same observer as `compensate` (JAX), run by the NumPy reference
    np.testing.assert_allclose(est, chosen.causal, rtol=0, atol=1e-8)
    lag_sensor, lag_est = _lag63(ts, y[:, 0]), _lag63(ts, est)
    after = ts > 50.0
    rmse_sensor = np.sqrt(np.mean((y[after, 0] - fluid[after]) ** 2))
    rmse_est = np.sqrt(np.mean((est[after] - fluid[after]) ** 2))
    print(f"63 % lag {lag_sensor:.1f} -> {lag_est:.1f} s; RMSE {rmse_sensor:.3f} -> "
          f"{rmse_est:.3f} °C")
    assert lag_est <= lag_sensor / 4      # the targets
    assert rmse_est <= rmse_sensor / 3


@pytest.mark.parametrize("build", ["float", "q16.16"])
def test_c_builds_are_bit_exact(artifact, tmp_path, build):
    import shutil

    folder = tmp_path / "c"
    shutil.copytree(artifact, folder)
    art = ref.load_observer(folder)
    ts, fluid, y = _step(seconds=200.0)
    y[700:760, 0] = np.nan                    # a dropout: prediction only, input held
    u = np.zeros((ts.size, 0))
    x0 = np.array([25.0, 25.0, 25.0])
    if build == "float":
        obs, prefix = art.float_observer(), "tj_observer"
        want = obs.run(x0, u, y, np.isnan(y))
        X0, U, Y, oc = x0, u, np.nan_to_num(y), np.isnan(y)
    else:
        obs, prefix = art.fixed_observer(), "tj_observer_q16_16"
        X0, U, Y, oc = obs.encode_states(x0), obs.encode_inputs(u), \
            obs.encode_outputs(np.nan_to_num(y)), np.isnan(y)
        want = obs.run(X0, U, Y, oc)
    src = ref.generate_c(obs, prefix, art.names)
    assert (folder / f"{prefix}.c").read_text() == src.source
    got = run_c(src, compile_artifact(folder, prefix), folder, X0, U, Y, oc)
    assert np.array_equal(got.states.astype(want.states.dtype), want.states)
    assert np.array_equal(got.in_use, want.in_use)


@pytest.mark.parametrize("flags, field", [
    (["--reconstruct", "T_fluid"], "--input-noise"),
    (["--reconstruct", "T_oil", "--input-noise", "0.3"], "--reconstruct"),
    (["--reconstruct", "T_fluid", "--input-noise", "0.3", "--method", "poles"], "--method"),
])
def test_reconstruct_mistakes_are_named(tmp_path, capsys, flags, field):
    assert main(["export", "--model", MODEL, "--rate", "10", "--out", str(tmp_path / "o"),
                 *flags, "--quiet"]) == 2
    assert field in capsys.readouterr().err


TWO_SENSORS = (CONFIGS / "rtd2.toml").read_text().replace('name = "rtd2"', 'name = "rtd2_room"') + """
[[nodes]]
name = "room_probe"
capacitance = 0.5

[[boundaries]]
node = "room_probe"
input = "T_room"
conductance = 0.05

[[sensors]]
node = "room_probe"
column = "T_probe"
noise = 0.01
"""


def test_a_sensor_subset_blind_to_the_input_holds_it(tmp_path):
    """An RTD in the fluid plus a probe in the room air: the probe alone cannot see the
    fluid, so its gain is the Kalman gain of the model without the input state (SciPy's
    DARE) with a zero row for the input, `observer.json` says "held", and while the RTD's
    channel is open the estimate of the fluid stays where it was (NumPy and C alike)."""
    model = tmp_path / "rtd2_room.toml"
    model.write_text(TWO_SENSORS)
    out = tmp_path / "obs"
    assert main(["export", "--model", str(model), "--rate", str(RATE), "--out", str(out),
                 "--reconstruct", "T_fluid", "--input-noise", "0.5", "--fixed", "q16.16",
                 "--quiet"]) == 0
    meta = json.loads((out / "observer.json").read_text())
    probe_only = next(s for s in meta["subsets"] if s["sensors"] == ["T_probe"])
    assert probe_only["method"].startswith("kalman, T_fluid held")
    both = next(s for s in meta["subsets"] if s["sensors"] == ["T_core", "T_probe"])
    assert "held" not in both["method"]
    art = ref.load_observer(out)
    # the held subset's gain: SciPy's Kalman gain of the plain model, zero for the fluid
    m = model_matrices(model)
    dt = 1.0 / RATE
    Phi = scipy.linalg.expm(m["A"] * dt)
    q = np.where(m["q"] > 0, m["q"], 1e-3)   # docs/observer.md §4: the default q
    Qd = np_van_loan(m["A"], np.diag(q ** 2), dt)
    C = m["Cy"][1:2]
    R = np.diag(m["noise"][1:2] ** 2)
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, R)
    L = P @ C.T @ np.linalg.inv(C @ P @ C.T + R)
    fluid_row = [s["name"] for s in meta["states"]].index("T_fluid")
    table = art.system.gain_table[0b10]
    np.testing.assert_allclose(np.delete(table, fluid_row, axis=0)[:, 1:], L,
                               rtol=1e-7, atol=1e-12)
    assert np.all(table[fluid_row] == 0)
    # playback: the fluid steps at 50 s, the RTD's channel opens for 20 s from 51 s
    ts = dt * np.arange(int(150.0 / dt) + 1)
    fluid = np.where(ts < 50.0, 25.0, 80.0)
    u = np.full((ts.size, 1), 22.0)                          # T_room, a known input
    x = np.linalg.solve(m["A"], -m["B"] @ np.array([25.0, 22.0]))
    _, y, _ = scipy.signal.lsim((m["A"], m["B"], m["Cy"], np.zeros((2, 2))),
                                np.column_stack([fluid, u[:, 0]]), ts, X0=x, interp=False)
    oc = np.zeros(y.shape, bool)
    window = (ts >= 51.0) & (ts < 71.0)
    oc[window, 0] = True
    x0 = np.insert(x, fluid_row, 25.0)
    fl = art.float_observer().run(x0, u, y, oc)
    held = fl.states[window, fluid_row]
    assert np.all(fl.in_use[window] == 0b10)
    np.testing.assert_allclose(held, held[0], rtol=0, atol=1e-9)   # Phi's row: 1 to roundoff
    assert 25.5 < held[0] < 79.0                              # held mid-way, not tracking
    assert abs(fl.states[-1, fluid_row] - 80.0) < 0.5         # back on the fluid after
    fx = art.fixed_observer()
    X0, U, Y = fx.encode_states(x0), fx.encode_inputs(u), fx.encode_outputs(y)
    want = fx.run(X0, U, Y, oc)
    assert len(set(want.states[window, fluid_row].tolist())) == 1
    prefix = "tj_observer_q16_16"
    src = ref.generate_c(fx, prefix, art.names)
    got = run_c(src, compile_artifact(out, prefix), out, X0, U, Y, oc)
    assert np.array_equal(got.states.astype(np.int64), want.states)
    assert np.array_equal(got.in_use, want.in_use)
