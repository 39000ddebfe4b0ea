"""State-space systems: the continuous linear system and its exact discrete counterpart."""

from __future__ import annotations

from .. import _jax_settings  # noqa: F401  (float64 and XLA options before any array is made)
import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float


class LinearSystem(eqx.Module):
    """Continuous LTI system `dx/dt = A x + B u`, `y = C x + D u`, in SI units.

    `holds[j]` says how input `j` moves between samples: `"foh"` (piecewise
    linear) or `"zoh"` (piecewise constant). When the system comes from a thermal
    network, `capacitance` holds the node capacitances `c` (J/K) such that
    `-diag(c) A` is symmetric; the modal discretization and the diagonal
    associative scan use that structure. It is `None` for a general system.
    """

    A: Float[Array, "states states"]
    B: Float[Array, "states inputs"]
    C: Float[Array, "outputs states"]
    D: Float[Array, "outputs inputs"]
    holds: tuple[str, ...] = eqx.field(static=True)
    capacitance: Float[Array, " states"] | None = None

    def __check_init__(self):
        n, m, p = self.A.shape[0], self.B.shape[1], self.C.shape[0]
        if self.A.shape != (n, n) or self.B.shape[0] != n or self.C.shape[1] != n or \
                self.D.shape != (p, m):
            raise ValueError(f"`LinearSystem` got inconsistent shapes A{self.A.shape} "
                             f"B{self.B.shape} C{self.C.shape} D{self.D.shape}.")
        if len(self.holds) != m or any(h not in ("foh", "zoh") for h in self.holds):
            raise ValueError(f"`LinearSystem(holds=...)` needs one of 'foh'/'zoh' per input "
                             f"({m} inputs), got {self.holds}.")

    @property
    def n_states(self) -> int:
        return self.A.shape[0]

    def vector_field(self, t, x: Float[Array, " states"], u: Float[Array, " inputs"]):
        """`dx/dt` in K/s (diffrax's `f(t, y, args)` with the input as `args`)."""
        return self.A @ x + self.B @ u

    def observe(self, x: Float[Array, " states"], u: Float[Array, " inputs"]):
        return self.C @ x + self.D @ u

    def steady_state(self, u: Float[Array, " inputs"]) -> Float[Array, " states"]:
        """The equilibrium `x` with `A x + B u = 0` for a constant input `u`."""
        return jnp.linalg.solve(self.A, -(self.B @ u))


class DiscreteSystem(eqx.Module):
    """Sampled system `x[k+1] = Phi x[k] + B0 u[k] + B1 u[k+1]`, `y[k] = C x[k] + D u[k]`.

    The two input matrices carry both holds exactly: a zero-order-hold input has
    a zero column in `B1`; a first-order-hold input splits its effect between
    the samples at either end of the step. `dt` is the sample period (s).
    """

    Phi: Float[Array, "states states"]
    B0: Float[Array, "states inputs"]
    B1: Float[Array, "states inputs"]
    C: Float[Array, "outputs states"]
    D: Float[Array, "outputs inputs"]
    dt: Float[Array, ""]

    @property
    def Gamma(self) -> Float[Array, "states inputs"]:
        """Total input gain over one step for a constant input, `B0 + B1` (the ZOH `B_d`)."""
        return self.B0 + self.B1
