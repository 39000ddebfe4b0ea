"""Candidates scored on Kalman innovations (issue 10 item 4): the innovation map of
`fitting._likelihood` against an independent NumPy Kalman filter.

The map is the filter's own linear recursion applied to output-space directions. Two
properties make it the right score under the Kalman likelihood, both checked here on
a two-node network with process noise on both nodes and a gap in the data:

1. the map of the free-run residuals is the filter's standardized innovations;
2. the derivative of the innovations along an added heat input is minus the map of
   that input's free-run output response (the direction the score test uses).
"""

from __future__ import annotations

import numpy as np
import pytest

from thermojax.fitting._likelihood import dataset_innovation_map, kalman_sample_nll
from thermojax.measurements._data import Dataset, Experiment
from thermojax.model import ThermalModel
from thermojax.model._model_file import parse_model

from helpers import np_discretize, np_kalman

DT, N = 60.0, 240
C_A, C_B, G_AB, G_OUT, NOISE, Q = 4000.0, 20000.0, 15.0, 8.0, 0.05, (0.002, 0.004)
MODEL = f"""
name = "two"
[[nodes]]
name = "a"
capacitance = {C_A}
process_noise = {Q[0]}
[[nodes]]
name = "b"
capacitance = {C_B}
process_noise = {Q[1]}
[[links]]
between = ["a", "b"]
conductance = {G_AB}
[[boundaries]]
node = "a"
input = "T_out"
conductance = {G_OUT}
[[heat_inputs]]
node = "b"
input = "P"
gain = {{ value = 1.0, fixed = true }}
hold = "zoh"
[[sensors]]
node = "a"
column = "T_a"
noise = {NOISE}
"""


def network(extra: float = 0.0):
    """`A`, `B` (inputs T_out, P, Q: Q a second heat input on b with gain `extra`)."""
    A = np.array([[-(G_AB + G_OUT) / C_A, G_AB / C_A], [G_AB / C_B, -G_AB / C_B]])
    B = np.array([[G_OUT / C_A, 0.0, 0.0], [0.0, 1.0 / C_B, extra / C_B]])
    return A, B


def numpy_filter(U, Y, mask, extra=0.0, terms=False):
    """Standardized innovations (T,) of `helpers.np_kalman` on `Y` (T,) °C where `mask`
    (T,) (P0 = I °C², mean from the steady state of the first input; 0 where not
    measured); with `terms`, each sample's −log p(y_k | y_<k) instead."""
    A, B = network(extra)
    mm = dict(A=A, B=B, Cy=np.array([[1.0, 0.0]]), holds=("foh", "zoh", "zoh"),
              q=np.array(Q), noise=np.array([NOISE]))
    ref = np_kalman(mm, U, Y[:, None], DT, np.linalg.solve(A, -B @ U[0]), np.eye(2),
                    mask=mask[:, None])
    if terms:
        return ref["nll_terms"]
    std = np.where(mask, ref["innovation_std"][:, 0], 1.0)
    return ref["innovations"][:, 0] / std


def free_run(U, extra=0.0, x0=None):
    A, B = network(extra)
    Phi, B0, B1 = np_discretize(A, B, DT, ("foh", "zoh", "zoh"))
    x = np.linalg.solve(A, -B @ U[0]) if x0 is None else x0
    y = np.zeros(len(U))
    for k in range(len(U)):
        y[k] = x[0]
        u1 = U[k + 1] if k + 1 < len(U) else U[k]
        x = Phi @ x + B0 @ U[k] + B1 @ u1
    return y


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(3)
    t = np.arange(N) * DT
    U = np.column_stack([20 + 5 * np.sin(t / 3000.0), 30.0 * (rng.random(N) < 0.3),
                         np.r_[0.0, 10.0 * (rng.random(N - 1) < 0.5)]])
    Y = free_run(U, extra=0.7) + NOISE * rng.standard_normal(N)
    mask = np.ones(N, bool)
    mask[100:120] = False  # a gap: no update there
    spec = parse_model(MODEL, "two.toml")
    model = ThermalModel.from_spec(spec)
    exp = Experiment(t, U[:, :2], np.where(mask, Y, np.nan)[:, None], "run")
    return U, Y, mask, model, Dataset.from_experiments([exp])


def test_map_of_free_run_residuals_is_the_standardized_innovations(case):
    U, Y, mask, model, data = case
    residual = np.where(mask, Y - free_run(np.column_stack([U[:, :2], 0 * U[:, 2]])), 0.0)
    mapped = np.asarray(dataset_innovation_map(model, data, residual[None, :, None, None]))
    truth = numpy_filter(np.column_stack([U[:, :2], 0 * U[:, 2]]), Y, mask)
    np.testing.assert_allclose(mapped[0, :, 0, 0], truth, rtol=1e-7, atol=1e-9)
    assert np.all(mapped[0, ~mask] == 0.0)


def test_innovation_derivative_along_a_heat_input_is_minus_the_mapped_direction(case):
    U, Y, mask, model, data = case
    h = 1e-3  # innovations are linear in the added gain: the central difference is exact
    numeric = (numpy_filter(U, Y, mask, h) - numpy_filter(U, Y, mask, -h)) / (2 * h)
    # the free-run output response to Q with unit gain (Q starts at 0: x0 unchanged)
    direction = free_run(U, 1.0) - free_run(U, 0.0)
    mapped = np.asarray(dataset_innovation_map(model, data, direction[None, :, None, None]))
    np.testing.assert_allclose(-mapped[0, :, 0, 0], numeric, rtol=1e-6, atol=1e-9)


def test_the_loops_whitening_of_many_directions_is_each_ones_filter(case):
    """The loop whitens directions in padded blocks (`innovation_directions`): each of
    33 columns (over one block) is the standardized innovations of the NumPy filter run
    on that direction alone."""
    from types import SimpleNamespace

    from thermojax.investigation._diagnose_step import WHITEN_BLOCK, innovation_directions

    U, Y, mask, model, data = case
    residual = np.where(mask, Y - free_run(np.column_stack([U[:, :2], 0 * U[:, 2]])), 0.0)
    scales = np.linspace(-2.0, 3.0, WHITEN_BLOCK + 1)
    V = residual[None, :, None, None] * scales  # (runs, T, p, 33)
    whitened = innovation_directions(SimpleNamespace(model=model), data)(V)
    assert whitened.shape == V.shape
    truth = numpy_filter(np.column_stack([U[:, :2], 0 * U[:, 2]]), Y, mask)
    for j, a in enumerate(scales):  # the map is linear: the residual scaled by a
        np.testing.assert_allclose(whitened[0, :, 0, j], a * truth, rtol=1e-7, atol=1e-9)


def test_per_sample_terms_for_held_out_blocks(case):
    # the prequential score of a held-out block sums these terms over its rows
    U, Y, mask, model, data = case
    terms = np.asarray(kalman_sample_nll(model, data))[0]
    truth = numpy_filter(np.column_stack([U[:, :2], 0 * U[:, 2]]), Y, mask, terms=True)
    np.testing.assert_allclose(terms, truth, rtol=1e-9, atol=1e-12)
