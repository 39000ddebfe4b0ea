"""The cost of the symbolic search over heat laws (`thermojax.discovery.symbolic_search`),
per generation and per law fitted, on heats generated from known laws.

For each law (an Arrhenius law in kelvin, a saturating law of a difference, a sum of two
mechanisms) the search runs at a budget of evaluations; the script prints, per
generation, the laws fitted, the seconds (the first generation includes the one
compilation of the fitting program) and the milliseconds per law after it, and
whether the front holds the truth's form with its constants. Usage:

    python benchmarks/symbolic_search.py [--evaluations N] [--generations G] [--samples N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

import thermojax  # noqa: F401  (float64)
from thermojax.discovery import heat_variables, symbolic_search
from thermojax.discovery._symbolic_grammar import PRIMITIVE_INDEX, canonical

NOISE = 0.01


def data(n: int):
    t = np.linspace(0.0, 1.0, n)
    T = 25.0 + 60.0 * np.abs(np.sin(3.0 * t))
    Tb = 25.0 + 60.0 * np.abs(np.sin(3.0 * t - 0.3))
    u = 3.0 * np.clip(np.sin(7.0 * t), 0.0, None)
    variables = heat_variables([np.stack([T, Tb], 1)], ["pcb", "housing"], "pcb",
                               ["housing"], {"u": [u]})
    return variables, T, Tb - T, u


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--evaluations", type=int, default=1500)
    ap.add_argument("--generations", type=int, default=5)
    ap.add_argument("--samples", type=int, default=2000)
    args = ap.parse_args()
    variables, T, d, u = data(args.samples)
    idx = {v.name: i for i, v in enumerate(variables)}
    cases = {
        "arrhenius c exp(-E/T)": (2.0e6 * np.exp(-5000.0 / (T + 273.15)),
                                  [[(PRIMITIVE_INDEX["arrh"], idx["kelvin(pcb)"])]]),
        "saturating a d/(1+b|d|)": (0.3 * d / (1.0 + 0.15 * np.abs(d)),
                                    [[(PRIMITIVE_INDEX["sat"], idx["(housing - pcb)"])]]),
        "sum h|d|^n d + c u^2": (0.05 * np.abs(d) ** 0.25 * d + 0.04 * (u / 3.0) ** 2,
                                 [[(PRIMITIVE_INDEX["spow"], idx["(housing - pcb)"])],
                                  [(PRIMITIVE_INDEX["pow"], idx["(u / 3)"])]]),
    }
    rng = np.random.default_rng(0)
    for name, (q, truth) in cases.items():
        stamps = []
        t0 = time.perf_counter()

        def say(line, stamps=stamps, t0=t0):
            stamps.append((time.perf_counter() - t0, int(line.split(", ")[1].split()[0])))

        front = symbolic_search(variables, q + NOISE * rng.standard_normal(q.size),
                                np.full(q.size, NOISE), evaluations=args.evaluations,
                                generations=args.generations, say=say, random_state=0)
        found = [law for law in front.front if law.tree == canonical(truth)]
        print(f"\n{name}: {front.evaluated} laws in {front.seconds:.1f} s "
              f"({front.generations} generations, stopped: {front.stopped})")
        prev_t, prev_n = 0.0, 0
        for g, (t, n) in enumerate(stamps):
            per = 1e3 * (t - prev_t) / max(n - prev_n, 1)
            print(f"  generation {g}: {n - prev_n:4d} laws, {t - prev_t:6.2f} s, "
                  f"{per:6.2f} ms per law")
            prev_t, prev_n = t, n
        if found:
            law = found[0]
            print(f"  truth's form on the front: {law.expression}, R² {law.r2:.6f}")
            print("  " + ", ".join(f"{k} = {v:.6g} ± {law.stds.get(k, float('nan')):.2g}"
                                   for k, v in law.parameters.items()))
        else:
            print("  truth's form NOT on the front")


if __name__ == "__main__":
    main()
