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
import numpy as np
import scipy.sparse
import scipy.sparse.csgraph

from .._blas_threads import every_blas_thread

#: Links from the states a parameter acts on within which its sensitivities are kept, to
#: start with: doubled until the dropped tails are below `MAX_TAIL`.
RADIUS = 40
#: The largest share of a sampled column's norm that may lie beyond its footprint.
MAX_TAIL = 1e-2


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


def _compressed(columns, footprint: np.ndarray, n_rows: int, batch: int):
    """`(colour (P,), compressed (n_rows, p, colours))`: `footprint`'s colouring and one
    forward product per colour, along the sum of its parameters' unit directions
    (`columns(V (P, batch)) -> J V (n_rows p, batch)`)."""
    P, p = footprint.shape
    colour = colouring(footprint)
    k = int(colour.max()) + 1
    compressed = np.empty((n_rows, p, k))
    for start in range(0, k, batch):
        width = min(batch, k - start)
        directions = np.zeros((P, batch))
        for c in range(start, start + width):
            directions[colour == c, c - start] = 1.0
        cols = np.asarray(columns(jax.device_put(directions)))
        compressed[:, :, start:start + width] = cols[:, :width].reshape(n_rows, p, width)
    return colour, compressed


def sensor_states(plan) -> np.ndarray:
    """`(p, n)` bool: the states each sensor reads (a `SparsePlan`'s non-zeros of `C`)."""
    out = np.zeros((plan.c_cols.shape[0], plan.a_cols.shape[0]), bool)
    for j in range(out.shape[0]):
        out[j, plan.c_cols[j][plan.c_real[j]]] = True
    return out


def dropped_tails(columns, footprint: np.ndarray, n_rows: int, batch: int) -> float:
    """The largest share of a column's norm that lies outside its footprint, over up to
    `batch` parameters spread evenly (their exact columns, one batch of forward
    products)."""
    P, p = footprint.shape
    sample = np.unique(np.linspace(0, P - 1, min(batch, P)).round().astype(int))
    directions = np.zeros((P, batch))
    directions[sample, np.arange(sample.size)] = 1.0
    cols = np.asarray(columns(jax.device_put(directions)))
    cols = cols[:, :sample.size].reshape(n_rows, p, sample.size)
    total = np.sqrt(np.sum(cols ** 2, axis=(0, 1)))
    outside = np.sqrt(np.sum((cols * ~footprint[sample].T[None]) ** 2, axis=(0, 1)))
    return float(np.max(outside / np.maximum(total, 1e-300)))


def local_information(columns, acted_on: np.ndarray, plan, n_rows: int, batch: int,
                      radius: int = RADIUS) -> tuple[np.ndarray, int, float]:
    """`(H, radius, tail)`: the information `JᵀJ` (P, P) from the columns of `J` kept on
    each parameter's footprint (see the module docstring), one forward product per
    colour; the radius used, doubled from `radius` until the dropped tails
    (`dropped_tails`) are below `MAX_TAIL` (or the radius spans the network); and that
    largest dropped tail.

    `columns(V)`: the Jacobian `J V` (n_rows · p, batch) of the weighted residuals,
    rows in (row, sensor) order, for directions `V` (P, batch); `acted_on` (P, n) bool:
    the states each parameter acts on; `plan`: the network's `SparsePlan` (its graph and
    the sensors' states)."""
    n = plan.a_cols.shape[0]
    sensors = sensor_states(plan)
    while True:
        fp = footprints(acted_on, plan.a_cols, plan.a_real, sensors, radius)
        tail = dropped_tails(columns, fp, n_rows, batch)
        if tail <= MAX_TAIL or radius >= n:
            break
        radius *= 2
    colour, compressed = _compressed(columns, fp, n_rows, batch)
    P = acted_on.shape[0]
    H = np.zeros((P, P))
    with every_blas_thread():
        for s in range(fp.shape[1]):
            members = np.flatnonzero(fp[:, s])    # their colours are distinct: no overlap
            Y = compressed[:, s, colour[members]]
            H[np.ix_(members, members)] += Y.T @ Y
    return H, radius, tail
