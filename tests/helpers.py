"""Shared test helpers: tolerant tree comparison, random networks, model paths."""

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import thermojax as tj

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"

# A one-room building (Bacher & Madsen's Ti) with an envelope mass added by an effect.
ROOM_WITH_ENVELOPE = """
[[nodes]]
name = "Ti"
capacitance = 1e6
[[boundaries]]
node = "Ti"
input = "Ta"
conductance = 200.0
[[heat_inputs]]
node = "Ti"
input = "Ps"
gain = 5.0
[[sensors]]
node = "Ti"
column = "yTi"
noise = 0.01
[[effects]]
kind = "extra_node"
where = ["Ti", "Ta"]
name = "Te"
capacitance = 1e7
conductance = 400.0
conductance_b = 400.0
"""


def tree_allclose(x, y, *, rtol=1e-5, atol=1e-8):
    return eqx.tree_equal(x, y, typematch=True, rtol=rtol, atol=atol)


def random_topology(rng: np.random.Generator, n: int, grounded: bool = True,
                    n_heat: int = 1) -> tj.Topology:
    """A random connected network of `n` nodes (a random spanning tree plus extra links).

    With `grounded`, one or more nodes get a boundary; otherwise none does.
    """
    links = set()
    for i in range(1, n):
        links.add((int(rng.integers(0, i)), i))
    for _ in range(int(rng.integers(0, n))):
        i, j = sorted(rng.choice(n, 2, replace=False).tolist())
        links.add((i, j))
    b_nodes = tuple(sorted(rng.choice(n, int(rng.integers(1, min(3, n) + 1)), replace=False).tolist())) \
        if grounded else ()
    h_nodes = tuple(int(x) for x in rng.choice(n, n_heat, replace=True))
    inputs = ("T_amb",) + tuple(f"P{k}" for k in range(n_heat))
    return tj.Topology(
        node_names=tuple(f"n{i}" for i in range(n)),
        links=tuple(sorted(links)),
        boundary_nodes=b_nodes,
        boundary_inputs=tuple(0 for _ in b_nodes),
        heat_nodes=h_nodes,
        heat_inputs=tuple(1 + k for k in range(n_heat)),
        input_names=inputs,
        input_holds=("foh",) + ("zoh",) * n_heat,
        sensor_nodes=(0,),
        sensor_names=("T0",),
    )


def random_network(rng: np.random.Generator, n: int, grounded: bool = True) -> tj.ThermalNetwork:
    """Random network with capacitances 1e-3..10 J/K and conductances 1e-3..1 W/K."""
    topo = random_topology(rng, n, grounded)
    return tj.ThermalNetwork.from_physical(
        topo,
        capacitance=10 ** rng.uniform(-3, 1, n),
        conductance=10 ** rng.uniform(-3, 0, len(topo.links)),
        boundary_conductance=10 ** rng.uniform(-3, 0, len(topo.boundary_nodes)),
        heat_gain=np.ones(len(topo.heat_nodes)),
    )


def imu6() -> tj.ThermalNetwork:
    return tj.ThermalNetwork.from_spec(tj.load_model(CONFIGS / "imu6.toml"))


def rtd2() -> tj.ThermalNetwork:
    return tj.ThermalNetwork.from_spec(tj.load_model(CONFIGS / "rtd2.toml"))


def as_np(x):
    return np.asarray(jnp.asarray(x))


__all__ = ["tree_allclose", "random_topology", "random_network", "imu6", "rtd2", "as_np", "jax"]


def toml_network(path):
    """The physical matrices of a model file, read with `tomllib` alone (no thermojax).

    An independent reference for tests: returns a dict with `c` (J/K, per node),
    `K = L + diag(g_b)` (W/K), `G` (heat flow per unit input, W/K or 1, inputs in
    the file's order: boundaries first, then heat inputs), `input_names`, `holds`
    (default "foh"), and `A = -K / c`, `B = G / c` as NumPy float64.
    """
    import tomllib

    with open(path, "rb") as f:
        doc = tomllib.load(f)

    def value(v):
        return float(v["value"] if isinstance(v, dict) else v)

    names = [node["name"] for node in doc["nodes"]]
    idx = {name: i for i, name in enumerate(names)}
    n = len(names)
    c = np.array([value(node["capacitance"]) for node in doc["nodes"]])
    K = np.zeros((n, n))
    for link in doc.get("links", []):
        i, j = (idx[x] for x in link["between"])
        g = value(link["conductance"])
        K[i, i] += g
        K[j, j] += g
        K[i, j] -= g
        K[j, i] -= g
    entries = [(b, value(b["conductance"]), True) for b in doc.get("boundaries", [])] + \
              [(h, value(h.get("gain", 1.0)), False) for h in doc.get("heat_inputs", [])]
    input_names, holds = [], []
    for entry, _, _ in entries:
        if entry["input"] not in input_names:
            input_names.append(entry["input"])
            holds.append(entry.get("hold", "foh"))
    G = np.zeros((n, len(input_names)))
    for entry, g, is_boundary in entries:
        i, j = idx[entry["node"]], input_names.index(entry["input"])
        G[i, j] += g
        if is_boundary:
            K[i, i] += g
    return {"c": c, "K": K, "G": G, "input_names": tuple(input_names), "holds": tuple(holds),
            "A": -K / c[:, None], "B": G / c[:, None]}


# ---------------------------------------------------------------------------
# Independent NumPy/SciPy references for fitting and Kalman tests (no thermojax maths).


def model_matrices(path):
    """`toml_network(path)` plus the sensor matrix `Cy`, sensor columns, process-noise
    diffusion stds `q` (°C/√s, 0 when absent), initial values and initial stds, all read
    with `tomllib` alone."""
    import tomllib

    with open(path, "rb") as f:
        doc = tomllib.load(f)

    def value(v, default=None):
        if v is None:
            return default
        return float(v["value"] if isinstance(v, dict) else v)

    net = toml_network(path)
    names = [node["name"] for node in doc["nodes"]]
    idx = {name: i for i, name in enumerate(names)}
    sensors = doc.get("sensors", [])
    Cy = np.zeros((len(sensors), len(names)))
    for k, s in enumerate(sensors):
        Cy[k, idx[s["node"]]] = 1.0
    net.update(
        Cy=Cy, names=tuple(names), sensor_columns=tuple(s["column"] for s in sensors),
        noise=np.array([value(s.get("noise"), 0.01) for s in sensors]),
        q=np.array([value(node.get("process_noise"), 0.0) for node in doc["nodes"]]),
        initial={i: value(node["initial"]) for i, node in enumerate(doc["nodes"])
                 if "initial" in node and node["initial"] != "steady"},
        initial_std=np.array([float(node.get("initial_std", 1.0)) for node in doc["nodes"]]))
    return net


def np_discretize(A, B, dt, holds):
    """Exact sampling `x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]` by `scipy.linalg.expm` of
    `[[A dt, B dt, 0], [0, 0, I], [0, 0, 0]]` (FOH: `u` linear between samples; ZOH: the
    `u[k+1]` term dropped and its share moved to `u[k]`)."""
    import scipy.linalg

    n, m = B.shape
    M = np.zeros((n + 2 * m, n + 2 * m))
    M[:n, :n] = A * dt
    M[:n, n:n + m] = B * dt
    M[n:n + m, n + m:] = np.eye(m)
    E = scipy.linalg.expm(M)
    Phi, G0, G1 = E[:n, :n], E[:n, n:n + m], E[:n, n + m:]
    foh = np.array([h == "foh" for h in holds], dtype=float)
    B1 = G1 * foh[None, :]
    return Phi, G0 - B1, B1


def np_van_loan(A, Qc, dt, method="quad"):
    """`Qd = ∫0^dt e^{As} Qc e^{Aᵀs} ds`, (n, n), for `A` (n, n) 1/s, `Qc` (n, n) °C²/s:
    by adaptive quadrature (`scipy.integrate.quad_vec`, `method="quad"`) or by Van Loan's
    block exponential `expm([[-A, Qc], [0, Aᵀ]] dt)` (`"expm"`: fast, for optimizer loops)."""
    import scipy.integrate
    import scipy.linalg

    if method == "expm":
        n = A.shape[0]
        M = np.zeros((2 * n, 2 * n))
        M[:n, :n], M[:n, n:], M[n:, n:] = -A * dt, Qc * dt, A.T * dt
        F = scipy.linalg.expm(M)
        Qd = F[n:, n:].T @ F[:n, n:]
    else:
        Qd, _ = scipy.integrate.quad_vec(
            lambda s: (lambda E: E @ Qc @ E.T)(scipy.linalg.expm(A * s)), 0.0, dt,
            epsabs=1e-16, epsrel=1e-12)
    return 0.5 * (Qd + Qd.T)


def np_simulate(A, B, Cy, x0, U, dt, holds, Qd=None, rng=None):
    """States and outputs of the exact-hold recurrence from `x0`, optionally with process
    noise `w[k] ~ N(0, Qd)` added each step (drawn from `rng`)."""
    Phi, B0, B1 = np_discretize(A, B, dt, holds)
    T, n = U.shape[0], A.shape[0]
    X = np.zeros((T, n))
    X[0] = x0
    Lq = None if Qd is None else np.linalg.cholesky(Qd + 1e-300 * np.eye(n))
    for k in range(T - 1):
        X[k + 1] = Phi @ X[k] + B0 @ U[k] + B1 @ U[k + 1]
        if Lq is not None:
            X[k + 1] += Lq @ rng.standard_normal(n)
    return X, X @ Cy.T


def np_steady(A, B, u0):
    """Equilibrium `x` with `A x + B u0 = 0`."""
    return np.linalg.solve(A, -B @ u0)


def np_kalman(mm, U, Y, dt, m0, P0=None, *, mask=None, offset=None, van_loan="quad"):
    """The reference continuous-discrete Kalman filter (docs/formats.md §2): update before
    predict, every measured sample included (the first too), exact-hold sampling
    (`np_discretize`), Van Loan process noise (`np_van_loan`), the textbook update
    `P − K S Kᵀ` and `−log L = Σ_k ½ (log det(2π S_k) + e_kᵀ S_k⁻¹ e_k)` over measured rows.

    - `mm`: dict with `A` (n, n) 1/s, `B` (n, inputs), `Cy` (sensors, n), `holds`, `q`
      (n,) process-noise diffusion stds °C/√s, `noise` (sensors,) sensor stds °C, and
      `initial_std` (n,) °C unless `P0` is given: `model_matrices` gives them all.
    - `U` (T, inputs); `Y` (T, sensors) °C, NaN where dropped; `dt` s.
    - `m0` (n,) initial mean °C; `P0` (n, n) °C² (default `diag(initial_std²)`).
    - `mask` (T, sensors) bool, measured samples (default `isfinite(Y)`); `offset`
      (sensors,) °C, the outputs are `Cy x + offset`; `van_loan`: `np_van_loan`'s method.

    Returns a dict: `m_pred`, `m_filt` (T, n) and `P_pred`, `P_filt` (T, n, n), before and
    after each sample's update; `innovations`, `innovation_std` (T, sensors) °C, 0 where
    not measured; `nll_terms` (T,) `−log p(y_k | y_<k)`; `nll` their sum; `Phi` (n, n).
    """
    A, B, Cy = (np.asarray(mm[k], float) for k in ("A", "B", "Cy"))
    U, Y = np.asarray(U, float), np.asarray(Y, float)
    (T, p), n = Y.shape, A.shape[0]
    mask = np.isfinite(Y) if mask is None else np.asarray(mask, bool)
    y_off = np.zeros(p) if offset is None else np.asarray(offset, float)
    Phi, B0, B1 = np_discretize(A, B, dt, mm["holds"])
    Qd = np_van_loan(A, np.diag(np.asarray(mm["q"], float) ** 2), dt, method=van_loan)
    r = np.asarray(mm["noise"], float) ** 2
    drive = U @ B0.T + np.concatenate([U[1:], U[-1:]]) @ B1.T  # (T, n): u[T] := u[T-1]
    m = np.array(m0, float)
    P = np.diag(np.asarray(mm["initial_std"], float) ** 2) if P0 is None else np.array(P0, float)
    out = {"m_pred": np.zeros((T, n)), "m_filt": np.zeros((T, n)),
           "P_pred": np.zeros((T, n, n)), "P_filt": np.zeros((T, n, n)),
           "innovations": np.zeros((T, p)), "innovation_std": np.zeros((T, p)),
           "nll_terms": np.zeros(T)}
    seen, full = mask.any(axis=1), mask.all(axis=1)
    R = np.diag(r)
    for k in range(T):
        out["m_pred"][k], out["P_pred"][k] = m, P
        if seen[k]:
            obs = mask[k]
            H, Rk = (Cy, R) if full[k] else (Cy[obs], R[np.ix_(obs, obs)])
            S = H @ P @ H.T + Rk
            S_inv = np.linalg.inv(S)
            e = Y[k, obs] - H @ m - y_off[obs]
            logdet = np.log(np.linalg.det(2 * np.pi * S))  # S is positive definite
            out["nll_terms"][k] = 0.5 * (logdet + e @ S_inv @ e)
            K = P @ H.T @ S_inv
            m = m + K @ e
            P = P - K @ S @ K.T
            P = 0.5 * (P + P.T)
            out["innovations"][k, obs] = e
            out["innovation_std"][k, obs] = np.sqrt(np.diag(S))
        out["m_filt"][k], out["P_filt"][k] = m, P
        m = Phi @ m + drive[k]
        P = Phi @ P @ Phi.T + Qd
        P = 0.5 * (P + P.T)
    out.update(nll=float(np.sum(out["nll_terms"])), Phi=Phi)
    return out


# ---------------------------------------------------------------------------
# A small identifiable scenario shared by the fit, Kalman and CLI tests (one compilation
# per likelihood for all of them: same structure, same data shapes).

RTD2H_TEXT = """\
# rtd2 (configs/rtd2.toml) with a measured heater on the sheath and a second sensor:
# every capacitance and conductance is identifiable. The core's initial temperature is
# estimated per run; the sheath starts at the equilibrium of the first input sample, as
# the generated runs do.
name = "rtd2h"

[[nodes]]
name = "sheath"
capacitance = 0.8
initial = "steady"

[[nodes]]
name = "core"
capacitance = 0.1
initial = 20.0  # estimated per run

[[links]]
between = ["sheath", "core"]
conductance = 0.08333333333333333

[[boundaries]]
node = "sheath"
input = "T_fluid"
conductance = 0.2

[[heat_inputs]]
node = "sheath"
input = "P_heater"
gain = { value = 1.0, fixed = true }
hold = "zoh"

[[sensors]]
node = "core"
column = "T_core"
noise = 0.01

[[sensors]]
node = "sheath"
column = "T_sheath"
noise = { value = 0.02, fixed = true }
"""

RTD2H_TRUTH = {
    "nodes.sheath.capacitance": 0.8,
    "nodes.core.capacitance": 0.1,
    "links.sheath-core.conductance": 1 / 12,
    "boundaries.sheath-T_fluid.conductance": 0.2,
}
RTD2H_RUNS = ((600, 1.0), (400, 2.0))  # (samples, sample period s) per run
# Run names: `Dataset` keeps them as static fields, so every test that fits these shapes
# under these names (the CLI ones too, run from the folder holding a.csv and b.csv) reuses
# one compilation per likelihood.
RTD2H_NAMES = ("a.csv", "b.csv")
RTD2H_CORE_OFFSET = (3.0, -2.0)  # true initial core temperature minus its steady state, °C
RTD2H_Q = np.array([0.004, 0.002])  # process-noise diffusion stds of the Kalman data, °C/√s


def text_matrices(text: str) -> dict:
    """`model_matrices` of model TOML text (through a temporary file)."""
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "model.toml"
        path.write_text(text)
        return model_matrices(path)


def rtd2h_inputs(n: int, dt: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(ts, U): a drifting sinusoidal fluid temperature (°C, FOH) and a random 0/0.5 W heater
    square wave switching on multiples of 10 samples (W, ZOH)."""
    ts = dt * np.arange(n)
    T_fluid = 20.0 + 10.0 * np.sin(2 * np.pi * ts / 300.0) + 0.02 * ts
    P = np.repeat(0.5 * rng.integers(0, 2, n // 10 + 1), 10)[:n].astype(float)
    return ts, np.stack([T_fluid, P], axis=1)


def rtd2h_data(seed: int = 1, process_noise: bool = False):
    """Synthetic runs of the rtd2h truth (true noise: T_core 0.01 °C, T_sheath 0.02 °C), each
    from the steady state of its first input with the core `RTD2H_CORE_OFFSET` off it,
    simulated by the NumPy exact-hold recurrence (with `RTD2H_Q` process noise if asked).
    Returns (ts, U, Y, x0, X) per run, X the true node temperatures."""
    mm = text_matrices(RTD2H_TEXT)
    rng = np.random.default_rng(seed)
    runs = []
    for (n, dt), offset in zip(RTD2H_RUNS, RTD2H_CORE_OFFSET):
        ts, U = rtd2h_inputs(n, dt, rng)
        x0 = np_steady(mm["A"], mm["B"], U[0]) + np.array([0.0, offset])
        Qd = np_van_loan(mm["A"], np.diag(RTD2H_Q ** 2), dt) if process_noise else None
        X, Y = np_simulate(mm["A"], mm["B"], mm["Cy"], x0, U, dt, mm["holds"], Qd=Qd, rng=rng)
        runs.append((ts, U, Y + rng.standard_normal(Y.shape) * mm["noise"], x0, X))
    return runs


def rtd2h_spec(text: str = RTD2H_TEXT):
    return tj.parse_model(text, source="rtd2h.toml")


def rtd2h_experiments(seed: int = 1, process_noise: bool = False):
    from thermojax.measurements._data import Experiment

    return [Experiment(ts, U, Y, name=name) for name, (ts, U, Y, *_)
            in zip(RTD2H_NAMES, rtd2h_data(seed, process_noise))]


_FITS: dict = {}


def cached_fit(key, make):
    """`make()` once per test session per `key` (fits are shared between test modules)."""
    if key not in _FITS:
        _FITS[key] = make()
    return _FITS[key]


def rtd2h_oe_fit():
    """The output-error fit of the rtd2h runs (seed 1), shared by the test modules."""
    from thermojax.fitting._fit import fit

    def make():
        experiments = rtd2h_experiments(1)
        return {"result": fit(rtd2h_spec(), experiments), "experiments": experiments,
                "truth": rtd2h_data(1)}

    return cached_fit(("rtd2h", "output_error"), make)


def rtd2h_kalman_fit():
    """The Kalman fit of rtd2h runs simulated with process noise (seed 1)."""
    from thermojax.fitting._fit import fit

    def make():
        experiments = rtd2h_experiments(1, process_noise=True)
        return {"result": fit(rtd2h_spec(), experiments, likelihood="kalman"),
                "experiments": experiments, "truth": rtd2h_data(1, process_noise=True)}

    return cached_fit(("rtd2h", "kalman"), make)


IMU6_RUNS = ((1500, 1.0), (1000, 1.0))


def imu6_data(seed: int = 0):
    """Two imu6 runs (configs/imu6.toml as the truth; sensors on housing, pcb and asic,
    0.01 °C noise) at 1 s: a chamber ramp up and down with a 0.05/0.15 W ASIC power square
    wave (ZOH), from steady state, by the NumPy exact-hold recurrence. (ts, U, Y, x0) per run."""
    mm = model_matrices(CONFIGS / "imu6.toml")
    rng = np.random.default_rng(seed)
    runs = []
    for n, dt in IMU6_RUNS:
        ts = dt * np.arange(n)
        T_ch = 25 + 20 * np.clip((ts - 100) / 600, 0, 1) - 15 * np.clip((ts - 900) / 400, 0, 1)
        P = 0.05 + 0.1 * ((ts // 97) % 2)
        U = np.stack([T_ch, P], axis=1)
        x0 = np_steady(mm["A"], mm["B"], U[0])
        _, Y = np_simulate(mm["A"], mm["B"], mm["Cy"], x0, U, dt, mm["holds"])
        runs.append((ts, U, Y + rng.standard_normal(Y.shape) * mm["noise"], x0))
    return runs


def off_by_factor(spec, factor: float):
    """`spec` with its free capacitances and conductances multiplied by `factor` and
    `1/factor` alternately, in file order."""
    import dataclasses

    from thermojax.model._spec import Parameter

    k = iter(range(1000))

    def move(p):
        return p if p.fixed else Parameter(p.value * factor ** (1 - 2 * (next(k) % 2)), False)

    return spec.replace(
        nodes=tuple(dataclasses.replace(n, capacitance=move(n.capacitance)) for n in spec.nodes),
        links=tuple(dataclasses.replace(x, conductance=move(x.conductance)) for x in spec.links),
        boundaries=tuple(dataclasses.replace(b, conductance=move(b.conductance))
                         for b in spec.boundaries))


def imu6_fit():
    """The output-error fit of `imu6_data()` started 3x off (`off_by_factor(imu6, 3)`)."""
    from thermojax.measurements._data import Experiment
    from thermojax.fitting._fit import fit

    def make():
        data = imu6_data()
        experiments = [Experiment(ts, U, Y, name=f"imu6_run{i}")
                       for i, (ts, U, Y, _) in enumerate(data)]
        start = off_by_factor(tj.load_model(CONFIGS / "imu6.toml"), 3.0)
        return {"result": fit(start, experiments), "experiments": experiments, "truth": data,
                "start": start}

    return cached_fit(("imu6", "output_error"), make)


def law_truths(expression: str, truths: dict) -> dict:
    """The parameters `truths` of a generated law `c·u^p·…` as a learned `expression`
    states them: a column read in its size, `(u / U)`, has `c·U^p` for its coefficient
    (c·u^p = c·U^p·(u/U)^p); the other parameters are unchanged."""
    import re

    scaled = re.search(r"\(\s*[A-Za-z_]\w*\s*/\s*([0-9.]+(?:[eE][+-]?\d+)?)\s*\)", expression)
    out = dict(truths)
    if scaled is not None:
        out["c"] = truths["c"] * float(scaled.group(1)) ** truths["p"]
    return out


def run_cli(capsys, *argv):
    """`thermojax ARGV` in this process: `(exit status, stdout, stderr)`."""
    from thermojax.cli import main

    capsys.readouterr()
    try:
        rc = main(list(map(str, argv)))
    except SystemExit as e:
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_refused(rc, err, *fragments):
    """A user's mistake: exit 2, no traceback, and each fragment in the message."""
    assert rc == 2, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, (fragment, err)


def chain_data():
    """`benchmarks/_chain_data.py` (the large-network benchmark's generated chain and its
    SciPy truth) as a module."""
    import importlib.util

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "_chain_data.py"
    spec = importlib.util.spec_from_file_location("_chain_data", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
