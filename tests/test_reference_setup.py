"""Shared builders for the `thermojax.reference` tests (imported by the other
`test_reference_*.py` files), and checks of the builders themselves.

The six-node IMU (`configs/imu6.toml`) is read with `tomllib` and discretized at 20 Hz by
`scipy.linalg.expm` of the augmented matrix (`helpers.np_discretize`); the gains are
steady-state Kalman gains from `scipy.linalg.solve_discrete_are`, one per sensor subset.
"""

import itertools

import numpy as np
import scipy.linalg
import scipy.signal

from helpers import CONFIGS, model_matrices, np_discretize

import thermojax.reference as ref

DT = 0.05            # 20 Hz observer
T_REF = 35.0         # fixed-point reference temperature (°C)
Q_DIFFUSION = 0.01   # the test builders' process noise, K/sqrt(s) on every node (export uses 1e-3)
SENSOR_NOISE = 0.01  # K, the model file's sensor noise


def imu6_matrices(dt=DT):
    net = model_matrices(CONFIGS / "imu6.toml")
    Phi, B0, B1 = np_discretize(net["A"], net["B"], dt, net["holds"])
    C = net["Cy"]
    D = np.zeros((C.shape[0], B0.shape[1]))
    return Phi, B0, B1, C, D, net


def kalman_gain(Phi, C, Qd, R):
    """Filter-form steady-state Kalman gain `P⁻ Cᵀ (C P⁻ Cᵀ + R)⁻¹` from the DARE."""
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, R)
    return P @ C.T @ np.linalg.inv(C @ P @ C.T + R)


def subset_gains(Phi, C, dt=DT):
    n, p = Phi.shape[0], C.shape[0]
    Qd = (Q_DIFFUSION ** 2 * dt) * np.eye(n)
    gains = {}
    for r in range(1, p + 1):
        for s in itertools.combinations(range(p), r):
            Cs = C[list(s)]
            gains[frozenset(s)] = kalman_gain(Phi, Cs, Qd, SENSOR_NOISE ** 2 * np.eye(len(s)))
    return gains


def imu6_system(dt=DT):
    Phi, B0, B1, C, D, _ = imu6_matrices(dt)
    return ref.ObserverSystem.build(Phi, B0, B1, C, D, subset_gains(Phi, C, dt))


IMU6_SCALING = {  # T_chamber is a temperature (offset 35 °C), P_asic a power (offset 0, 1 W)
    "q16.16": ref.FixedScaling(T_REF, T_REF, (T_REF, 0.0), (1.0, 1.0)),
    "q8.24": ref.FixedScaling(T_REF, T_REF, (T_REF, 0.0), (1.0, 1.0)),
    "q15": ref.FixedScaling(T_REF, T_REF, (T_REF, 0.0), (128.0, 1.0)),
    "q31": ref.FixedScaling(T_REF, T_REF, (T_REF, 0.0), (128.0, 1.0)),
}


def chamber_profile(steps, dt=DT, seed=0, low=-40.0, high=85.0):
    """Chamber temperature (plateaus of 5-40 min joined by 1-10 °C/min ramps, FOH) and
    ASIC power (0.05-0.4 W, steps every 1-30 min, ZOH), `(steps, 2)`."""
    rng = np.random.default_rng(seed)
    t_knots, T_knots = [0.0], [25.0]
    while t_knots[-1] < steps * dt:
        target = rng.uniform(low, high)
        ramp = abs(target - T_knots[-1]) / (rng.uniform(1, 10) / 60)
        t_knots += [t_knots[-1] + ramp, t_knots[-1] + ramp + rng.uniform(300, 2400)]
        T_knots += [target, target]
    t = np.arange(steps) * dt
    T = np.interp(t, t_knots, T_knots)
    P = np.empty(steps)
    k = 0
    while k < steps:
        n = int(rng.uniform(60, 1800) / dt)
        P[k:k + n] = rng.uniform(0.05, 0.4)
        k += n
    return np.stack([T, P], 1)


def simulate_plant(Phi, B0, B1, C, D, x0, u):
    """Exact noiseless plant `x[k] = Phi x[k-1] + B0 u[k-1] + B1 u[k]`, by modal IIR
    filters (`scipy.signal.lfilter`, one per eigenvalue), returns `(x, y)`."""
    lam, V = np.linalg.eig(Phi)
    Vi = np.linalg.inv(V)
    drive = np.zeros((u.shape[0], Phi.shape[0]), complex)
    drive[1:] = (u[:-1] @ B0.T + u[1:] @ B1.T) @ Vi.T
    z0 = Vi @ x0
    z = np.empty_like(drive)
    for i in range(len(lam)):
        d = drive[:, i].copy()
        d[0] = z0[i]
        z[:, i] = scipy.signal.lfilter([1.0], [1.0, -lam[i]], d)
    x = (z @ V.T).real
    return x, x @ C.T + u @ D.T


def steady_state(Phi, B0, B1, u0):
    return np.linalg.solve(np.eye(Phi.shape[0]) - Phi, (B0 + B1) @ u0)


def playback(steps, seed=0, noise=SENSOR_NOISE, dt=DT):
    """A chamber playback through imu6: `(system, u, y, x_true, x0)`."""
    Phi, B0, B1, C, D, _ = imu6_matrices(dt)
    system = imu6_system(dt)
    u = chamber_profile(steps, dt, seed)
    x0 = steady_state(Phi, B0, B1, u[0])
    x, y = simulate_plant(Phi, B0, B1, C, D, x0, u)
    y = y + noise * np.random.default_rng(seed + 1).standard_normal(y.shape)
    return system, u, y, x, x0


# -- checks of the builders ---------------------------------------------------------------

def test_discretization_matches_thermojax():
    """scipy's augmented `expm` and thermojax's JAX `discretize` agree (two implementations)."""
    import thermojax as tj

    net = tj.ThermalNetwork.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    d = tj.discretize(net.linear_system(), DT)
    Phi, B0, B1, *_ = imu6_matrices()
    for a, b in ((d.Phi, Phi), (d.B0, B0), (d.B1, B1)):
        np.testing.assert_allclose(np.asarray(a), b, rtol=0, atol=1e-13)  # both exact; roundoff


def test_plant_simulation_matches_loop():
    """The modal `lfilter` plant equals the plain state recursion."""
    Phi, B0, B1, C, D, _ = imu6_matrices()
    u = chamber_profile(2000)
    x0 = steady_state(Phi, B0, B1, u[0])
    x, _ = simulate_plant(Phi, B0, B1, C, D, x0, u)
    xs = x0.copy()
    for k in range(1, 2000):
        xs = Phi @ xs + B0 @ u[k - 1] + B1 @ u[k]
    np.testing.assert_allclose(x[-1], xs, rtol=0, atol=1e-9)  # eigenbasis roundoff over 2000 steps


def test_gains_stabilize_every_subset():
    system = imu6_system()
    for r in range(1, 4):
        for s in itertools.combinations(range(3), r):
            rho = np.abs(np.linalg.eigvals(system.error_dynamics(s))).max()
            assert rho < 1.0


def modal_filter(A, drive, z0):
    """`z[0] = z0`, `z[k] = A z[k-1] + drive[k]` by one IIR filter per eigenvalue."""
    lam, V = np.linalg.eig(A)
    Vi = np.linalg.inv(V)
    d = drive.astype(complex) @ Vi.T
    d[0] = Vi @ z0
    z = np.empty_like(d)
    for i in range(len(lam)):
        z[:, i] = scipy.signal.lfilter([1.0], [1.0, -lam[i]], d[:, i])
    return (z @ V.T).real


def fault_free_observer(system, x0, u, y):
    """The float64 observer without faults as an LTI filter (an independent implementation):
    `x[k] = A_e x[k-1] + (I - L C)(B0 u[k-1] + B1 u[k]) + L (y[k] - D u[k])`."""
    L, C, D = system.L, system.C, system.D
    ILC = np.eye(system.n_states) - L @ C
    drive = np.zeros((u.shape[0], system.n_states))
    drive[1:] = (u[:-1] @ system.B0.T + u[1:] @ system.B1.T) @ ILC.T
    drive += (y - u @ D.T) @ L.T
    x00 = x0 + L @ (y[0] - C @ x0 - D @ u[0])
    return modal_filter(system.error_dynamics(), drive, x00)


def gcc_build(src, folder, *flags):
    """Compile a `CSource` with its harness; return the program's path."""
    import shutil
    import subprocess

    assert shutil.which("gcc") is not None, \
        "gcc is required for the generated-C tests (install the system package `gcc`)."
    paths = src.write(folder)
    exe = folder / f"{src.prefix}_prog"
    subprocess.run(["gcc", "-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror",
                    "-ffp-contract=off", *flags, "-o", str(exe), str(paths["source"]),
                    str(paths["harness"]), "-lm"], check=True, capture_output=True, text=True)
    return exe


def gcc_run(src, exe, folder, x0, u, y, open_mask=None):
    import subprocess

    (folder / "in.bin").write_bytes(src.pack_playback(x0, u, y, open_mask))
    subprocess.run([str(exe), str(folder / "in.bin"), str(folder / "out.bin")], check=True)
    return src.unpack_output((folder / "out.bin").read_bytes())


def test_fault_free_filter_matches_loop():
    """The LTI form of the observer equals the plain two-phase loop (both in the test)."""
    system, u, y, _, x0 = playback(3000)
    xf = fault_free_observer(system, x0, u, y)
    x = x0.copy()
    for k in range(3000):
        if k:
            x = system.Phi @ x + system.B0 @ u[k - 1] + system.B1 @ u[k]
        x = x + system.L @ (y[k] - system.C @ x - system.D @ u[k])
    np.testing.assert_allclose(xf[-1], x, rtol=0, atol=1e-9)  # eigenbasis roundoff
