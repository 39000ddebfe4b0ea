"""Adaptive-filter benchmark (issue 35 item 4): the six-node IMU with three ageing
conductances tracked (`pcb–asic`, `pcb–mems`, `bulkhead–pcb`), 2 h at 1 Hz (7,200
samples, 3 sensors), against the extended Kalman filter a user would write with SciPy.

- thermojax, study version: `thermojax.observer.track_conductances` (JAX, exact
  discretization per step by the matrix exponential, Jacobian by forward-mode
  differentiation, Van Loan process noise), first call (compilation included) and warm.
- SciPy, the expert peer: the same filter in NumPy, written plainly: per step
  `scipy.linalg.expm` of the augmented block matrix at the current conductances, the
  Jacobian in the conductances by `scipy.linalg.expm_frechet` of the same block (one per
  conductance), Van Loan's block exponential for the process noise, the same gate,
  ceiling and Joseph form. The two must agree (conductances within 1e-6 relative).
- Firmware: the NumPy reference (`thermojax.reference.AdaptiveReference`, plain Python
  floats, Tustin substeps) and its generated C (gcc -O2), per step.

Data: configs/imu6.toml with the three conductances at 80 % of nominal, 0.01 °C
noise, ambient ramps and switching ASIC power, simulated by SciPy (exact sampling).

Usage:  python benchmarks/adaptive_filter.py [--samples 7200]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import scipy.linalg  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))

import ten_year_ageing as study  # noqa: E402  (its profile and SciPy truth)

import thermojax.reference as ref  # noqa: E402
from thermojax.io import load_model  # noqa: E402
from thermojax.observer import adaptive_design, track_conductances  # noqa: E402
from thermojax.observer._adaptive import conductance_names  # noqa: E402

DRIFT, CEILING, EXCITATION = 5e-5, 0.5, 3.0


def scipy_ekf(spec, tracked, u, y, dt, x0):
    """The peer: the study version's filter in NumPy/SciPy (log conductances)."""
    C, links, bnd, heat, sensors, _ = study.network(spec)
    n, m, p = C.size, u.shape[1], len(sensors)
    names = conductance_names(spec)
    conds = [(a, b, g) for a, b, g in links] + [(a, -1 - c, g) for a, c, g in bnd]
    idx = [names.index(t) for t in tracked]
    k = len(idx)
    foh = np.array([h == "foh" for h in spec.input_holds], float)
    q = np.maximum(np.array([nd.process_noise.value if nd.process_noise else 1e-3
                             for nd in spec.nodes]), 1e-4)   # the model's default 1e-3
    R = np.diag([s.noise.value ** 2 for s in spec.sensors])

    def system(theta):
        g = np.array([c[2] for c in conds])
        g[idx] = np.exp(theta)
        K, B = np.zeros((n, n)), np.zeros((n, m))
        for (a, b, _), gi in zip(conds, g):
            if b >= 0:
                K[a, a] += gi; K[b, b] += gi; K[a, b] -= gi; K[b, a] -= gi  # noqa: E702
            else:
                K[a, a] += gi; B[a, -1 - b] += gi  # noqa: E702
        for a, c, gain in heat:
            B[a, c] += gain
        return -K / C[:, None], B / C[:, None]

    def block(A, B):
        Z = np.zeros
        return np.block([[A * dt, B * dt, Z((n, m))], [Z((m, n + m)), np.eye(m)],
                         [Z((m, n + 2 * m))]])

    def dblock(theta, j):
        """d block / d theta_j (the conductance j's pattern times its value)."""
        a, b, gi = conds[idx[j]]
        g = np.exp(theta[j])
        dK, dB = np.zeros((n, n)), np.zeros((n, m))
        if b >= 0:
            dK[a, a] = dK[b, b] = g
            dK[a, b] = dK[b, a] = -g
        else:
            dK[a, a] = g
            dB[a, -1 - b] = g
        return block(-dK / C[:, None], dB / C[:, None])

    H = np.zeros((p, n + k))
    H[np.arange(p), sensors] = 1.0
    every = np.log([c[2] for c in conds])
    z = np.concatenate([x0, every[idx]])
    P = np.diag(np.concatenate([np.ones(n), np.full(k, CEILING ** 2)]))
    out = np.empty((u.shape[0], k))
    ends = [conds[i] for i in idx]

    def correct(z, P, yk, uk):
        e = yk - H @ z
        S = H @ P @ H.T + R
        K = np.linalg.solve(S, H @ P).T
        for j, (a, b, _) in enumerate(ends):
            other = z[b] if b >= 0 else uk[-1 - b]
            var = P[a, a] + (P[b, b] - 2 * P[a, b] if b >= 0 else 0.0)
            if not abs(z[a] - other) > EXCITATION * np.sqrt(max(var, 0.0)):
                K[n + j] = 0.0
        IKH = np.eye(n + k) - K @ H
        P = IKH @ P @ IKH.T + K @ R @ K.T
        P = 0.5 * (P + P.T)
        s = np.sqrt(np.diag(P)[n:])
        sc = np.concatenate([np.ones(n), np.minimum(1.0, CEILING / s)])
        return z + K @ e, P * sc[:, None] * sc[None, :]

    z, P = correct(z, P, y[0], u[0])
    out[0] = np.exp(z[n:])
    for t in range(1, u.shape[0]):
        th = z[n:]
        A, B = system(th)
        Mb = block(A, B)
        E = scipy.linalg.expm(Mb)
        Phi, Gam, Lam = E[:n, :n], E[:n, n:n + m], E[:n, n + m:] * foh
        xk = Phi @ z[:n] + Gam @ u[t - 1] + Lam @ (u[t] - u[t - 1])
        F = np.eye(n + k)
        F[:n, :n] = Phi
        for j in range(k):
            dE = scipy.linalg.expm_frechet(Mb, dblock(th, j), compute_expm=False)
            F[:n, n + j] = (dE[:n, :n] @ z[:n] + dE[:n, n:n + m] @ u[t - 1]
                            + (dE[:n, n + m:] * foh) @ (u[t] - u[t - 1]))
        vl = scipy.linalg.expm(np.block([[-A, np.diag(q ** 2)], [np.zeros((n, n)), A.T]])
                               * dt)
        Qx = vl[n:, n:].T @ vl[:n, n:]
        Q = scipy.linalg.block_diag(0.5 * (Qx + Qx.T), np.diag(np.full(k, DRIFT ** 2 * dt)))
        z, P = correct(np.concatenate([xk, th]), F @ P @ F.T + Q, y[t], u[t])
        out[t] = np.exp(z[n:])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=7200)
    args = parser.parse_args()
    spec = load_model(study.MODEL)
    u, _ = study.profile()
    u = u[:args.samples]
    nominal = {k: p for k, p in zip(study.TRACKED, (0.02, 0.01, 0.1))}
    truth_spec = study.with_conductances(spec, {k: 0.8 * v for k, v in nominal.items()})
    x, y = study.simulate(truth_spec, u, np.random.default_rng(0))
    tracked = list(study.TRACKED)
    kw = dict(drift=DRIFT, ceiling=CEILING, x0=x[0])

    t0 = time.perf_counter()
    track_conductances(spec, tracked, u, y, study.DT, **kw)  # compiles
    t_first = time.perf_counter() - t0
    t0 = time.perf_counter()
    warm = track_conductances(spec, tracked, u, y, study.DT, **kw)
    t_warm = time.perf_counter() - t0

    t0 = time.perf_counter()
    peer = scipy_ekf(spec, tracked, u, y, study.DT, x[0])
    t_peer = time.perf_counter() - t0
    agree = float(np.abs(peer / warm.conductances - 1).max())

    design = adaptive_design(spec, tracked, study.DT, DRIFT, ceiling=CEILING)
    t0 = time.perf_counter()
    fw = ref.AdaptiveReference(design).run(x[0], u, y)
    t_ref = time.perf_counter() - t0
    src = ref.generate_adaptive_c(design, "tj_adaptive")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for name, text in (("tj_adaptive.h", src.header), ("tj_adaptive.c", src.source),
                           ("main.c", src.harness)):
            (tmp / name).write_text(text)
        subprocess.run(["gcc", "-std=c99", "-O2", "-ffp-contract=off", "-o",
                        str(tmp / "prog"), str(tmp / "tj_adaptive.c"), str(tmp / "main.c"),
                        "-lm"], check=True)
        (tmp / "in.bin").write_bytes(ref.pack_adaptive(x[0], u, y))
        t0 = time.perf_counter()
        subprocess.run([str(tmp / "prog"), str(tmp / "in.bin"), str(tmp / "out.bin")],
                       check=True)
        t_c = time.perf_counter() - t0
        c_run = ref.unpack_adaptive((tmp / "out.bin").read_bytes(), design.n, design.k)
    exact = all(np.array_equal(getattr(c_run, f), getattr(fw, f))
                for f in ("states", "conductances", "variances", "nis", "flags"))
    T = u.shape[0]
    truth = np.array([0.8 * nominal[k] for k in tracked])
    print(f"six-node IMU, {T} samples at 1 Hz, 3 sensors, 3 conductances tracked "
          f"({design.substeps} Tustin substeps in the firmware version)")
    print(f"thermojax (JAX) first call {t_first:.2f} s, warm {t_warm:.2f} s "
          f"({1e6 * t_warm / T:.0f} µs a step)")
    print(f"SciPy EKF {t_peer:.2f} s ({1e6 * t_peer / T:.0f} µs a step); "
          f"ratio SciPy / thermojax: first {t_peer / t_first:.1f}x, warm "
          f"{t_peer / t_warm:.1f}x; conductances agree to {agree:.1e}")
    print(f"firmware reference (Python floats) {t_ref:.2f} s; C (-O2, playback with file "
          f"I/O) {t_c:.3f} s ({1e6 * t_c / T:.1f} µs a step); bit-exact: {exact}")
    print("end estimate / truth: JAX " + ", ".join(f"{v:.4f}" for v in
                                                   warm.conductances[-1] / truth)
          + "; firmware " + ", ".join(f"{v:.4f}" for v in fw.conductances[-1] / truth))


if __name__ == "__main__":
    main()
