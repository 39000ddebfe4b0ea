"""The float reference observer (float64, float32) against independent implementations."""

import subprocess
import sys

import numpy as np
import pytest

from test_reference_setup import IMU6_SCALING, fault_free_observer, imu6_system, playback

import thermojax.reference as ref


def independent_loop(system, x0, u, y, masks):
    """Plain float64 two-phase observer with the gain chosen by a given mask sequence."""
    x = np.array(x0, float)
    out = np.empty((u.shape[0], system.n_states))
    for k in range(u.shape[0]):
        if k:
            x = system.Phi @ x + system.B0 @ u[k - 1] + system.B1 @ u[k]
        r = y[k] - system.C @ x - system.D @ u[k]
        use = np.array([(masks[k] >> j) & 1 for j in range(system.n_outputs)], bool)
        if use.any():
            x = x + system.gain_table[masks[k]][:, use] @ r[use]
        out[k] = x
    return out


def test_float64_equals_independent_filter():
    system, u, y, x_true, x0 = playback(24_000)  # 20 min at 20 Hz
    run = ref.FloatObserver(system).run(x0, u, y)
    expected = fault_free_observer(system, x0, u, y)
    np.testing.assert_allclose(run.states, expected, rtol=0, atol=1e-12 * 130)  # 1e-12 relative to ~100 °C
    assert np.all(run.in_use == 7)
    assert np.abs(run.states - x_true).max() < 0.1  # and it tracks the plant (noise 0.01 K)


def test_float64_with_faults_equals_independent_loop():
    system, u, y, _, x0 = playback(6000)
    y = y.copy()
    y[1000:1500, 1] = np.nan           # open circuit: pcb sensor
    y[3000:3010, 2] = 150.0            # implausible spike: asic sensor
    run = ref.FloatObserver(system).run(x0, u, y)
    assert set(np.unique(run.in_use)) == {7, 5, 3}
    expected = independent_loop(system, x0, u, y, run.in_use)
    np.testing.assert_allclose(run.states, expected, rtol=0, atol=1e-12 * 130)  # float64 roundoff


def test_float32_close_to_float64_and_deterministic():
    system, u, y, _, x0 = playback(6000)
    r64 = ref.FloatObserver(system).run(x0, u, y)
    obs = ref.FloatObserver(system, dtype=np.float32)
    a, b = obs.run(x0, u, y), obs.run(x0, u, y)
    assert a.states.dtype == np.float32
    assert np.array_equal(a.states, b.states)                 # run to run, bit for bit
    assert np.abs(a.states - r64.states).max() < 2e-3         # float32: ~1e-5 K per step, damped


def test_bad_arguments():
    system = imu6_system()
    with pytest.raises(ValueError, match="expected float64 or float32"):
        ref.FloatObserver(system, dtype=np.float16)
    with pytest.raises(ValueError, match=r"expected \(T, 2\) and \(T, 3\)"):
        ref.FloatObserver(system).run(np.zeros(6), np.zeros((5, 3)), np.zeros((5, 3)))
    Phi, B0, B1, C, D = system.Phi, system.B0, system.B1, system.C, system.D
    with pytest.raises(ValueError, match="lacks the gains for sensor subsets"):
        ref.ObserverSystem.build(Phi, B0, B1, C, D, {(0, 1, 2): system.L})
    with pytest.raises(ValueError, match="inconsistent shapes"):
        ref.ObserverSystem.build(Phi, B0, B1, C[:, :5], D, system.L)
    with pytest.raises(ValueError, match="not an equilibrium"):
        ref.FixedObserver(system, "q16.16", ref.FixedScaling(35.0, 35.0, (0.0, 0.0), (1.0, 1.0)))
    with pytest.raises(ValueError, match="cannot hold the limits"):
        ref.FixedObserver(system, ref.FixedFormat("q4.28", 32, 28, 1.0), IMU6_SCALING["q16.16"])
    with pytest.raises(ValueError, match="unknown format"):
        ref.fixed_format("q12.20")


def test_reference_imports_without_jax():
    code = ("import sys; sys.modules['jax'] = None; import thermojax.reference as r; "
            "assert not any(m == 'jax' or m.startswith(('jax.', 'jaxlib', 'equinox')) "
            "for m in sys.modules if sys.modules[m] is not None)")
    subprocess.run([sys.executable, "-c", code], check=True)
