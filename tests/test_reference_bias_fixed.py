"""Bias channels in the fixed-point reference and in the generated C.

- fixed point against the float64 reference within the derived bound
  (`FixedBiasEvaluator.error_bound` over `quantization_error_bound`), over a 24-hour
  −40…85 °C chamber playback at the observer rate (1,728,000 steps, run by the compiled C,
  itself bit-exact with the NumPy fixed point), the float bias computed by an independent
  vectorized NumPy formula (polynomial, gradient, exact rate rows, strains by
  `scipy.signal.lfilter` of the exact first-order-hold recursion; checked against
  `BiasEvaluator`, which `test_reference_bias` checks against `solve_ivp`);
- the generated C (fixed Q16.16, Q8.24, Q15; double and float) against the NumPy
  references bit for bit, with faults injected, at -O2 and -O3 -march=x86-64-v3;
- the scaling rule: no overflow for any state code, clamping at the plausibility limits;
- multi-rate execution with the artifact's bias channels.

The model is configs/imu6_bias.toml with two more viscoelastic terms on the gyro channel, so
that one channel has polynomial, gradient, rate and two strain terms (a Prony pair).
"""

import math

import numpy as np
import pytest
import scipy.signal

from helpers import CONFIGS, model_matrices
from test_reference_setup import DT, IMU6_SCALING, fault_free_observer, gcc_build, gcc_run, playback

import thermojax.reference as ref
from thermojax.reference._bias import FixedBiasEvaluator
from thermojax.observer import export_observer

GYRO_STRAINS = [("mems", 300.0, 0.5), ("proof_mass", 40.0, -0.2)]   # (node, tau s, deg/h/K)
ACCEL_STRAIN = ("mems", 1500.0, 0.6)
FAST_FLAGS = ("-O3", "-march=x86-64-v3")


def model_text():
    text = (CONFIGS / "imu6_bias.toml").read_text()
    for node, tau, k in GYRO_STRAINS:
        text += (f'\n[[effects]]\nkind = "viscoelastic"\nwhere = ["{node}", "gyro_x_dph"]\n'
                 f"time_constant = {tau}\nk = {k}\n")
    return text


@pytest.fixture(scope="module")
def artifact(tmp_path_factory):
    folder = tmp_path_factory.mktemp("bias_artifact")
    model = folder / "imu6_bias_prony.toml"
    model.write_text(model_text())
    export_observer(model, 1 / DT, folder / "observer")
    return ref.load_observer(folder / "observer")


def fixed_observer(art, fmt, faults=None):
    return ref.FixedObserver(art.system, fmt, IMU6_SCALING[fmt],
                             art.faults if faults is None else faults,
                             biases=art.bias_evaluator())


def foh_strain(T, tau, dt=DT):
    """ε of dε/dt = (T − ε)/τ, T linear between samples, ε[0] = T[0]: the exact recursion
    ε[k] = a ε[k−1] + (1 − β) T[k] + (β − a) T[k−1] as one IIR filter."""
    r = dt / tau
    a = math.exp(-r)
    beta = (1 - a) / r
    num, den = [1 - beta, beta - a], [1.0, -a]
    zi = scipy.signal.lfiltic(num, den, y=[T[0]], x=[T[0]])
    rest, _ = scipy.signal.lfilter(num, den, T[1:], zi=zi)
    return np.concatenate([[T[0]], rest])


def independent_bias(x, u):
    """The two channels written out from the model file's numbers, vectorized."""
    net = model_matrices(CONFIGS / "imu6_bias.toml")
    i = {n: k for k, n in enumerate(net["names"])}
    A, B = net["A"], net["B"]
    mems, pm = x[:, i["mems"]], x[:, i["proof_mass"]]
    gyro = (np.polynomial.polynomial.polyval(pm - 25.0, [0.5, 0.03, 5e-4, -2e-6])
            + 0.8 * (mems - x[:, i["asic"]]) + 4.0 * (x @ A[i["mems"]] + u @ B[i["mems"]]))
    for node, tau, k in GYRO_STRAINS:
        T = x[:, i[node]]
        gyro = gyro + k * (T - foh_strain(T, tau))
    node, tau, k = ACCEL_STRAIN
    accel = (np.polynomial.polynomial.polyval(mems - 25.0, [120.0, -1.5, 0.02])
             + 3.0 * (x[:, i["pcb"]] - mems) + k * (mems - foh_strain(mems, tau)))
    return np.stack([gyro, accel], 1)


def test_model_has_every_kind_of_term(artifact):
    ev = artifact.bias_evaluator()
    gyro = ev.channels[0]
    assert gyro.name == "gyro_x_dph" and len(gyro.poly) == 4 and gyro.gradients and gyro.rates
    assert len(gyro.strains) == 2 and len(ev.channels[1].strains) == 1
    # the vectorized formula is the reference's float64 evaluation (roundoff)
    _, u, y, _, x0 = playback(12_000, seed=2)
    xs = fault_free_observer(artifact.system, x0, u, y)
    np.testing.assert_allclose(ev.run(xs, u), independent_bias(xs, u), rtol=0, atol=1e-9)


def test_scaling_rule_and_formats(artifact):
    """The formats derived from −55…+125 °C, and no overflow for any state code: the
    estimate is clamped to the limits, the output never saturates."""
    for fmt in ("q16.16", "q8.24", "q15"):
        fb = fixed_observer(artifact, fmt).biases
        assert fb.f_t == 24 and fb.f_d == 23 and fb.f_e == 53     # |T − 25| ≤ 100 < 2**7 K
        assert fb.theta_lo == -80 << 24 and fb.theta_hi == 100 << 24
        assert list(fb.g) == [20, 19]       # gyro |b| ≤ 657 deg/h, accel ≤ 1240 ug by rule
        for ch in fb.channels:
            assert ch["bound"] * 2.0 ** ch["g"] <= 2 ** 30
            assert all(abs(q) < 2 ** 31 for _, _, q in ch["ops"])
        F = fb.fmt
        ev = artifact.bias_evaluator()
        rng = np.random.default_rng(0)
        # random codes over the whole word, with the corners: no overflow, no saturation
        X = rng.integers(F.word_min, F.word_max, (4000, 6), endpoint=True)
        X[:8] = [[F.word_min] * 6, [F.word_max] * 6] * 4
        U = rng.integers(F.word_min, F.word_max, (4000, 2), endpoint=True)
        fb.reset()
        codes = np.array([fb.step(X[k], U[k]) for k in range(4000)])
        assert np.all(np.abs(codes) < 2 ** 30)
        # at the limits and beyond, the fixed bias is the float bias at the clamped state
        fx = fixed_observer(artifact, fmt)
        T = rng.uniform(-80.0, 150.0, (400, 6))
        T[:4] = [[-55.0] * 6, [125.0] * 6, [-90.0] * 6, [160.0] * 6]
        u = np.column_stack([rng.uniform(-40, 85, 400), rng.uniform(0, 0.4, 400)])
        Xc = fx.encode_states(np.clip(T, -55, 125))
        Uc = fx.encode_inputs(u)
        fb.reset()
        got = fb.decode(np.array([fb.step(Xc[k], Uc[k]) for k in range(400)]))
        want = ev.run(fx.decode_states(Xc), fx.decode_inputs(Uc))
        own = fb.error_bound(np.zeros(6))
        assert np.all(np.abs(got - want).max(0) <= own), (np.abs(got - want).max(0), own)
        fb.reset()
        beyond = fb.decode(np.array([fb.step(v, w) for v, w in
                                     zip(fx.encode_states(T), Uc)]))
        if fmt != "q15":    # Q15 saturates at −93…+163 °C, before the bias clamps
            np.testing.assert_array_equal(beyond[:1], got[:1])


def test_strain_in_fixed_point_has_no_deadband():
    """A 1 mK step held for 5 τ: the 53-bit strain state follows it (a state at the
    observer's Q16.16 resolution would stall: 2**-17 K / w ≈ 0.2 K at τ = 1500 s)."""
    ev = ref.BiasEvaluator([ref.BiasChannel("s", 0, strains=((0, 1500.0, 1.0),))], DT)
    fb = FixedBiasEvaluator(ev, ref.Q16_16, [35.0], [0.0], [1.0], (-55.0, 125.0))
    steps = int(5 * 1500 / DT)
    X = np.zeros((steps, 1), np.int64)
    X[1:] = 66                            # 66 * 2**-16 K = 1.007 mK
    fb.reset()
    out = [fb.step(X[k], [0])[0] for k in range(steps)]
    got = fb.decode(np.array(out)[:, None])[:, 0]       # k (T − ε): decays from 1 mK
    T = X[:, 0] * 2.0 ** -16
    want = T - foh_strain(T, 1500.0)
    lsb = fb.lsb[0]                                      # 2**-22 K: |b| ≤ 200 K by rule
    assert lsb == 2.0 ** -22 and want[1] > 9.9e-4
    assert np.abs(got - want).max() < 2 * lsb           # a stalled strain would miss by 1 mK
    assert want[-1] < 1e-5


def faulted(steps=36_000, seed=7):
    _, u, y, _, x0 = playback(steps, seed=seed)
    y = y.copy()
    oc = np.zeros(y.shape, bool)
    y[4000:4600, 1] = 140.0               # implausible
    oc[9000:9200, 2] = True               # open circuit
    y[15000:15400, 0] = 20.0              # stuck: wire break
    return u, y, x0, oc


FAULTS = ref.FaultConfig(residual_threshold=0.5, wire_break_after=10, recover_after=20)


@pytest.mark.parametrize("fmt", ["q16.16", "q8.24", "q15", "q31"])
def test_fixed_bias_c_bit_exact(artifact, fmt, tmp_path):
    u, y, x0, oc = faulted()
    fx = fixed_observer(artifact, fmt, FAULTS)
    X0, U, Y = fx.encode_states(x0), fx.encode_inputs(u), fx.encode_outputs(y)
    want = fx.run(X0, U, Y, oc)
    assert want.wire_break.any() and len(set(want.in_use.tolist())) >= 3
    src = ref.generate_c(fx, "obs", names=artifact.names)
    assert src.q == 2 and "static int64_t obs_eps[3]" in src.source
    for flags in ((), FAST_FLAGS):
        got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, X0, U, Y, oc)
        assert np.array_equal(got.states.astype(np.int64), want.states)
        assert np.array_equal(got.bias, want.bias)
        assert np.array_equal(got.in_use, want.in_use)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_float_bias_c_bit_exact(artifact, dtype, tmp_path):
    u, y, x0, oc = faulted(24_000)
    obs = ref.FloatObserver(artifact.system, FAULTS, dtype=dtype,
                            biases=artifact.bias_evaluator())
    want = obs.run(x0, u, y, oc)
    src = ref.generate_c(obs, "obs", names=artifact.names)
    step = src.source[src.source.index("uint8_t obs_step("):]
    assert "for (" not in step and "static double obs_eps[3]" in src.source
    for flags in ((), FAST_FLAGS):
        got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, x0, u, y, oc)
        assert np.array_equal(got.states, want.states)
        assert np.array_equal(got.bias, want.bias)          # bit for bit, in double


MEASURED = {}


@pytest.mark.parametrize("fmt", ["q16.16", "q8.24"])
def test_fixed_bias_within_bound_24_hours(artifact, fmt, tmp_path):
    """24 h at 20 Hz: the compiled fixed-point C (bit-exact with NumPy, above) against the
    float64 observer and the independent float bias, within the derived bound."""
    steps = 1_728_000
    _, u, y, _, x0 = playback(steps, seed=9)          # chamber −39.3…84.3 °C
    system = artifact.system
    x64 = fault_free_observer(system, x0, u, y)
    b64 = independent_bias(x64, u)
    fx = fixed_observer(artifact, fmt)
    src = ref.generate_c(fx, "obs")
    out = gcc_run(src, gcc_build(src, tmp_path), tmp_path, fx.encode_states(x0),
                  fx.encode_inputs(u), fx.encode_outputs(y))
    xs = fx.decode_states(out.states)
    bs = fx.decode_bias(out.bias)
    margin = 0.5
    x_env = np.abs(x64 - fx.x_ref).max(0) + margin
    r_env = np.abs(y - x64 @ system.C.T).max(0) + margin
    sb = ref.quantization_error_bound(fx, x_env, x_env + margin, np.abs(u - fx.u_ref).max(0),
                                      r_env)
    assert np.all(np.abs(xs - x64).max(0) <= sb.bound)
    du = fx.u_scale * 2.0 ** -fx.fmt.frac_bits / 2
    bound = fx.biases.error_bound(sb.bound, du, x64.min() - margin, x64.max() + margin)
    err = np.abs(bs - b64).max(0)
    MEASURED[fmt] = (err, bound)
    print(f"{fmt}: worst bias error {err} (deg/h, ug), bound {bound}")
    assert np.all(err <= bound), (err, bound)
    assert np.all(bound < 50 * err)                 # the bound is not vacuous
    print(f"states {x64.min():.1f}…{x64.max():.1f} °C, chamber {u[:, 0].min():.1f}…{u[:, 0].max():.1f} °C")
    assert u[:, 0].min() < -39 and u[:, 0].max() > 84   # the playback spans the range


def test_multirate_with_artifact_bias_channels(artifact):
    """`run_multirate` evaluates the artifact's bias channels at the thermal rate (the
    same `_bias` code as `ObserverRun.bias`) and ramps them to 2 kHz without steps; the
    linear-matrix form still works."""
    _, u, y, _, x0 = playback(1200)
    obs = artifact.float_observer()
    R = 100
    mr = ref.run_multirate(obs, x0, u, y, ratio=R)
    want = obs.run(x0, u, y).bias
    np.testing.assert_array_equal(mr.bias, want)
    mr2 = ref.run_multirate(ref.FloatObserver(artifact.system), x0, u, y,
                            artifact.bias_evaluator(), ratio=R)
    np.testing.assert_array_equal(mr2.bias, want)
    np.testing.assert_array_equal(mr.inertial[R - 1::R][1:], mr.bias[1:])
    slope = np.abs(np.diff(mr.bias, axis=0)).max(0) / R
    assert np.all(np.abs(np.diff(mr.inertial, axis=0)).max(0) <= slope * (1 + 1e-9))
    # the first published value ramps from the bias of x0 (strains at rest)
    start = artifact.bias_evaluator().run(x0[None], u[:1])[0]
    np.testing.assert_allclose(mr.inertial[0], start + (mr.bias[0] - start) / R, rtol=1e-12)
    K = np.zeros((1, 6))
    K[0, 2], K[0, 3] = 0.3, -0.3
    lin = ref.run_multirate(ref.FloatObserver(artifact.system), x0, u, y, K, ratio=R)
    assert lin.inertial.shape == (1200 * R, 1)
    with pytest.raises(ValueError, match="no bias given"):
        ref.run_multirate(ref.FloatObserver(artifact.system), x0, u, y)
