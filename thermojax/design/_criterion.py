"""What a design maximizes: a scalar of the Fisher information, with a weak prior.

Both criteria work on the marginal information `F_m` of the judged parameters (the
initial temperatures estimated too, `marginal_information`) plus a prior precision
`I / s²` (`s = PRIOR_LOG_STD`: a parameter known to within a factor e before the run),
which keeps a criterion finite where a profile leaves a direction undetermined:

- D-optimal (`"d"`): maximize `log det (F_m + I/s²)`, the volume of the joint confidence
  region shrunk; for logs of positive parameters it does not depend on their units.
- Named variances (`"variance"`): minimize `Σ_i log [(F_m + I/s²)⁻¹]_ii` over the named
  parameters: each one's relative variance, the others estimated alongside.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._errors import InputError

CRITERIA = ("d", "variance")

#: The prior std of every judged parameter, in its log (a factor e).
PRIOR_LOG_STD = 1.0


def criterion_loss(Fm, kind: str, targets: np.ndarray | None = None):
    """The value a search minimizes: `−log det` (D) or the sum of log variances of the
    `targets` (indices into the judged parameters)."""
    k = Fm.shape[0]
    M = 0.5 * (Fm + Fm.T) + jnp.eye(k, dtype=Fm.dtype) / PRIOR_LOG_STD ** 2
    if kind == "d":
        L = jnp.linalg.cholesky(M)
        return -2.0 * jnp.sum(jnp.log(jnp.diag(L)))
    if kind == "variance":
        E = jnp.eye(k, dtype=Fm.dtype)[:, targets]
        X = jnp.linalg.solve(M, E)
        return jnp.sum(jnp.log(jnp.sum(E * X, axis=0)))
    raise ValueError(f"unknown criterion {kind!r}; expected one of {CRITERIA}.")


def target_indices(judged: list[str], targets: list[str] | None, kind: str,
                   source: str | None = None) -> np.ndarray | None:
    """Indices of the named parameters among the judged ones; refuses an unknown name."""
    if kind == "d":
        return None
    if not targets:
        raise InputError("the variance criterion needs at least one --parameter NAME.",
                         field="--parameter")
    out = []
    for name in targets:
        if name not in judged:
            raise InputError(f"'{name}' is not a free parameter of the model; free ones are "
                             f"{', '.join(judged)}.", file=source, field="--parameter")
        out.append(judged.index(name))
    return np.array(out, dtype=int)
