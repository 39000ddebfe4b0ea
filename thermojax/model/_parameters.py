"""Free and fixed parameters: a boolean mask per array leaf, and the free ones as one vector.

`eqx.partition` freezes whole leaves; a model file fixes single elements (one
capacitance of six). So the filter spec here is a pytree shaped like the model
whose leaves are boolean NumPy arrays, `True` where the element is free.
`free_parameters` gathers those elements into one flat vector (what an
optimizer sees) and `with_free_parameters` scatters a vector back. Inside
`jit`, pass `FreeIndex(mask)` instead: the same information, hashable. Both
work in NumPy on concrete arrays (no XLA compilation: what a fit does on the host) and
in `jax.numpy` under tracing.
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._network import ThermalNetwork
from ._spec import ModelSpec


def parameter_mask(network: ThermalNetwork, spec: ModelSpec) -> ThermalNetwork:
    """The free/fixed mask of a network built by `ThermalNetwork.from_spec(spec)`."""
    return eqx.tree_at(
        lambda n: (n.log_capacitance, n.log_conductance, n.log_boundary_conductance,
                   n.log_heat_gain),
        network,
        (_free(n.capacitance for n in spec.nodes), _free(k.conductance for k in spec.links),
         _free(b.conductance for b in spec.boundaries), _free(h.gain for h in spec.heat_inputs)),
    )


def _free(params) -> np.ndarray:
    return np.array([not p.fixed for p in params], dtype=bool)


@dataclass(frozen=True)
class FreeIndex:
    """Hashable form of a mask: the flat indices of the free elements, per array leaf."""

    per_leaf: tuple[tuple[int, ...], ...]

    def __init__(self, mask):
        leaves = jax.tree.leaves(eqx.filter(mask, lambda x: isinstance(x, np.ndarray)))
        object.__setattr__(self, "per_leaf",
                           tuple(tuple(int(i) for i in np.flatnonzero(m)) for m in leaves))

    @property
    def size(self) -> int:
        return sum(len(ix) for ix in self.per_leaf)


def _index(mask) -> FreeIndex:
    return mask if isinstance(mask, FreeIndex) else FreeIndex(mask)


def _xp(*arrays):
    """NumPy for concrete arrays, `jax.numpy` under tracing: eager `jax.numpy` would
    compile a small XLA program per shape (a dozen on a first fit)."""
    return jnp if any(isinstance(a, jax.core.Tracer) for a in arrays) else np


def free_parameters(tree, mask) -> jax.Array:
    """The free elements of `tree`'s array leaves, flattened in leaf order: (free,)."""
    leaves = jax.tree.leaves(eqx.filter(tree, eqx.is_array))
    xp = _xp(*leaves)
    parts = [xp.ravel(leaf)[np.array(ix, dtype=int)]
             for leaf, ix in zip(leaves, _index(mask).per_leaf)]
    out = xp.concatenate(parts) if parts else xp.zeros((0,))
    return out if xp is jnp else jax.device_put(out)


def with_free_parameters(tree, mask, theta: jax.Array):
    """`tree` with its free elements replaced by `theta` (free,), the inverse of
    `free_parameters`."""
    index = _index(mask)
    dynamic, static = eqx.partition(tree, eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    if len(leaves) != len(index.per_leaf):
        raise ValueError(f"`with_free_parameters` got a mask for {len(index.per_leaf)} array "
                         f"leaves and a tree with {len(leaves)}.")
    if index.size != theta.shape[0]:
        raise ValueError(f"`with_free_parameters` got {theta.shape[0]} values for {index.size} "
                         "free parameters.")
    xp = _xp(theta, *leaves)
    if xp is np:
        theta = np.asarray(theta)  # slicing a concrete jax.Array would compile too
    out, offset = [], 0
    for leaf, ix in zip(leaves, index.per_leaf):
        if ix:
            values, ix = theta[offset:offset + len(ix)], np.array(ix, dtype=int)
            if xp is jnp:
                leaf = jnp.ravel(leaf).at[ix].set(values).reshape(leaf.shape)
            else:
                flat = np.array(leaf).reshape(-1)
                flat[ix] = values
                leaf = jax.device_put(flat.reshape(np.shape(leaf)))
        out.append(leaf)
        offset += len(ix)
    return eqx.combine(jax.tree.unflatten(treedef, out), static)
