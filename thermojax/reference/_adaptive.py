"""The adaptive filter for firmware: node temperatures and drifting conductances, in
float64, operation for operation as the generated C (`_adaptive_c.py`).

The study version (`thermojax.observer.track_conductances`, JAX) discretizes exactly with
the matrix exponential; a microcontroller cannot afford one per step, so this one
integrates each sample period with `N` trapezoidal (Tustin) substeps, A-stable on any
network, and carries the sensitivities with it:

    M = diag(C) + (h/2) K(g),   N = diag(C) − (h/2) K(g),   h = dt / N_sub
    M x' = N x + (h/2) B(g) (u_s + u_s+1)
    M D' = N D                                  (D = ∂x/∂x[k−1], from I)
    M S_j' = N S_j − (h/2) ∂K/∂g_j (x + x') + (h/2) ∂B/∂g_j (u_s + u_s+1)   (from 0)

`K(g)` the conductance matrix, `B(g)` the boundary conductances and heat gains, `M`
factorized once a step (LU without pivoting: `M` is strictly diagonally dominant). The
conductances `g` themselves (W/K, not their logs: no transcendental function, so the C and
NumPy agree bit for bit on any libm) are random walks of relative intensity `drift`:
`Q_g = (drift g)² dt`; the nodes' process noise `Q_x = q² dt`. The correction is the
Joseph form with the study version's excitation gate (`Δ² > excitation² var Δ`), relative
covariance ceiling (std of `g` at most `ceiling · g`), χ² step detection over a ring of
`window` normalized innovations and reacquisition; `g` is floored at `1e-6` of its nominal
value.

Every sum runs in index order, every product as written, in double (`-ffp-contract=off`
in C): a Python float is a C double.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np


@dataclasses.dataclass(frozen=True)
class AdaptiveDesign:
    """Everything the firmware filter needs (built by
    `thermojax.observer.adaptive_design`):

    - `capacitance (n,)` J/K; `links` `(a, b, g)`; `boundaries` `(node, input, g)`;
      `heats` `(node, input, gain)`; `sensors` node per output; `holds` per input;
    - `tracked`: indices into links + boundaries of the conductances estimated;
    - `dt` s, `substeps`; `process_noise (n,)` °C/√s; `sensor_noise (p,)` °C;
    - `drift (k,)` per √s (relative), `ceiling (k,)` (relative std), `excitation`,
      `window` samples, `threshold` (windowed NIS), `reacquire`, `initial_std` °C.
    """

    capacitance: tuple
    links: tuple
    boundaries: tuple
    heats: tuple
    sensors: tuple
    holds: tuple
    tracked: tuple
    dt: float
    substeps: int
    process_noise: tuple
    sensor_noise: tuple
    drift: tuple
    ceiling: tuple
    excitation: float
    window: int
    threshold: float
    reacquire: bool
    initial_std: float

    @property
    def n(self) -> int:
        return len(self.capacitance)

    @property
    def k(self) -> int:
        return len(self.tracked)

    def conductance(self, i: int) -> tuple:
        """`(a, b, c, g)` of conductance `i` (links then boundaries): `b` −1 for a
        boundary, `c` its input (−1 for a link)."""
        if i < len(self.links):
            a, b, g = self.links[i]
            return int(a), int(b), -1, float(g)
        a, c, g = self.boundaries[i - len(self.links)]
        return int(a), -1, int(c), float(g)


@dataclasses.dataclass(frozen=True, eq=False)
class AdaptiveReferenceRun:
    """Per sample: `states (T, n)`, `conductances (T, k)` W/K, `variances (T, n + k)`
    (the diagonal of `P`), `nis (T,)`, `flags (T,)` bool."""

    states: np.ndarray
    conductances: np.ndarray
    variances: np.ndarray
    nis: np.ndarray
    flags: np.ndarray
    # bit masks per sample of the inputs held and the readings not trusted
    # (`_sample_guard`); None from the C harness
    input_fault: np.ndarray | None = None
    reading_fault: np.ndarray | None = None


#: W: a heat input beyond this is not a plausible sample (held as a fault).
MAX_POWER_W = 1e6


def adaptive_input_limits(design, reading_limits=None) -> np.ndarray:
    """`(m, 2)` input limits of the adaptive filter: a boundary temperature within the
    plausibility limits, any other input (a power) within ±`MAX_POWER_W`."""
    from ._sample_guard import READING_LIMITS

    lim = READING_LIMITS if reading_limits is None else reading_limits
    temps = {c for _, c, _ in design.boundaries}
    return np.array([list(lim) if j in temps else [-MAX_POWER_W, MAX_POWER_W]
                     for j in range(len(design.holds))], float).reshape(-1, 2)


def _product(A, B):
    """`A @ B` of square lists, each sum from 0.0 in index order (the C's loops)."""
    n = len(A)
    out = [[0.0] * n for _ in range(n)]
    for r in range(n):
        for c in range(n):
            acc = 0.0
            for j in range(n):
                acc = acc + A[r][j] * B[j][c]
            out[r][c] = acc
    return out


def _product_t(A, B):
    """`A @ Bᵀ` of square lists, in the same order."""
    n = len(A)
    out = [[0.0] * n for _ in range(n)]
    for r in range(n):
        for c in range(n):
            acc = 0.0
            for j in range(n):
                acc = acc + A[r][j] * B[c][j]
            out[r][c] = acc
    return out


def _lu(A):
    """In place LU without pivoting (Doolittle), the C's order."""
    n = len(A)
    for c in range(n):
        for i in range(c + 1, n):
            A[i][c] = A[i][c] / A[c][c]
            for j in range(c + 1, n):
                A[i][j] = A[i][j] - A[i][c] * A[c][j]


def _solve(LU, b):
    """`x` of `LU x = b` (forward then back substitution)."""
    n = len(LU)
    x = list(b)
    for i in range(n):
        for j in range(i):
            x[i] = x[i] - LU[i][j] * x[j]
    for i in range(n - 1, -1, -1):
        for j in range(i + 1, n):
            x[i] = x[i] - LU[i][j] * x[j]
        x[i] = x[i] / LU[i][i]
    return x


class AdaptiveReference:
    """The firmware adaptive filter in plain float64 Python (see the module)."""

    def __init__(self, design: AdaptiveDesign):
        from ._sample_guard import SampleGuard

        self.d = design
        d = design
        self.guard = SampleGuard(adaptive_input_limits(design))
        self.input_fault = self.reading_fault = 0
        self.g_nominal = [d.conductance(i)[3] for i in d.tracked]
        self.g_min = [1e-6 * g for g in self.g_nominal]
        self.h = d.dt / float(d.substeps)
        self.hh = 0.5 * self.h

    def reset(self, x0) -> None:
        d = self.d
        n, k = d.n, d.k
        self.x = [float(v) for v in x0]
        self.g = list(self.g_nominal)
        s = d.initial_std * d.initial_std
        self.P = [[0.0] * (n + k) for _ in range(n + k)]
        for i in range(n):
            self.P[i][i] = s
        for j in range(k):
            c = d.ceiling[j] * self.g[j]
            self.P[n + j][n + j] = c * c
        self.buf = [0.0] * d.window
        self.guard.reset()
        self.count = 0
        self.u_prev = None

    # -- the model at the current conductances --------------------------------------------
    def _matrices(self):
        d = self.d
        n, m = d.n, len(d.holds)
        g_all = [d.conductance(i)[3] for i in range(len(d.links) + len(d.boundaries))]
        for j, i in enumerate(d.tracked):
            g_all[i] = self.g[j]
        K = [[0.0] * n for _ in range(n)]
        B = [[0.0] * m for _ in range(n)]
        for l, (a, b, _) in enumerate(d.links):
            g = g_all[l]
            K[a][a] = K[a][a] + g
            K[b][b] = K[b][b] + g
            K[a][b] = K[a][b] - g
            K[b][a] = K[b][a] - g
        for i, (a, c, _) in enumerate(d.boundaries):
            g = g_all[len(d.links) + i]
            K[a][a] = K[a][a] + g
            B[a][c] = B[a][c] + g
        for a, c, gain in d.heats:
            B[a][c] = B[a][c] + gain
        return K, B

    def _predict(self, u):
        """`(x⁻, F)` over one sample period from `u_prev` to `u`."""
        d, hh = self.d, self.hh
        n, k, m, N = d.n, d.k, len(d.holds), d.substeps
        K, B = self._matrices()
        M = [[(d.capacitance[i] if i == j else 0.0) + hh * K[i][j] for j in range(n)]
             for i in range(n)]
        Nm = [[(d.capacitance[i] if i == j else 0.0) - hh * K[i][j] for j in range(n)]
              for i in range(n)]
        _lu(M)
        x = list(self.x)
        D = [[1.0 if i == j else 0.0 for j in range(n)] for i in range(n)]   # D[i][col]
        S = [[0.0] * k for _ in range(n)]
        up = self.u_prev

        def u_at(s):
            fr = float(s) / float(N)
            return [up[c] + (u[c] - up[c]) * fr if d.holds[c] == "foh" else up[c]
                    for c in range(m)]

        for s in range(N):
            ua, ub = u_at(s), u_at(s + 1)
            w = [ua[c] + ub[c] for c in range(m)]
            rhs = [0.0] * n
            for i in range(n):
                acc = 0.0
                for j in range(n):
                    acc = acc + Nm[i][j] * x[j]
                bw = 0.0
                for c in range(m):
                    bw = bw + B[i][c] * w[c]
                rhs[i] = acc + hh * bw
            x_new = _solve(M, rhs)
            D_new = [[0.0] * n for _ in range(n)]
            for col in range(n):
                r = [0.0] * n
                for i in range(n):
                    acc = 0.0
                    for j in range(n):
                        acc = acc + Nm[i][j] * D[j][col]
                    r[i] = acc
                v = _solve(M, r)
                for i in range(n):
                    D_new[i][col] = v[i]
            S_new = [[0.0] * k for _ in range(n)]
            for jj in range(k):
                a, b, c, _ = d.conductance(d.tracked[jj])
                r = [0.0] * n
                for i in range(n):
                    acc = 0.0
                    for j in range(n):
                        acc = acc + Nm[i][j] * S[j][jj]
                    r[i] = acc
                if b >= 0:
                    delta = (x[a] + x_new[a]) - (x[b] + x_new[b])
                    r[a] = r[a] - hh * delta
                    r[b] = r[b] + hh * delta
                else:
                    delta = (x[a] + x_new[a]) - w[c]
                    r[a] = r[a] - hh * delta
                v = _solve(M, r)
                for i in range(n):
                    S_new[i][jj] = v[i]
            x, D, S = x_new, D_new, S_new
        F = [[0.0] * (n + k) for _ in range(n + k)]
        for i in range(n):
            for j in range(n):
                F[i][j] = D[i][j]
            for jj in range(k):
                F[i][n + jj] = S[i][jj]
        for jj in range(k):
            F[n + jj][n + jj] = 1.0
        return x, F

    def _correct(self, z, P, y, u):
        """Joseph-form correction with the gate, the ceiling; returns `(z, P, nis)`."""
        d = self.d
        n, k, p = d.n, d.k, len(d.sensors)
        nk = n + k
        sen = d.sensors
        ok = [math.isfinite(v) for v in y]  # the guard made an untrusted reading NaN
        e = [y[i] - z[sen[i]] if ok[i] else 0.0 for i in range(p)]
        Sm = [[P[sen[i]][sen[j]] + (d.sensor_noise[i] * d.sensor_noise[i] if i == j else 0.0)
               for j in range(p)] for i in range(p)]
        _lu(Sm)
        Kt = [_solve(Sm, [P[sen[i]][c] for i in range(p)]) for c in range(nk)]  # Kt[c] = K row c
        for jj in range(k):
            a, b, c, _ = d.conductance(d.tracked[jj])
            if b >= 0:
                delta = z[a] - z[b]
                var = (P[a][a] + P[b][b]) - 2.0 * P[a][b]
            else:
                delta = z[a] - u[c]
                var = P[a][a]
            if not delta * delta > (d.excitation * d.excitation) * var:
                Kt[n + jj] = [0.0] * p
        for i in range(p):  # an untrusted reading corrects nothing (Joseph form: any gain)
            if not ok[i]:
                for r in range(nk):
                    Kt[r][i] = 0.0
        v = _solve(Sm, e)
        nis = 0.0
        for i in range(p):
            nis = nis + e[i] * v[i]
        z_new = list(z)
        for r in range(nk):
            acc = 0.0
            for i in range(p):
                acc = acc + Kt[r][i] * e[i]
            z_new[r] = z[r] + acc
        A = [[(1.0 if r == c else 0.0) for c in range(nk)] for r in range(nk)]
        for r in range(nk):
            for i in range(p):
                A[r][sen[i]] = A[r][sen[i]] - Kt[r][i]
        APA = _product_t(_product(A, P), A)
        Pn = [[0.0] * nk for _ in range(nk)]
        for r in range(nk):
            for c in range(nk):
                kr = 0.0
                for i in range(p):
                    kr = kr + Kt[r][i] * (d.sensor_noise[i] * d.sensor_noise[i]) * Kt[c][i]
                Pn[r][c] = APA[r][c] + kr
        for r in range(nk):
            for c in range(r + 1, nk):
                s = 0.5 * (Pn[r][c] + Pn[c][r])
                Pn[r][c] = s
                Pn[c][r] = s
        for jj in range(k):
            q = n + jj
            z_new[q] = max(z_new[q], self.g_min[jj])
            cap = d.ceiling[jj] * z_new[q]
            if Pn[q][q] > cap * cap:
                sc = cap / math.sqrt(Pn[q][q])
                for c in range(nk):
                    Pn[q][c] = Pn[q][c] * sc
                for r in range(nk):
                    Pn[r][q] = Pn[r][q] * sc
        return z_new, Pn, nis

    def step(self, u, y) -> tuple[bool, float]:
        """One sample: `u (m,)`, `y (p,)`; returns `(flag, nis)`."""
        d = self.d
        n, k = d.n, d.k
        nk = n + k
        u, self.input_fault = self.guard.inputs([float(v) for v in u])
        y, self.reading_fault = self.guard.readings([float(v) for v in y])
        if self.u_prev is None:
            z, P = self.x + self.g, self.P
        else:
            x, F = self._predict(u)
            z = x + self.g
            P = _product_t(_product(F, self.P), F)
            for i in range(n):
                P[i][i] = P[i][i] + (d.process_noise[i] * d.process_noise[i]) * d.dt
            for jj in range(k):
                s = d.drift[jj] * self.g[jj]
                P[n + jj][n + jj] = P[n + jj][n + jj] + (s * s) * d.dt
        z, P, nis = self._correct(z, P, y, u)
        self.x, self.g, self.P = z[:n], z[n:], P
        self.buf[self.count % d.window] = nis
        self.count += 1
        total = 0.0
        for v in self.buf:
            total = total + v
        flag = total > d.threshold
        if flag and d.reacquire:
            for jj in range(k):
                q = n + jj
                for c in range(nk):
                    P[q][c] = 0.0
                    P[c][q] = 0.0
                cap = d.ceiling[jj] * self.g[jj]
                P[q][q] = cap * cap
            self.buf = [0.0] * d.window
        self.u_prev = u
        return flag, nis

    def run(self, x0, u, y) -> AdaptiveReferenceRun:
        """Play back `u (T, m)`, `y (T, p)` from `x0 (n,)`."""
        u, y = np.asarray(u, float), np.asarray(y, float)
        T = u.shape[0]
        n, k = self.d.n, self.d.k
        xs, gs = np.empty((T, n)), np.empty((T, k))
        vs, nis, flags = np.empty((T, n + k)), np.empty(T), np.zeros(T, bool)
        u_fault, y_fault = np.zeros(T, np.int64), np.zeros(T, np.int64)
        self.reset(x0)
        for t in range(T):
            flags[t], nis[t] = self.step(u[t], y[t])
            u_fault[t], y_fault[t] = self.input_fault, self.reading_fault
            xs[t], gs[t] = self.x, self.g
            vs[t] = [self.P[i][i] for i in range(n + k)]
        return AdaptiveReferenceRun(xs, gs, vs, nis, flags, u_fault, y_fault)
