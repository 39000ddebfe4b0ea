"""The information of a network too large for one product per parameter: each
parameter's sensitivities kept on the sensors near the nodes it acts on, all of them
from a few compressed forward products.

On a 1,000-node chain (3,001 free parameters) the exact information `JᵀJ` takes 3,001
forward and reverse product pairs, about 8 minutes, and its Jacobian (9.6 GB) is too
large to hold. But a parameter moves the sensors far from its nodes only through the
slow, weak diffusion between them: its column of `J` is concentrated on the sensors
within a few links. Keeping each column on the sensors within `radius` links of the
states the parameter acts on (its *footprint*), parameters whose footprints do not
overlap share one forward product (Curtis, Powell and Reid's compression of a sparse
Jacobian, with footprints from the network's graph): the product along the sum of a
colour's unit directions is, on each parameter's footprint, that parameter's column
plus the others' tails from beyond their radius. A greedy colouring needs about
`3 (2 radius + 1)` colours on a chain whatever its length, so the information takes a
few batches of forward products instead of `P` pairs.

What it approximates: the tails beyond the radius are dropped from every column, so the
information and the standard errors from it are those of sensitivities truncated at
`radius` links (a test compares them with the exact ones); the fit's steps stay exact
(the conjugate-gradient solves use the exact products, this information only
preconditions them), and the report's `method` says where the stds come from.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from .._blas_threads import every_blas_thread
from ..compilation._traced_cache import stored_jit
from ..dynamics._taylor_hold import gathered

#: Links from the states a parameter acts on within which its sensitivities are kept, to
#: start with: doubled until the dropped tails are below `MAX_TAIL`.
RADIUS = 40
#: The largest share of a sampled column's norm that may lie beyond its footprint.
MAX_TAIL = 1e-2
#: Unit directions per batch when the states each parameter acts on are found.
_TOUCH_BATCH = 16


@stored_jit
def _moved_rows(theta, ap, directions):
    """`(k, n)`: for each direction (k, P), the summed absolute tangent of each state's
    row of `A` (the plan's non-zeros) and of `B`, and of its start in every run."""
    from ._adjoint import _initial
    from ._problem import _model_of

    problem, plan = ap.problem, ap.plan
    data = problem.data

    def parts(t):
        model, run_initial = _model_of(t, problem)
        system = model.linear_system()
        u0 = data.inputs[:, 0].astype(system.A.dtype)
        if run_initial is None or run_initial.shape[1] == 0:
            x0 = jax.vmap(lambda u: _initial(model, system, u, None))(u0)
        else:
            x0 = jax.vmap(lambda u, r: _initial(model, system, u, r))(u0, run_initial)
        return gathered(system.A, plan.a_cols, plan.a_real), system.B, x0

    def tangent(v):
        dA, dB, dx0 = jax.jvp(parts, (theta,), (v,))[1]
        return jnp.abs(dA).sum(1) + jnp.abs(dB).sum(1) + jnp.abs(dx0).sum(0)

    return jax.vmap(tangent)(directions)


def _acted_on(theta, ap) -> np.ndarray:
    """`(P, n)` bool: the states whose row of `A` or `B`, or whose start in some run,
    moves with each parameter (`_moved_rows`, `_TOUCH_BATCH` directions at a time)."""
    P = theta.shape[0]
    out = np.zeros((P, ap.plan.a_cols.shape[0]), bool)
    eye = np.eye(P)
    for start in range(0, P, _TOUCH_BATCH):
        block = eye[start:start + _TOUCH_BATCH]
        k = block.shape[0]
        if k < _TOUCH_BATCH:
            block = np.concatenate([block, np.zeros((_TOUCH_BATCH - k, P))])
        moved = np.asarray(_moved_rows(theta, ap, jax.device_put(block)))
        out[start:start + k] = moved[:k] > 0
    return out


def footprints(acted_on: np.ndarray, a_cols: np.ndarray, a_real: np.ndarray,
               sensor_states: np.ndarray, radius: int) -> np.ndarray:
    """`(P, p)` bool: the sensors reading a state within `radius` links (of `A`'s
    non-zeros, either direction) of a state each parameter acts on. `sensor_states`
    (p, n) bool: the states each sensor reads. A parameter acting on no state (a global
    one) has every sensor."""
    n = a_cols.shape[0]
    rows = np.repeat(np.arange(n), a_cols.shape[1])[a_real.reshape(-1)]
    cols = a_cols.reshape(-1)[a_real.reshape(-1)]
    graph = scipy.sparse.coo_matrix((np.ones(rows.size), (rows, cols)), shape=(n, n))
    hops = scipy.sparse.csgraph.dijkstra(graph, directed=False, unweighted=True,
                                          limit=radius + 0.5)
    near = (hops <= radius).astype(np.float32)                 # (n, n); counts in BLAS
    reach = (acted_on.astype(np.float32) @ near) > 0           # (P, n)
    out = (reach.astype(np.float32) @ sensor_states.T.astype(np.float32)) > 0
    out[~acted_on.any(1)] = True
    return out


def colouring(footprint: np.ndarray) -> np.ndarray:
    """`(P,)` colours, greedy: each parameter takes the first colour none of whose
    parameters' footprints overlaps its own (`footprint` (P, p) bool)."""
    used: list[np.ndarray] = []
    colour = np.empty(footprint.shape[0], int)
    for i, f in enumerate(footprint):
        for c, mask in enumerate(used):
            if not (mask & f).any():
                mask |= f
                colour[i] = c
                break
        else:
            used.append(f.copy())
            colour[i] = len(used) - 1
    return colour


def _compressed(theta, ap, footprint: np.ndarray):
    """`(colour (P,), compressed (R T, p, colours))`: `footprint`'s colouring and one
    forward product per colour, along the sum of its parameters' unit directions."""
    from ._adjoint import _BATCH, _jacobian_columns

    R, T, p = ap.problem.data.outputs.shape
    colour = colouring(footprint)
    k = int(colour.max()) + 1
    P = theta.shape[0]
    compressed = np.empty((R * T, p, k))
    for start in range(0, k, _BATCH):
        width = min(_BATCH, k - start)
        directions = np.zeros((P, _BATCH))
        for c in range(start, start + width):
            directions[colour == c, c - start] = 1.0
        cols = np.asarray(_jacobian_columns(theta, ap, jax.device_put(directions)))
        compressed[:, :, start:start + width] = cols[:, :width].reshape(R * T, p, width)
    return colour, compressed


def _sensor_states(ap) -> np.ndarray:
    """`(p, n)` bool: the states each sensor reads (the plan's non-zeros of `C`)."""
    plan = ap.plan
    out = np.zeros((plan.c_cols.shape[0], plan.a_cols.shape[0]), bool)
    for j in range(out.shape[0]):
        out[j, plan.c_cols[j][plan.c_real[j]]] = True
    return out


def dropped_tails(theta, ap, footprint: np.ndarray) -> float:
    """The largest share of a column's norm that lies outside its footprint, over up to
    `_BATCH` parameters spread evenly (their exact columns, one batch of forward
    products)."""
    from ._adjoint import _BATCH, _jacobian_columns

    P = theta.shape[0]
    R, T, p = ap.problem.data.outputs.shape
    sample = np.unique(np.linspace(0, P - 1, min(_BATCH, P)).round().astype(int))
    directions = np.zeros((P, _BATCH))
    directions[sample, np.arange(sample.size)] = 1.0
    cols = np.asarray(_jacobian_columns(theta, ap, jax.device_put(directions)))
    cols = cols[:, :sample.size].reshape(R * T, p, sample.size)
    total = np.sqrt(np.sum(cols ** 2, axis=(0, 1)))
    outside = np.sqrt(np.sum((cols * ~footprint[sample].T[None]) ** 2, axis=(0, 1)))
    return float(np.max(outside / np.maximum(total, 1e-300)))


def local_information(theta, ap, radius: int = RADIUS) -> tuple[np.ndarray, int, float]:
    """`(H, radius, tail)`: the information `JᵀJ` (P, P) of the weighted data residuals at
    `theta` from the columns of `J` kept on each parameter's footprint (see the module
    docstring), one forward product per colour in the adjoint path's batches; the radius
    used, doubled from `radius` until the dropped tails (`dropped_tails`) are below
    `MAX_TAIL` (or the radius spans the network); and that largest dropped tail."""
    n = ap.plan.a_cols.shape[0]
    plan, acted_on, sensors = ap.plan, _acted_on(theta, ap), _sensor_states(ap)
    while True:
        fp = footprints(acted_on, plan.a_cols, plan.a_real, sensors, radius)
        tail = dropped_tails(theta, ap, fp)
        if tail <= MAX_TAIL or radius >= n:
            break
        radius *= 2
    colour, compressed = _compressed(theta, ap, fp)
    P = theta.shape[0]
    H = np.zeros((P, P))
    with every_blas_thread():
        for s in range(fp.shape[1]):
            members = np.flatnonzero(fp[:, s])    # their colours are distinct: no overlap
            Y = compressed[:, s, colour[members]]
            H[np.ix_(members, members)] += Y.T @ Y
    return H, radius, tail
