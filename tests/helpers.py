"""Shared test helpers: tolerant tree comparison, random networks, model paths."""

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import thermojax as tj

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


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
