"""Twin optima: two starts that reach the same likelihood at different parameter values.

The curvature at one optimum says nothing of another optimum as good: a capacitance at
0.240 ± 0.0007 J/K where another start reaches the same −log L at 0.80 is not
determined to 0.3 %, it is not determined at all between two values. Where several
starts were fitted (`fit(..., n_starts=N)`), every parameter that a start within
`TWIN_NLL` of the best reaches more than `TWIN_STDS` stds away is reported as
non-identifiable, with both values.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ._identifiability import Identifiability

TWIN_NLL = 1.0  # −log L: two optima this close are the same fit for a likelihood-ratio test
TWIN_STDS = 5.0  # stds of the best optimum's curvature


def _physical(name: str, theta: float) -> float:
    return theta if name.endswith(".initial") or name.startswith("effects.") else \
        float(np.exp(theta))


def with_twin_optima(ident: Identifiability, names: list[str], theta: np.ndarray, nll: float,
                     alternatives: list[tuple[np.ndarray, float]]) -> Identifiability:
    """`ident` with the parameters that a twin optimum moves marked non-identifiable.

    `theta` (free,) and `nll` of the best start; `alternatives`: `(theta, nll)` of the
    other starts (theta units: logs of positive parameters)."""
    stds = ident.stds if ident.stds is not None else np.sqrt(np.clip(np.diag(
        ident.covariance), 0.0, None))
    directions, bad = list(ident.directions), set(ident.unidentifiable_parameters)
    for other, other_nll in alternatives:
        if not (np.isfinite(other_nll) and other_nll - nll <= TWIN_NLL):
            continue
        d = np.asarray(other, float) - np.asarray(theta, float)
        far = [j for j, n in enumerate(names) if not n.endswith(".initial")
               and n not in bad and abs(d[j]) > TWIN_STDS * max(float(stds[j]), 1e-300)]
        if not far:
            continue
        pairs = ", ".join(f"{names[j]} {_physical(names[j], theta[j]):.4g} against "
                          f"{_physical(names[j], other[j]):.4g}" for j in far)
        directions.append({
            "parameters": [names[j] for j in far], "dimension": len(far),
            "directions": [{"combination": {names[j]: float(d[j]) for j in far},
                            "log_std": None}],
            "cause": "twin optimum", "fix": [names[j] for j in far],
            "message": (f"two starts reach the same likelihood (−log L within "
                        f"{abs(other_nll - nll):.2g}) at different values: {pairs}. The "
                        "data cannot choose between them, whatever the curvature at one "
                        "says; fix one of these parameters from design data, or add a "
                        "run that excites them differently.")})
        bad.update(names[j] for j in far)
    if len(directions) == len(ident.directions):
        return ident
    stds = np.array(stds, float)
    stds[[j for j, n in enumerate(names) if n in bad]] = np.inf
    return dataclasses.replace(ident, directions=directions, unidentifiable_parameters=bad,
                               stds=stds)
