"""Free and fixed parameters: a boolean mask per array leaf, and the free ones as one vector.

`eqx.partition` freezes whole leaves; a model file fixes single elements (one
capacitance of six). So the filter spec here is a pytree shaped like the model
whose leaves are boolean NumPy arrays, `True` where the element is free.
`free_parameters` gathers those elements into one flat vector (what an
optimizer sees) and `with_free_parameters` scatters a vector back.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._network import ThermalNetwork
from ._spec import ModelSpec


def parameter_mask(network: ThermalNetwork, spec: ModelSpec) -> ThermalNetwork:
    """The free/fixed mask of a network built by `ThermalNetwork.from_spec(spec)`."""
    free = lambda params: np.array([not p.fixed for p in params], dtype=bool)  # noqa: E731
    return eqx.tree_at(
        lambda n: (n.log_capacitance, n.log_conductance, n.log_boundary_conductance,
                   n.log_heat_gain),
        network,
        (free(n.capacitance for n in spec.nodes), free(k.conductance for k in spec.links),
         free(b.conductance for b in spec.boundaries), free(h.gain for h in spec.heat_inputs)),
    )


def _leaves(tree):
    return jax.tree.leaves(eqx.filter(tree, eqx.is_array))


def _mask_leaves(mask):
    return jax.tree.leaves(eqx.filter(mask, lambda x: isinstance(x, np.ndarray)))


def free_parameters(tree, mask) -> jax.Array:
    """The free elements of `tree`'s array leaves, flattened in leaf order."""
    parts = [jnp.ravel(leaf)[np.flatnonzero(m)] for leaf, m in zip(_leaves(tree), _mask_leaves(mask))]
    return jnp.concatenate(parts) if parts else jnp.zeros((0,))


def with_free_parameters(tree, mask, theta: jax.Array):
    """`tree` with its free elements replaced by `theta` (inverse of `free_parameters`)."""
    dynamic, static = eqx.partition(tree, eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    out, offset = [], 0
    for leaf, m in zip(leaves, _mask_leaves(mask)):
        idx = np.flatnonzero(m)
        flat = jnp.ravel(leaf).at[idx].set(theta[offset:offset + idx.size])
        out.append(flat.reshape(leaf.shape))
        offset += idx.size
    if offset != theta.shape[0]:
        raise ValueError(f"`with_free_parameters` got {theta.shape[0]} values for {offset} free "
                         "parameters.")
    return eqx.combine(jax.tree.unflatten(treedef, out), static)
