"""The thermal RC network as an equinox Module with unconstrained leaves."""

from __future__ import annotations

from dataclasses import dataclass

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._spec import ModelSpec
from ._system import LinearSystem


@dataclass(frozen=True)
class Topology:
    """Hashable structure of a network: names and indices, no numbers to fit.

    Inputs are the distinct data columns driving the network, boundary
    temperatures (°C) and heat inputs (W) in one list; outputs are the sensors.
    """

    node_names: tuple[str, ...]
    links: tuple[tuple[int, int], ...]
    boundary_nodes: tuple[int, ...]
    boundary_inputs: tuple[int, ...]  # index into input_names, per boundary entry
    heat_nodes: tuple[int, ...]
    heat_inputs: tuple[int, ...]  # index into input_names, per heat-input entry
    input_names: tuple[str, ...]
    input_holds: tuple[str, ...]
    sensor_nodes: tuple[int, ...]
    sensor_names: tuple[str, ...]

    @property
    def n_nodes(self) -> int:
        return len(self.node_names)

    def __post_init__(self):
        n, m = len(self.node_names), len(self.input_names)
        for i, j in self.links:
            if not (0 <= i < n and 0 <= j < n) or i == j:
                raise ValueError(f"`Topology(links=...)` has link ({i}, {j}), but only {n} nodes "
                                 "were given. Node indices are 0-based and a link joins two "
                                 "different nodes.")
        for idx in (*self.boundary_nodes, *self.heat_nodes, *self.sensor_nodes):
            if not 0 <= idx < n:
                raise ValueError(f"`Topology` refers to node {idx}, but only {n} nodes were "
                                 "given. Node indices are 0-based.")
        for idx in (*self.boundary_inputs, *self.heat_inputs):
            if not 0 <= idx < m:
                raise ValueError(f"`Topology` refers to input {idx}, but only {m} inputs were "
                                 "given.")
        if len(self.boundary_nodes) != len(self.boundary_inputs) or \
                len(self.heat_nodes) != len(self.heat_inputs) or \
                len(self.sensor_nodes) != len(self.sensor_names) or \
                len(self.input_holds) != m:
            raise ValueError("`Topology` got lists of mismatched lengths.")

    def link_incidence(self) -> np.ndarray:
        """`(links, nodes)`: +1 at a link's first node, −1 at its second (static)."""
        E = np.zeros((len(self.links), self.n_nodes))
        for k, (i, j) in enumerate(self.links):
            E[k, i], E[k, j] = 1.0, -1.0
        return E

    def boundary_incidence(self) -> np.ndarray:
        """`(boundaries, nodes)`: 1 at each boundary entry's node (static)."""
        E = np.zeros((len(self.boundary_nodes), self.n_nodes))
        E[np.arange(len(self.boundary_nodes)), list(self.boundary_nodes)] = 1.0
        return E

    @classmethod
    def from_spec(cls, spec: ModelSpec) -> "Topology":
        idx = {name: i for i, name in enumerate(spec.node_names)}
        cols = {c: j for j, c in enumerate(spec.input_columns)}
        return cls(
            node_names=spec.node_names,
            links=tuple((idx[a], idx[b]) for a, b in (link.between for link in spec.links)),
            boundary_nodes=tuple(idx[b.node] for b in spec.boundaries),
            boundary_inputs=tuple(cols[b.input] for b in spec.boundaries),
            heat_nodes=tuple(idx[h.node] for h in spec.heat_inputs),
            heat_inputs=tuple(cols[h.input] for h in spec.heat_inputs),
            input_names=spec.input_columns,
            input_holds=spec.input_holds,
            sensor_nodes=tuple(idx[s.node] for s in spec.sensors),
            sensor_names=spec.sensor_columns,
        )


#: Each parameter group a unit may scale (dotted name `group.key.name`, docs/formats.md
#: §5): the `ThermalNetwork` leaf holding its logs, and the parameter's `name`.
SCALABLE_LEAVES = {"nodes": ("log_capacitance", "capacitance"),
                   "links": ("log_conductance", "conductance"),
                   "boundaries": ("log_boundary_conductance", "conductance"),
                   "heat_inputs": ("log_heat_gain", "gain")}


class ThermalNetwork(eqx.Module):
    """Lumped RC network `C dT/dt = -(L + diag(g_b)) T + G_b u_T + B_q q`, `y = T[sensors]`.

    `L` is the Laplacian of the link conductances, `g_b` the boundary conductance
    summed per node, `u_T` the boundary temperatures (°C) and `q` the heat
    inputs (W). Every leaf is unconstrained: capacitances (J/K), conductances
    (W/K) and heat-input gains are the exponentials of the leaves, so any
    optimizer step keeps the model physical. `A = -C⁻¹(L + diag(g_b))` is similar
    through `C^½` to a symmetric negative semidefinite matrix, and negative
    definite when every node has a path to a boundary.

    Build it with `ThermalNetwork.from_physical(...)` or `from_spec(spec)`.
    """

    log_capacitance: Float[Array, " nodes"]
    log_conductance: Float[Array, " links"]
    log_boundary_conductance: Float[Array, " boundaries"]
    log_heat_gain: Float[Array, " heat_inputs"]
    topology: Topology = eqx.field(static=True)

    def __check_init__(self):
        t = self.topology
        expected = (t.n_nodes, len(t.links), len(t.boundary_nodes), len(t.heat_nodes))
        got = (self.log_capacitance.shape, self.log_conductance.shape,
               self.log_boundary_conductance.shape, self.log_heat_gain.shape)
        if tuple(s[0] if len(s) == 1 else -1 for s in got) != expected:
            raise ValueError(f"`ThermalNetwork` leaves have shapes {got}, but the topology needs "
                             f"{expected} (nodes, links, boundaries, heat inputs).")

    @classmethod
    def from_physical(cls, topology: Topology, capacitance, conductance, boundary_conductance,
                      heat_gain=None) -> "ThermalNetwork":
        """Build from physical values: capacitance (J/K, per node), conductance (W/K, per
        link), boundary_conductance (W/K, per boundary entry), heat_gain (per heat input,
        default 1)."""
        if heat_gain is None:
            heat_gain = np.ones(len(topology.heat_nodes))

        def log(x, what):
            if isinstance(x, jax.core.Tracer):
                return jnp.log(x)
            x = np.asarray(x, dtype=float)  # concrete: checked and logged in NumPy
            if x.ndim != 1 or not np.all(x > 0):
                raise ValueError(f"`ThermalNetwork.from_physical({what}=...)` needs a 1-d array "
                                 f"of positive values, got {x}.")
            return jax.device_put(np.log(x))

        return cls(log(capacitance, "capacitance"), log(conductance, "conductance"),
                   log(boundary_conductance, "boundary_conductance"),
                   log(heat_gain, "heat_gain"), topology)

    @classmethod
    def from_spec(cls, spec: ModelSpec) -> "ThermalNetwork":
        """Build from a model file's values (each parameter starts at its value)."""
        return cls.from_physical(
            Topology.from_spec(spec),
            [n.capacitance.value for n in spec.nodes],
            [link.conductance.value for link in spec.links],
            [b.conductance.value for b in spec.boundaries],
            [h.gain.value for h in spec.heat_inputs],
        )

    @property
    def capacitance(self) -> Float[Array, " nodes"]:
        return jnp.exp(self.log_capacitance)

    @property
    def conductance(self) -> Float[Array, " links"]:
        return jnp.exp(self.log_conductance)

    @property
    def boundary_conductance(self) -> Float[Array, " boundaries"]:
        return jnp.exp(self.log_boundary_conductance)

    @property
    def heat_gain(self) -> Float[Array, " heat_inputs"]:
        return jnp.exp(self.log_heat_gain)

    def conductance_matrix(self) -> Float[Array, "nodes nodes"]:
        """`K = L + diag(g_b)` (W/K): symmetric, positive semidefinite."""
        return conductance_matrix(self.topology, self.conductance, self.boundary_conductance)

    def input_matrix(self) -> Float[Array, "nodes inputs"]:
        """Heat flow per unit input (W/K for temperatures, 1 for powers), before `C⁻¹`."""
        t = self.topology
        G = jnp.zeros((t.n_nodes, len(t.input_names)))
        if t.boundary_nodes:
            G = G.at[np.array(t.boundary_nodes), np.array(t.boundary_inputs)].add(
                self.boundary_conductance)
        if t.heat_nodes:
            G = G.at[np.array(t.heat_nodes), np.array(t.heat_inputs)].add(self.heat_gain)
        return G

    def output_matrix(self) -> Float[Array, "sensors nodes"]:
        t = self.topology
        return jnp.zeros((len(t.sensor_nodes), t.n_nodes)).at[
            np.arange(len(t.sensor_nodes)), np.array(t.sensor_nodes, dtype=int)].set(1.0)

    def linear_system(self) -> LinearSystem:
        """The continuous state-space form, states = node temperatures (°C)."""
        c = self.capacitance
        A = -self.conductance_matrix() / c[:, None]
        B = self.input_matrix() / c[:, None]
        Cy = self.output_matrix()
        D = jnp.zeros((Cy.shape[0], B.shape[1]))
        return LinearSystem(A, B, Cy, D, holds=self.topology.input_holds, capacitance=c)

    def time_constants(self) -> Float[Array, " nodes"]:
        """The network's time constants (s), ascending: `1/eig(C^-½ K C^-½)`."""
        return time_constants(self.capacitance, self.conductance_matrix())


def conductance_matrix(topology: Topology, conductance, boundary_conductance):
    """`K = Eᵀ diag(g) E + E_bᵀ diag(g_b) E_b` (W/K, `(nodes, nodes)`) from the link and
    boundary incidences. NumPy in, NumPy out (host-side checks need no compilation);
    JAX arrays in, JAX out (traced in a fit)."""
    xp = np if isinstance(conductance, np.ndarray) else jnp
    g, gb = xp.asarray(conductance), xp.asarray(boundary_conductance)
    if xp is jnp and topology.n_nodes >= _SCATTER_NODES:
        return _scattered_conductance_matrix(topology, g, gb)
    E, Eb = topology.link_incidence(), topology.boundary_incidence()
    return E.T @ (g[:, None] * E) + Eb.T @ (gb[:, None] * Eb)


# From this many nodes on, a traced `K` is written entry by entry: the incidence product
# costs `links · nodes²` (2e9 operations, about 0.15 s on two cores, at 1,000 nodes) where
# the entries cost `links`. Below it the product stays (the programs compiled for small
# networks unchanged).
_SCATTER_NODES = 64


def _scattered_conductance_matrix(topology: Topology, g, gb):
    """`conductance_matrix` (JAX) by adding each link's and boundary's entries."""
    n = topology.n_nodes
    K = jnp.zeros((n, n), g.dtype)
    if topology.links:
        i, j = np.array(topology.links).T
        K = K.at[i, i].add(g).at[j, j].add(g).at[i, j].add(-g).at[j, i].add(-g)
    if topology.boundary_nodes:
        b = np.array(topology.boundary_nodes)
        K = K.at[b, b].add(gb)
    return K


def local_time_constants(spec: ModelSpec) -> dict[str, float]:
    """Each node's own time constant `C_i / Σ G` (s) at the spec's values: its
    capacitance over the conductances touching it (nodes touching none are left out)."""
    total = {n.name: 0.0 for n in spec.nodes}
    for k in spec.links:
        for n in k.between:
            total[n] += k.conductance.value
    for b in spec.boundaries:
        total[b.node] += b.conductance.value
    return {n.name: n.capacitance.value / total[n.name] for n in spec.nodes if total[n.name] > 0}


def time_constants(capacitance, K):
    """Time constants (s, ascending) `1/eig(C^-½ K C^-½)` of capacitances (J/K) and a
    conductance matrix `K` (W/K); inf for a node set with no path to a boundary.
    NumPy or JAX, as `conductance_matrix`."""
    xp = np if isinstance(K, np.ndarray) else jnp
    s = xp.sqrt(xp.asarray(capacitance))
    S = K / s[:, None] / s[None, :]
    return xp.sort(1.0 / xp.linalg.eigvalsh(0.5 * (S + S.T)))


class StableDynamics(eqx.Module):
    """A dense black-box block `A = -(M Mᵀ + eps I) + (S - Sᵀ)`, Hurwitz by construction.

    Its symmetric part `-(M Mᵀ + eps I)` is negative definite, so every
    eigenvalue of `A` has real part at most `-eps` (1/s). Use it for parts of a
    model with no physical structure; `M` and `S` are unconstrained.
    """

    M: Float[Array, "states states"]
    S: Float[Array, "states states"]
    eps: float = eqx.field(static=True, default=1e-6)

    def matrix(self) -> Float[Array, "states states"]:
        n = self.M.shape[0]
        return -(self.M @ self.M.T + self.eps * jnp.eye(n)) + (self.S - self.S.T)
