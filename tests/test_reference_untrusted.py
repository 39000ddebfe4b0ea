"""Every input and sensor sample is untrusted (issue 32, item 3), in NumPy and in the
compiled C: non-finite and implausible inputs held at their last good value and flagged,
readings exactly at a limit implausible in every build, fixed-point state saturation
counted, `healthy` only for a state in range. Each fault class against an independent
truth: a run whose bad sample was replaced by the previous one, a formula on the
recorded states, and the C equal to the NumPy reference bit for bit."""

import numpy as np
import pytest

from test_reference_setup import IMU6_SCALING, gcc_build, gcc_run, playback

import thermojax.reference as ref

STEPS = 600
BUILDS = ["float64", "float32", "float64-columns", "float32-columns", "q16.16", "q8.24", "q15"]
FIELDS = ("states", "residuals", "in_use", "healthy", "wire_break", "input_fault", "state_ok",
          "saturations")


def observer(build, system, faults=None):
    if build.startswith("q"):
        return ref.FixedObserver(system, build, IMU6_SCALING[build], faults)
    dtype = np.float64 if build.startswith("float64") else np.float32
    return ref.FloatObserver(system, faults, dtype=dtype)


def run(obs, x0, u, y, oc=None):
    """Play back physical values; fixed point on codes (`run`, not `run_physical`, so that
    the C gets the same codes). Returns `(run, codes)`."""
    if isinstance(obs, ref.FixedObserver):
        codes = obs.encode_states(x0), obs.encode_inputs(u), obs.encode_outputs(y)
    else:
        codes = x0, u, y
    return obs.run(*codes, oc), codes


def c_run(obs, build, codes, oc, folder):
    src = ref.generate_c(obs, "obs", layout="columns" if build.endswith("columns") else "rows")
    return gcc_run(src, gcc_build(src, folder), folder, *codes, oc)


def assert_same(got, want):
    """Every field equal (NaN equal to NaN; for float states bit for bit but for the sign
    of an exact zero, which the columns layout may flip, see `generate_c`)."""
    for f in FIELDS:
        a, b = np.asarray(getattr(got, f)), np.asarray(getattr(want, f))
        assert a.shape == b.shape, f
        if a.dtype.kind == "f":
            np.testing.assert_array_equal(a + 0, b + 0, err_msg=f)
        else:
            assert np.array_equal(a.astype(np.int64), b.astype(np.int64)), f


def bad_inputs(u):
    """Input faults of every class, and the same inputs with each bad sample replaced by
    the previous one (the truth)."""
    bad, held = u.copy(), u.copy()
    spots = [(100, 0, np.nan), (101, 1, np.nan), (200, 1, np.inf), (300, 0, -np.inf),
             (400, 1, 1e6), (401, 1, 1e6), (402, 1, -1e6), (500, 0, 1e300)]
    for k, j, v in spots:
        bad[k, j] = v
    for k, j, _ in spots:
        held[k, j] = held[k - 1, j]
    return bad, held, spots


@pytest.mark.parametrize("build", BUILDS)
def test_bad_inputs_held_and_flagged(build, tmp_path):
    system, u, y, _, x0 = playback(STEPS)
    bad, held, spots = bad_inputs(u)
    obs = observer(build, system)
    got, codes = run(obs, x0, bad, y)
    truth, _ = run(obs, x0, held, y)
    # the state never sees a bad sample: equal to the run with the previous value
    assert np.all(np.isfinite(np.asarray(got.states, float)))
    np.testing.assert_array_equal(got.states, truth.states)
    assert np.array_equal(got.in_use, truth.in_use) and np.array_equal(got.healthy,
                                                                       truth.healthy)
    want_mask = np.zeros(STEPS, np.int64)
    for k, j, _ in spots:
        want_mask[k] |= 1 << j
    assert np.array_equal(got.input_fault.astype(np.int64), want_mask)
    assert not truth.input_fault.any() and got.state_ok.all() and got.healthy.min() == 7
    # the compiled C: the same, bit for bit
    assert_same(c_run(obs, build, codes, None, tmp_path), got)


@pytest.mark.parametrize("build", ["float64", "float32", "q16.16", "q15"])
def test_bad_first_input_held_at_middle_of_limits(build):
    system, u, y, _, x0 = playback(50)
    faults = ref.FaultConfig(input_limits=[(-55.0, 125.0), (-0.9, 0.9)])
    bad, truth_u = u.copy(), u.copy()
    bad[0] = [np.nan, 1e6]
    truth_u[0] = [35.0, 0.0]              # the middles of the input limits
    obs = observer(build, system, faults)
    got, _ = run(obs, x0, bad, y)
    truth, _ = run(obs, x0, truth_u, y)
    np.testing.assert_array_equal(got.states, truth.states)
    assert got.input_fault[0] == 0b11 and not got.input_fault[1:].any()


def test_encoder_never_turns_nan_into_a_value():
    F = ref.Q16_16
    codes = ref.encode([np.nan, np.inf, -np.inf, 35.0], F.frac_bits, F, 35.0, 1.0)
    assert codes.tolist() == [F.word_min, F.word_max, F.word_min, 0]
    system, u, y, _, x0 = playback(STEPS)
    bad, held, _ = bad_inputs(u)
    fx = observer("q16.16", system)
    got = fx.run_physical(x0, bad, y)
    truth = fx.run_physical(x0, held, y)
    np.testing.assert_array_equal(got.states, truth.states)
    assert got.input_fault[100] == 0b01 and got.input_fault[101] == 0b10


@pytest.mark.parametrize("limit", [125.0, -55.0])
def test_reading_at_a_limit_is_implausible_in_every_build(limit, tmp_path):
    system, u, y, _, x0 = playback(STEPS)
    y = y.copy()
    y[200:300, 1] = limit                 # pcb sensor stuck exactly at a limit
    y[400:410, 1] = np.nextafter(limit, 35.0) if limit > 0 else limit + 1e-3
    masks = {}
    for build in BUILDS:
        obs = observer(build, system)
        got, codes = run(obs, x0, u, y)
        assert np.all(got.in_use[200:300] == 0b101), build          # dropped at once
        assert np.all(got.healthy[200:300] & 0b010 == 0), build
        masks[build] = got.in_use
        assert_same(c_run(obs, build, codes, None, tmp_path / build), got)
    for build in BUILDS:                  # the same channel decisions everywhere
        assert np.array_equal(masks[build][:400], masks["float64"][:400]), build


def hot(steps=3000):
    """`(x0, u)`: every node at 120 °C, the chamber held there with 0.99 W in the ASIC:
    the ASIC node leaves the limits after about 10 steps and passes 163 °C (35 + 128 K,
    the end of Q8.24's and Q15's range) after about 250, heading for 187 °C."""
    u = np.zeros((steps, 2))
    u[:, 0], u[:, 1] = 120.0, 0.99
    return np.full(6, 120.0), u


@pytest.mark.parametrize("build", ["q8.24", "q15"])
def test_fixed_saturation_counted_and_flagged(build, tmp_path):
    system, *_ = playback(10)
    x0, u = hot()
    y = np.full((len(u), 3), np.nan)      # no sensor readable: prediction only
    oc = np.ones(y.shape, bool)
    fx = observer(build, system)
    got, codes = run(fx, x0, u, y, oc)
    F, c, sh, X, U = fx.fmt, fx.coef, fx.shift, got.states, codes[1]
    # the truth: no channel in use, so each step is the prediction alone; a clamp happened
    # where the exact prediction (docs/observer.md section 6) is beyond the word
    acc = (X[:-1] @ (c["Phi"] << sh["Phi"]).T + U[:-1] @ (c["B0"] << sh["B0"]).T
           + U[1:] @ (c["B1"] << sh["B1"]).T)
    exact = (acc + (1 << (fx.f_pred - 1))) >> fx.f_pred
    clamped = np.r_[False, np.any((exact > F.word_max) | (exact < F.word_min), axis=1)]
    assert clamped.sum() > 1000
    np.testing.assert_array_equal(got.saturations, np.cumsum(clamped))   # counted, per step
    # state_ok false while saturated or beyond the limits, and then nothing is healthy
    T = fx.decode_states(got.states)
    inside = np.all((T > -55.0) & (T < 125.0), axis=1)
    np.testing.assert_array_equal(got.state_ok.astype(bool), inside & ~clamped)
    assert np.all(got.healthy[~got.state_ok.astype(bool)] == 0)
    assert_same(c_run(fx, build, codes, oc, tmp_path), got)


@pytest.mark.parametrize("build", ["float64", "float32-columns"])
def test_healthy_only_when_state_in_range(build, tmp_path):
    system, *_ = playback(10)
    x0, u = hot()
    y = np.full((len(u), 3), 130.0)       # implausible readings: prediction only
    obs = observer(build, system)
    got, codes = run(obs, x0, u, y)
    inside = np.all((got.states > -55.0) & (got.states < 125.0), axis=1)
    assert inside.any() and not inside.all()
    np.testing.assert_array_equal(got.state_ok.astype(bool), inside)
    assert np.all(got.healthy[~inside] == 0)
    assert_same(c_run(obs, build, codes, None, tmp_path / "hot"), got)
    # a state that is not finite (a NaN prior) is never healthy either
    _, u, y, _, x_nan = playback(200)
    x_nan[3] = np.nan
    got, codes = run(obs, x_nan, u, y)
    assert not got.state_ok.any() and not got.healthy.any()
    assert_same(c_run(obs, build, codes, None, tmp_path / "nan"), got)


def test_input_limits_checked_and_defaults_derived():
    system, *_ = playback(10)
    lim = ref.FaultConfig().input_limits_array(system)
    G = system.C @ np.linalg.solve(np.eye(6) - system.Phi, system.B0 + system.B1) + system.D
    # pseudo-inverse against solve, cond(I - Phi) ~ 1e4: roundoff only
    np.testing.assert_allclose(lim[:, 1], 180.0 / np.abs(G).max(0), rtol=1e-9)
    np.testing.assert_array_equal(lim[:, 0], -lim[:, 1])
    # a held state (a random walk: Phi row of the identity, no input, unmeasured) adds no
    # gain and leaves the limits as they were
    import types
    pad = lambda M, rows, cols: np.pad(M, ((0, rows), (0, cols)))
    Phi = pad(system.Phi, 1, 1)
    Phi[6, 6] = 1.0
    held = types.SimpleNamespace(n_states=7, n_inputs=2, n_outputs=3, Phi=Phi,
                                 B0=pad(system.B0, 1, 0), B1=pad(system.B1, 1, 0),
                                 C=pad(system.C, 0, 1), D=system.D)
    np.testing.assert_allclose(ref.default_input_limits(held, (-55.0, 125.0)), lim,
                               rtol=1e-9)   # as above
    with pytest.raises(ValueError, match="input_limits"):
        ref.FaultConfig(input_limits=[(0.0, 1.0)] * 3).input_limits_array(system)
    with pytest.raises(ValueError, match="input_limits"):
        ref.FaultConfig(input_limits=(1.0, 0.0)).input_limits_array(system)


def test_artifact_records_input_limits_and_reads_older_ones(tmp_path):
    import json

    from test_reference_setup import CONFIGS

    from thermojax.observer import export_observer

    export_observer(CONFIGS / "imu6.toml", 20.0, tmp_path / "obs", fixed="q16.16")
    meta_path = tmp_path / "obs" / "observer.json"
    meta = json.loads(meta_path.read_text())
    art = ref.load_observer(tmp_path / "obs")
    units = [i["units"] for i in meta["inputs"]]
    lim = art.faults.input_limits_array(art.system)
    default = ref.FaultConfig().input_limits_array(art.system)
    for j, unit in enumerate(units):   # a temperature: the plausibility limits; a power: derived
        want = [-55.0, 125.0] if unit == "°C" else default[j].tolist()
        assert meta["faults"]["input_limits"][j] == want and lim[j].tolist() == want
    # the artifact's observers hold a NaN input (float and fixed)
    _, u, y, _, x0 = playback(STEPS)
    bad, held, _ = bad_inputs(u)
    obs = art.float_observer()
    np.testing.assert_array_equal(obs.run(x0, bad, y).states, obs.run(x0, held, y).states)
    fx = art.fixed_observer()
    np.testing.assert_array_equal(fx.run_physical(x0, bad, y).states,
                                  fx.run_physical(x0, held, y).states)
    # an artifact written before input supervision (no `input_limits`): the defaults
    del meta["faults"]["input_limits"]
    del meta["content_sha256"]   # nor the content hash (issue 67), which the edit breaks
    meta_path.write_text(json.dumps(meta))
    old = ref.load_observer(tmp_path / "obs")
    assert old.faults.input_limits is None
    np.testing.assert_array_equal(old.faults.input_limits_array(old.system), default)
    meta["faults"]["input_limits"] = [[0.0, 1.0]]          # one pair for two inputs
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ref.ArtifactError, match="faults"):
        ref.load_observer(tmp_path / "obs")
