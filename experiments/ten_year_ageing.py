"""Study: the ten-year question. How do die-attach ageing and thermal-interface pump-out
degrade the compensated gyro bias of the six-node IMU over its service life, with the
factory observer, with periodic recalibration, and with the adaptive filter?

Issue 35, item 5; the seed: "Thermal system parameters shift over time as die-attach
adhesives age and thermal interface materials pump out under thermal cycling. The
fundamental question remains how parameter drift in the conduction matrix affects
long-term tactical stability across a ten-year shelf life." The seed gives no ageing
rates, so they are **assumptions**, stated here and in the results (`--help` changes
none of them; edit `AGEING`):

- ASIC die attach (`pcb–asic`, 0.02 W/K) and MEMS die attach (`pcb–mems`, 0.01 W/K):
  voids grow and saturate, `g = g0 (1 − a (1 − e^(−t / 3 y)))`, `a ~ U(0.1, 0.5)` per
  unit (a 10–50 % loss for life);
- thermal pad under the board (`bulkhead–pcb`, 0.1 W/K) pumps out linearly,
  `g = g0 (1 − b t / 10 y)`, `b ~ U(0, 0.4)`.

Each unit (configs/imu6.toml; its factory model exact at age 0, unit-to-unit variation
left to `unit_variance_procurement.py`) is simulated at each age over one operating
profile (an independent NumPy/SciPy simulation: `scipy.linalg.expm` per sample period,
0.01 °C sensor noise on housing, pcb and asic): an hour of operation at 25 °C with the
ASIC power switching 0.10/0.25 W every 10 min, then a two-hour mission with ambient
ramps 25 → −20 → 60 → 25 °C at 2 °C/min, with dwells, power still switching. The gyro
bias is imu6_bias.toml's (cubic in the proof-mass temperature, 0.8 °/h/K × (T_mems −
T_asic), 4 °/h per °C/s of MEMS rate); the compensation error is the bias model on the
observer's estimates (the rate from the observer's own model) minus the bias on the
truth, its peak over the mission against the tactical 0.5 °/h (the seed's in-run
stability). Three observers (`thermojax.observer.track_conductances`, one code):

- **factory**: the Kalman filter of the age-0 model, never updated;
- **recalibrated every 2 years**: the model of the last recalibration, taken just before
  the next one (the worst point of each interval; the recalibration itself exact);
- **adaptive**: the three conductances tracked online (random walks 5e-5 /√s, ceiling
  0.5, excitation gate 3σ). Each age starts it from the factory values: the first hour
  is its time to converge (in service it would have tracked all along).

    python experiments/ten_year_ageing.py [--out DIR] [--force] [--quick] [--units N]

writes `ageing.md`, `results.json` and `ageing.png`. `--quick`: 3 units, ages 0, 5, 10.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import scipy.linalg

from thermojax._plots import new_figure, save_figure
from thermojax.io import load_model
from thermojax.model._parameters_by_name import spec_parameters, with_spec_parameters
from thermojax.model._spec import Parameter
from thermojax.observer import track_conductances

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "experiments"))
from _study_cli import results_folder, study_parser, write_results  # noqa: E402

MODEL = ROOT / "configs" / "imu6.toml"
DT = 1.0
SPEC_DPH = 0.5          # tactical in-run bias stability, °/h (the seed)
NOISE = 0.01            # °C
AGES = (0.0, 1.0, 2.0, 5.0, 10.0)
RECAL_YEARS = 2.0
TRACKED = ("links.pcb-asic.conductance", "links.pcb-mems.conductance",
           "links.bulkhead-pcb.conductance")
# (law, low, high): the loss fraction's range per unit (assumptions, see the docstring)
AGEING = {"links.pcb-asic.conductance": ("voids", 0.1, 0.5),
          "links.pcb-mems.conductance": ("voids", 0.1, 0.5),
          "links.bulkhead-pcb.conductance": ("pump_out", 0.0, 0.4)}
GYRO_POLY = (0.5, 0.03, 5e-4, -2e-6)   # °/h in (T_pm − 25)
GYRO_GRADIENT, GYRO_RATE = 0.8, 4.0     # °/h/K (mems − asic), °/h per °C/s of mems


def aged(g0: float, law: str, loss: float, years: float) -> float:
    if law == "voids":
        return g0 * (1.0 - loss * (1.0 - np.exp(-years / 3.0)))
    return g0 * (1.0 - loss * years / 10.0)


def profile():
    """Inputs (T, 2): ambient °C, ASIC power W; the index where the mission starts."""
    burn = np.full(3600, 25.0)
    legs = [np.full(600, 25.0), np.linspace(25, -20, 1350), np.full(900, -20.0),
            np.linspace(-20, 60, 2400), np.full(900, 60.0), np.linspace(60, 25, 1050)]
    ambient = np.concatenate([burn, *legs])
    t = np.arange(ambient.size) * DT
    power = np.where((t // 600) % 2 == 0, 0.10, 0.25)
    return np.stack([ambient, power], axis=1), burn.size


def network(spec):
    """Capacitances, links, boundaries, heat inputs of `spec` as NumPy (the truth's)."""
    idx = {n: i for i, n in enumerate(spec.node_names)}
    C = np.array([n.capacitance.value for n in spec.nodes])
    links = [(idx[a], idx[b], k.conductance.value) for k in spec.links
             for a, b in [k.between]]
    cols = {c: j for j, c in enumerate(spec.input_columns)}
    bnd = [(idx[b.node], cols[b.input], b.conductance.value) for b in spec.boundaries]
    heat = [(idx[h.node], cols[h.input], h.gain.value) for h in spec.heat_inputs]
    return C, links, bnd, heat, [idx[s.node] for s in spec.sensors], idx


def matrices(spec):
    C, links, bnd, heat, _, _ = network(spec)
    n, m = C.size, len(spec.input_columns)
    K, B = np.zeros((n, n)), np.zeros((n, m))
    for a, b, g in links:
        K[a, a] += g
        K[b, b] += g
        K[a, b] -= g
        K[b, a] -= g
    for a, c, g in bnd:
        K[a, a] += g
        B[a, c] += g
    for a, c, g in heat:
        B[a, c] += g
    return -K / C[:, None], B / C[:, None]


def simulate(spec, u, rng):
    """Independent truth: exact sampling (`scipy.linalg.expm` of the block matrix with
    the input and its slope), the ambient linear between samples and the power held, as
    the model file says; steady start. Returns states (T, n) and readings (T, p)."""
    A, B = matrices(spec)
    n, m = B.shape
    Z = np.zeros
    M = scipy.linalg.expm(np.block([[A * DT, B * DT, Z((n, m))], [Z((m, n + m)), np.eye(m)],
                                    [Z((m, n + 2 * m))]]))
    Phi, Gam, Lam = M[:n, :n], M[:n, n:n + m], M[:n, n + m:]
    Lam = Lam * np.array([h == "foh" for h in spec.input_holds], float)
    x = np.empty((u.shape[0], n))
    x[0] = np.linalg.solve(-A, B @ u[0])
    for k in range(u.shape[0] - 1):
        x[k + 1] = Phi @ x[k] + Gam @ u[k] + Lam @ (u[k + 1] - u[k])
    sensors = network(spec)[4]
    return x, x[:, sensors] + NOISE * rng.standard_normal((u.shape[0], len(sensors)))


def gyro(x, mems_rate, idx):
    d = x[:, idx["proof_mass"]] - 25.0
    return (np.polynomial.polynomial.polyval(d, GYRO_POLY)
            + GYRO_GRADIENT * (x[:, idx["mems"]] - x[:, idx["asic"]]) + GYRO_RATE * mems_rate)


def mems_rate(spec, x, g_mems_pcb=None):
    """dT_mems/dt (°C/s) of states `x (T, n)` by `spec`'s links, with the pcb–mems
    conductance replaced by `g_mems_pcb (T,)` where given (the adaptive estimate)."""
    C, links, _, _, _, idx = network(spec)
    m = idx["mems"]
    rate = np.zeros(x.shape[0])
    for a, b, g in links:
        if m not in (a, b):
            continue
        other = b if a == m else a
        if g_mems_pcb is not None and {a, b} == {m, idx["pcb"]}:
            g = g_mems_pcb
        rate = rate + g * (x[:, other] - x[:, m])
    return rate / C[m]


def with_conductances(spec, values: dict):
    params = spec_parameters(spec)
    return with_spec_parameters(spec, {k: Parameter(v, params[k].fixed)
                                       for k, v in values.items()})


def run_unit(spec, losses, ages, u, mission, seed):
    """Peak mission bias error (°/h) per age for each observer, and the adaptive
    filter's final estimate / truth per tracked conductance."""
    nominal = {k: p.value for k, p in spec_parameters(spec).items() if k in TRACKED}
    idx = network(spec)[5]
    out = {"factory": [], "recalibrated": [], "adaptive": [], "adaptive_ratio": []}
    for i, years in enumerate(ages):
        true_g = {k: aged(nominal[k], AGEING[k][0], losses[k], years) for k in TRACKED}
        true_spec = with_conductances(spec, true_g)
        x, y = simulate(true_spec, u, np.random.default_rng(seed * 100 + i))
        b_true = gyro(x, mems_rate(true_spec, x), idx)
        last_recal = max(0.0, years - RECAL_YEARS) if years > 0 else 0.0
        recal_g = {k: aged(nominal[k], AGEING[k][0], losses[k], last_recal) for k in TRACKED}
        for name, believed in (("factory", nominal), ("recalibrated", recal_g)):
            obs_spec = with_conductances(spec, believed)
            run = track_conductances(obs_spec, list(TRACKED), u, y, DT, drift=0.0,
                                     ceiling=1e-9, x0=x[0])
            err = gyro(run.states, mems_rate(obs_spec, run.states), idx) - b_true
            out[name].append(float(np.abs(err[mission:]).max()))
        run = track_conductances(spec, list(TRACKED), u, y, DT, drift=5e-5, ceiling=0.5,
                                 x0=x[0])
        g_mems = run.conductances[:, TRACKED.index("links.pcb-mems.conductance")]
        err = gyro(run.states, mems_rate(spec, run.states, g_mems), idx) - b_true
        out["adaptive"].append(float(np.abs(err[mission:]).max()))
        out["adaptive_ratio"].append([float(run.conductances[-1, j] / true_g[k])
                                      for j, k in enumerate(TRACKED)])
    return out


def main(argv=None) -> Path:
    parser = study_parser("ten_year_ageing", __doc__, "3 units, ages 0, 5 and 10 years")
    parser.add_argument("--units", type=int, default=None,
                        help="units in the population (default 8; --quick 3)")
    args = parser.parse_args(argv)
    folder = results_folder("ten_year_ageing", args.out, args.force)
    units = args.units or (3 if args.quick else 8)
    ages = (0.0, 5.0, 10.0) if args.quick else AGES
    spec = load_model(MODEL)
    u, mission = profile()
    rng = np.random.default_rng(args.seed)
    results, t0 = [], time.time()
    for unit in range(units):
        losses = {k: float(rng.uniform(lo, hi)) for k, (_, lo, hi) in AGEING.items()}
        res = run_unit(spec, losses, ages, u, mission, args.seed * 1000 + unit)
        results.append({"losses": losses, **res})
        print(f"unit {unit + 1}/{units} ({time.time() - t0:.0f} s): peak error °/h by age "
              + "; ".join(f"{s} " + " ".join(f"{v:.3f}" for v in res[s])
                          for s in ("factory", "recalibrated", "adaptive")), flush=True)
    table = summarize(results, ages)
    res = {"ages_years": list(ages), "units": units, "spec_dph": SPEC_DPH,
           "ageing_assumptions": {k: list(v) for k, v in AGEING.items()},
           "recalibration_years": RECAL_YEARS, "per_unit": results,
           "wall_time_s": time.time() - t0}
    write_results(folder, res, table, "ageing.md")
    plot(results, ages, folder / "ageing.png")
    return folder


def summarize(results, ages) -> str:
    lines = ["# The ten-year question: compensated gyro bias after ageing", "",
             f"{len(results)} unit{'s' if len(results) != 1 else ''}; peak |bias error| "
             f"over the mission, °/h (median, worst); units within the tactical "
             f"{SPEC_DPH} °/h.", "",
             "| age (y) | factory median / worst / within | recalibrated "
             f"every {RECAL_YEARS:g} y | adaptive |", "|---|---|---|---|"]
    for i, years in enumerate(ages):
        cells = []
        for s in ("factory", "recalibrated", "adaptive"):
            v = np.array([r[s][i] for r in results])
            cells.append(f"{np.median(v):.3f} / {v.max():.3f} / "
                         f"{np.mean(v <= SPEC_DPH):.0%}")
        lines.append(f"| {years:g} | " + " | ".join(cells) + " |")
    lines += ["", "Adaptive filter's end estimate / truth per tracked conductance "
              "(median over units, [min, max]):", ""]
    for j, k in enumerate(TRACKED):
        ratios = np.array([[r["adaptive_ratio"][i][j] for r in results]
                           for i in range(len(ages))])
        lines.append(f"- `{k}`: " + "; ".join(
            f"{years:g} y {np.median(ratios[i]):.3f} [{ratios[i].min():.3f}, "
            f"{ratios[i].max():.3f}]" for i, years in enumerate(ages)))
    return "\n".join(lines) + "\n"


def plot(results, ages, path) -> None:
    fig = new_figure()
    ax = fig.add_subplot()
    for s, colour in (("factory", "C3"), ("recalibrated", "C1"), ("adaptive", "C0")):
        v = np.array([r[s] for r in results])          # (units, ages)
        ax.plot(ages, np.median(v, axis=0), "o-", color=colour, label=f"{s}: median")
        ax.fill_between(ages, v.min(axis=0), v.max(axis=0), color=colour, alpha=0.15,
                        label=f"{s}: range over units")
    ax.axhline(SPEC_DPH, color="k", ls="--", lw=1, label=f"tactical {SPEC_DPH} °/h")
    ax.set_xlabel("age (years)")
    ax.set_ylabel("peak compensated gyro bias error (°/h)")
    ax.set_yscale("log")
    ax.set_title("Six-node IMU: die-attach voiding and pad pump-out (assumed rates)")
    ax.legend(fontsize=7, ncol=2)
    save_figure(fig, path)


if __name__ == "__main__":
    main()
