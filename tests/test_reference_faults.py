"""Firmware behaviour of the reference observer, each with injected faults."""

import numpy as np

from test_reference_setup import fault_free_observer, playback

import thermojax.reference as ref


def test_implausible_and_open_drop_channel_switch_gain_and_recover():
    system, u, y, x_true, x0 = playback(8000)
    y = y.copy()
    y[2000:2400, 1] = -80.0            # pcb reads below -55 °C: implausible
    oc = np.zeros(y.shape, bool)
    oc[5000:5300, 2] = True            # asic front end reports open circuit
    M = 20
    obs = ref.FloatObserver(system, ref.FaultConfig(recover_after=M))
    run = obs.run(x0, u, y, oc)
    assert np.all(run.in_use[2000:2400] == 0b101) and np.all(run.in_use[5000:5300] == 0b011)
    # recovery after exactly M plausible samples (the M-th one is used)
    assert np.all(run.in_use[2400:2400 + M - 1] == 0b101) and run.in_use[2400 + M - 1] == 7
    assert np.all(run.in_use[5300:5300 + M - 1] == 0b011) and run.in_use[5300 + M - 1] == 7
    # no reset: during the fault the reduced-order gain keeps tracking the plant
    assert np.abs(run.states[2000:2400] - x_true[2000:2400]).max() < 0.2
    # the step that dropped the channel used the reduced gain: check it by hand
    k = 2000
    xm = system.Phi @ run.states[k - 1] + system.B0 @ u[k - 1] + system.B1 @ u[k]
    L = system.gain((0, 2))
    expect = xm + L[:, [0, 2]] @ (y[k, [0, 2]] - xm[[0, 3]])
    np.testing.assert_allclose(run.states[k], expect, rtol=0, atol=1e-12)  # float64 roundoff
    # after recovery the estimate returns to the fault-free one
    ff = fault_free_observer(system, x0, u, y * 0 + np.where(np.isfinite(y), y, 0))
    assert np.abs(run.states[-1] - ff[-1]).max() < 0.02


def test_anti_windup_railed_channel_gets_no_correction():
    system, u, y, _, x0 = playback(6000)
    rail_hi = float(np.quantile(y[:, 2], 0.6))      # ASIC ADC saturates at this reading
    clipped = y.copy()
    clipped[:, 2] = np.minimum(clipped[:, 2], rail_hi)
    rails = [(-np.inf, np.inf), (-np.inf, np.inf), (-np.inf, rail_hi)]
    obs = ref.FloatObserver(system, ref.FaultConfig(rails=rails))
    run = obs.run(x0, u, clipped)
    at_rail = clipped[:, 2] >= rail_hi
    assert at_rail.sum() > 100
    assert np.all(run.in_use[at_rail] == 0b011) and np.all(run.in_use[~at_rail] == 7)
    # windup: without the rail rule the clipped channel drags the estimate down
    naive = ref.FloatObserver(system).run(x0, u, clipped)
    truth = fault_free_observer(system, x0, u, y)
    err_aw = np.abs(run.states[at_rail, 3] - truth[at_rail, 3]).max()
    err_naive = np.abs(naive.states[at_rail, 3] - truth[at_rail, 3]).max()
    assert err_aw < err_naive / 3


def test_wire_break_flag_after_n_large_residuals():
    system, u, y, _, x0 = playback(6000)
    y = y.copy()
    y[3000:3500, 0] = 20.0      # housing sensor stuck at a plausible but wrong 20 °C
    N, M = 10, 40
    faults = ref.FaultConfig(residual_threshold=0.5, wire_break_after=N, recover_after=M)
    for obs in (ref.FloatObserver(system, faults),
                ref.FixedObserver(system, "q16.16",
                                  ref.FixedScaling(35.0, 35.0, (35.0, 0.0), (1.0, 1.0)), faults)):
        run = obs.run_physical(x0, u, y) if isinstance(obs, ref.FixedObserver) else \
            obs.run(x0, u, y)
        first_large = 3000 + np.argmax(np.abs(run.residuals[3000:, 0]) > 0.5)
        assert first_large == 3000
        assert not run.wire_break[first_large + N - 2] & 1
        assert run.wire_break[first_large + N - 1] & 1 and not run.in_use[first_large + N - 1] & 1
        assert np.all(run.in_use[first_large:first_large + N - 1] & 1)   # used until flagged
        # back after exactly M consecutive small residuals. It takes about a minute: the N
        # samples before the flag pulled the housing estimate toward 20 °C, and the
        # remaining sensors (pcb, asic) observe the housing only slowly.
        back = 3500 + np.argmax(run.in_use[3500:] & 1)
        assert back < 3500 + 2400
        assert np.all(np.abs(run.residuals[back - M + 1:back + 1, 0]) <= 0.5)
        assert np.abs(run.residuals[back - M, 0]) > 0.5 or back - M + 1 == 3500
        assert run.wire_break[back - 1] & 1 and not run.wire_break[back] & 1


def test_multirate_interpolation_has_no_steps():
    system, u, y, _, x0 = playback(1200)          # 1 min of 20 Hz -> 2 kHz
    K = np.array([[0.0, 0.0, 0.3, -0.3, 0.0, 0.0],     # gyro bias from the pcb-asic gradient
                  [0.0, 0.0, 0.0, 0.0, 1.5, -1.5]])    # and from mems - proof mass
    obs = ref.FloatObserver(system)
    R = 100
    mr = ref.run_multirate(obs, x0, u, y, K, ratio=R)
    jumps = np.abs(np.diff(mr.inertial, axis=0)).max(0)
    slope = np.abs(np.diff(mr.bias, axis=0)).max(0) / R
    assert np.all(jumps <= slope * (1 + 1e-9))                     # the slope bound
    assert np.all(np.abs(np.diff(mr.bias, axis=0)).max(0) > 10 * jumps)   # a step would be R x
    # the inertial value reaches each thermal value one thermal period later
    np.testing.assert_array_equal(mr.inertial[R - 1::R][1:], mr.bias[1:])
    # with publication jitter (task run time 0..90 ticks) still no step above twice the slope
    delay = np.random.default_rng(0).integers(0, 90, 1200)
    mrj = ref.run_multirate(obs, x0, u, y, K, ratio=R, delay_ticks=delay)
    assert np.all(np.abs(np.diff(mrj.inertial, axis=0)).max(0) <= 2 * slope * (1 + 1e-9))


def test_double_buffer_flips_after_write():
    buf = ref.DoubleBuffer(2)
    seq0, v0 = buf.read()
    buf.publish([1.0, 2.0])
    seq1, v1 = buf.read()
    assert seq1 == seq0 + 1 and v1.tolist() == [1.0, 2.0] and v0.tolist() == [0.0, 0.0]
    buf.publish([3.0, 4.0])
    assert buf.slots[1 - buf.published].tolist() == [1.0, 2.0]   # the old slot is intact
