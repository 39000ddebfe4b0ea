"""Output Jacobian of a nonlinear model: thermojax's per-sample linearization against
`jax.jacfwd` of the ETD2 scan and against forward differences (what
`scipy.optimize.least_squares(jac="2-point")` does), in the same run.

The problem is the one a candidate refit of the imu6 investigation solves
(`benchmarks/investigate.py --imu6`): the six-node IMU with a housing-chamber radiation
term, three 3.5 h runs at 1 Hz (3 x 12,601 samples), 14 free parameters. Every method
differentiates the same ETD2 simulation; the script prints the time per Jacobian
(compiled, best of `--repeats`), the compile time of each, and the largest column
difference relative to the column's size.

Usage:  python benchmarks/nonlinear_jacobian.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "benchmarks"))

import equinox as eqx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import thermojax  # noqa: E402
from investigate import IMU6_HIDDEN, imu6_runs  # noqa: E402
from thermojax.dynamics._nonlinear import dataset_outputs_nonlinear  # noqa: E402
from thermojax.dynamics._nonlinear_sensitivity import dataset_outputs_and_jacobian  # noqa: E402
from thermojax.fitting._problem import _model_of, make_problem, prepare  # noqa: E402
from thermojax.measurements._data import Experiment  # noqa: E402
from thermojax.model._parameters import free_parameters  # noqa: E402


def problem():
    """`(theta, problem)` of imu6 + radiation on the investigation benchmark's runs."""
    radiation = IMU6_HIDDEN.split('[[effects]]\nkind = "sensor_lag"')[0]
    spec = thermojax.parse_model((REPO / "configs" / "imu6.toml").read_text() + radiation)
    experiments = []
    for i, (ts, cols) in enumerate(imu6_runs()):
        u = np.stack([cols[c] for c in spec.input_columns], 1)
        y = np.stack([cols[c] for c in spec.sensor_columns], 1)
        experiments.append(Experiment(ts, u, y, f"run{i}"))
    prep = prepare(spec, experiments, "output_error")
    theta = free_parameters(prep.template, prep.index)
    return theta, make_problem(prep.template, prep.index, prep.data, prep.sigma, theta)


def timed(f, *args, repeats: int):
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(*args))
    first = time.perf_counter() - t0
    best = np.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(*args))
        best = min(best, time.perf_counter() - t0)
    return out, first - best, best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    theta, prob = problem()

    def outputs(t, prob):
        model, run_initial = _model_of(t, prob)
        return dataset_outputs_nonlinear(model, prob.data, run_initial)

    # The problem is an argument, not a closed-over constant (XLA would fold it).
    linearized = eqx.filter_jit(lambda t, prob: dataset_outputs_and_jacobian(
        lambda s: _model_of(s, prob), t, prob.data)[1])
    jacfwd = eqx.filter_jit(jax.jacfwd(outputs))
    simulate = eqx.filter_jit(outputs)

    def forward_differences(t, prob):  # P + 1 simulations, relative step sqrt(eps) as SciPy
        y0 = simulate(t, prob)
        h = np.sqrt(np.finfo(float).eps) * np.maximum(1.0, np.abs(np.asarray(t)))
        cols = [(simulate(t.at[i].add(h[i]), prob) - y0) / h[i] for i in range(t.shape[0])]
        return jnp.stack(cols, axis=-1)

    J, c_lin, t_lin = timed(linearized, theta, prob, repeats=args.repeats)
    J_ref, c_fwd, t_fwd = timed(jacfwd, theta, prob, repeats=args.repeats)
    _, c_sim, t_sim = timed(simulate, theta, prob, repeats=args.repeats)
    J_fd, _, t_fd = timed(forward_differences, theta, prob, repeats=max(1, args.repeats // 2))
    scale = np.abs(np.asarray(J_ref)).reshape(-1, theta.shape[0]).max(axis=0)

    def err(A):  # the worst column's largest difference, relative to the column's size
        return float((np.abs(np.asarray(A) - np.asarray(J_ref)).reshape(-1, theta.shape[0])
                      .max(axis=0) / scale).max())

    print(f"imu6 + radiation, {prob.data.ts.shape[0]} runs x {prob.data.ts.shape[1]} samples, "
          f"{theta.shape[0]} parameters; load {os.getloadavg()[0]:.2f}")
    print(f"{'method':<40} {'per Jacobian s':>15} {'compile s':>10} {'max col. error':>15}")
    print(f"{'thermojax (per-sample linearization)':<40} {t_lin:>15.3f} {c_lin:>10.2f} "
          f"{err(J):>15.1e}")
    print(f"{'jax.jacfwd of the ETD2 scan':<40} {t_fwd:>15.3f} {c_fwd:>10.2f} {'(reference)':>15}")
    print(f"{'forward differences (P + 1 simulations)':<40} {t_fd:>15.3f} {'':>10} "
          f"{err(J_fd):>15.1e}")
    print(f"one simulation: {t_sim:.3f} s (compile {c_sim:.2f} s)")
    print(f"ratios: jacfwd / thermojax {t_fwd / t_lin:.2f}x, forward differences / thermojax "
          f"{t_fd / t_lin:.2f}x; thermojax / one simulation {t_lin / t_sim:.1f}x")


if __name__ == "__main__":
    main()
