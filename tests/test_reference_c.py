"""The generated C99, compiled with gcc, against the NumPy reference: bit for bit."""

import numpy as np
import pytest

from test_reference_setup import IMU6_SCALING, gcc_build, gcc_run, playback

import thermojax.reference as ref

STEPS = 36_000  # 30 min at 20 Hz through the NumPy reference


def faulted_playback():
    system, u, y, _, x0 = playback(STEPS, seed=7)
    y = y.copy()
    oc = np.zeros(y.shape, bool)
    y[4000:4600, 1] = 140.0               # implausible
    oc[9000:9200, 2] = True               # open circuit
    y[15000:15400, 0] = 20.0              # stuck: wire break
    y[20000:26000, 2] = np.minimum(y[20000:26000, 2], np.quantile(y[20000:26000, 2], 0.3))
    return system, u, y, x0, oc


FAULTS = ref.FaultConfig(rails=[(-np.inf, np.inf)] * 2 + [(-60.0, 1e9)],
                         residual_threshold=0.5, wire_break_after=10, recover_after=20)


@pytest.mark.parametrize("fmt", ["q16.16", "q8.24", "q15", "q31"])
def test_fixed_c_bit_exact(fmt, tmp_path):
    system, u, y, x0, oc = faulted_playback()
    fx = ref.FixedObserver(system, fmt, IMU6_SCALING[fmt], FAULTS)
    X0, U, Y = fx.encode_states(x0), fx.encode_inputs(u), fx.encode_outputs(y)
    oc = oc | np.isnan(y)
    want = fx.run(X0, U, Y, oc)
    src = ref.generate_c(fx, "obs")
    got = gcc_run(src, gcc_build(src, tmp_path), tmp_path, X0, U, Y, oc)
    assert len(set(want.in_use.tolist())) >= 3 and want.wire_break.any()
    assert np.array_equal(got.states.astype(np.int64), want.states)
    assert np.array_equal(got.residuals.astype(np.int64), want.residuals)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f))


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_float_c_matches(dtype, tmp_path):
    """double: equal to the NumPy float64 reference (to 1e-12, and in fact bit for bit);
    float: bit for bit, compiled with -ffp-contract=off (no FMA)."""
    system, u, y, x0, oc = faulted_playback()
    obs = ref.FloatObserver(system, FAULTS, dtype=dtype)
    want = obs.run(x0, u, y, oc)
    src = ref.generate_c(obs, "obs")
    got = gcc_run(src, gcc_build(src, tmp_path), tmp_path, x0, u, y, oc)
    np.testing.assert_allclose(got.states, want.states, rtol=0, atol=1e-12 * 130)
    assert np.array_equal(got.states, want.states)
    assert np.array_equal(got.in_use, want.in_use)


def test_generated_source_is_static(tmp_path):
    system, *_ = playback(10)
    src = ref.generate_c(ref.FixedObserver(system, "q16.16", IMU6_SCALING["q16.16"]), "obs")
    assert "malloc" not in src.source and "static const int32_t OBS_PHI[6][6]" in src.source
    assert "int64_t" in src.source
    # without bias channels: no bias code, the harness writes states, residuals, flags
    assert src.q == 0 and "obs_bias" not in src.source and "OBS_Q" not in src.header


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_step_is_straight_line(dtype):
    """The step has no loops: products unrolled with literal coefficients, zeros skipped,
    one comment per matrix row."""
    system, *_ = playback(10)
    src = ref.generate_c(ref.FloatObserver(system, dtype=dtype), "obs",
                         names=(["housing", "bulkhead", "pcb", "asic", "mems", "proof_mass"],
                                ["T_chamber", "P_asic"], ["T_housing", "T_pcb", "T_asic"]))
    step = src.source[src.source.index("uint8_t obs_step("):]
    assert "for (" not in step and "OBS_PHI" not in step
    assert "/* x-[bulkhead] = Phi[bulkhead, :] x" in step
    assert "r1 = y[1] - (xm2);" in step             # C selects pcb: 1 * x is x
    n_products = step.count(" * ")
    nz = sum(np.count_nonzero(M) for M in (system.Phi, system.B0, system.B1,
                                           system.gain_table[1:]))
    assert n_products == nz                          # every nonzero gain/plant entry, once


@pytest.mark.parametrize("fmt", ["q16.16", "q8.24"])
def test_fixed_c_gated_bit_exact(fmt, tmp_path):
    """Innovation gating (`FaultConfig(gate=True)`) in the fixed builds: C as NumPy, bit for
    bit, and gating changes which samples correct (the stuck and offset faults)."""
    import dataclasses

    system, u, y, x0, oc = faulted_playback()
    x0 = x0 + 3.0              # a start 3 K off: the first step corrects all the same
    gated = dataclasses.replace(FAULTS, gate=True)
    fx = ref.FixedObserver(system, fmt, IMU6_SCALING[fmt], gated)
    X0, U, Y = fx.encode_states(x0), fx.encode_inputs(u), fx.encode_outputs(y)
    oc = oc | np.isnan(y)
    want = fx.run(X0, U, Y, oc)
    plain = ref.FixedObserver(system, fmt, IMU6_SCALING[fmt], FAULTS).run(X0, U, Y, oc)
    assert not np.array_equal(want.in_use, plain.in_use)
    assert want.in_use[0] == 7                 # the first step is never gated
    src = ref.generate_c(fx, "obs")
    got = gcc_run(src, gcc_build(src, tmp_path), tmp_path, X0, U, Y, oc)
    assert np.array_equal(got.states.astype(np.int64), want.states)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f))


@pytest.mark.parametrize("layout, supervision", [("rows", "branches"), ("rows", "lanes"),
                                                 ("columns", "lanes")])
def test_float_c_gated_from_a_far_start(layout, supervision, tmp_path):
    """Gating from a start 3 K off in every float layout: the first step corrects (its
    state is a guess), later large residuals do not; C as NumPy, bit for bit."""
    import dataclasses

    system, u, y, x0, oc = faulted_playback()
    obs = ref.FloatObserver(system, dataclasses.replace(FAULTS, gate=True))
    want = obs.run(x0 + 3.0, u, y, oc)
    assert want.in_use[0] == 7
    src = ref.generate_c(obs, "obs", layout=layout, supervision=supervision)
    got = gcc_run(src, gcc_build(src, tmp_path), tmp_path, x0 + 3.0, u, y, oc)
    assert np.array_equal(got.in_use, want.in_use)
    assert np.abs(got.states - want.states).max() == 0.0

