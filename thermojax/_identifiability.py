"""What the data can and cannot tell: the Fisher information in plain words.

The fit's parameters are logs of positive quantities, so the Fisher
information `F` (Gauss-Newton `JᵀJ` of the weighted residuals, or the Hessian
of the Kalman `-log L`) is scale-free: `1/sqrt(μ)` along an eigenvector is the
relative uncertainty of that combination of parameters. A direction whose
relative std exceeds `max_log_std` (default 1: the data cannot pin it within
a factor e ≈ 2.7) is unidentifiable; the parameters that make it up get no
standard error, and the report names the combination and what would fix it.
Initial temperatures (°C) are marginalized out first (Schur complement).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._spec import ModelSpec


@dataclass
class Identifiability:
    covariance: np.ndarray  # pseudo-inverse of F on the identifiable subspace (theta units)
    condition_number: float
    directions: list[dict] = field(default_factory=list)  # unidentifiable combinations
    unidentifiable_parameters: set[str] = field(default_factory=set)

    @property
    def ok(self) -> bool:
        return not self.directions

    @property
    def messages(self) -> list[str]:
        return [d["message"] for d in self.directions]

    def to_json(self) -> dict:
        return {"identifiable": self.ok, "condition_number": _finite(self.condition_number),
                "unidentifiable": [{k: v for k, v in d.items()} for d in self.directions]}


def _finite(x: float):
    return float(x) if np.isfinite(x) else None


def identifiability(info: np.ndarray, names: list[str], spec: ModelSpec,
                    max_log_std: float = 1.0, max_initial_std: float = 10.0) -> Identifiability:
    """Analyse a Fisher information matrix `info` over the free parameters `names`."""
    info = 0.5 * (np.asarray(info, float) + np.asarray(info, float).T)
    k = len(names)
    if k == 0:
        return Identifiability(np.zeros((0, 0)), 1.0)
    is_log = np.array([not n.endswith(".initial") for n in names])
    lg, ini = np.flatnonzero(is_log), np.flatnonzero(~is_log)
    # Marginal information of the log block: F_ll - F_li F_ii^+ F_il.
    F_ll = info[np.ix_(lg, lg)]
    if ini.size:
        F_li = info[np.ix_(lg, ini)]
        F_ll = F_ll - F_li @ np.linalg.pinv(info[np.ix_(ini, ini)]) @ F_li.T
    mu, V = np.linalg.eigh(0.5 * (F_ll + F_ll.T))
    mu_max = max(float(mu.max()) if mu.size else 1.0, 1e-300)
    cond = mu_max / max(float(mu.min()), 1e-300) if mu.size else 1.0
    weak = (mu < 1.0 / max_log_std ** 2) | (mu < 1e-12 * mu_max)
    directions, bad = [], set()
    for j in np.flatnonzero(weak):
        v = V[:, j] / np.max(np.abs(V[:, j]))
        v = v * np.sign(v[np.argmax(np.abs(v))])
        members = {names[lg[i]]: round(float(v[i]), 3) for i in np.argsort(-np.abs(v))
                   if abs(v[i]) > 0.2}
        bad.update(members)
        std = 1.0 / np.sqrt(max(mu[j], 1e-300))
        directions.append({"combination": members, "log_std": _finite(std) if std < 1e150 else None,
                           "message": _explain(members, spec, std)})
    # Covariance: pseudo-inverse over the identifiable directions of the full matrix.
    w, U = np.linalg.eigh(info)
    keep = w > max(1e-12 * max(w.max(), 1e-300), 1.0 / max_log_std ** 2 * 1e-6)
    cov = (U[:, keep] / w[keep]) @ U[:, keep].T
    for i in ini:
        if not (np.sqrt(max(cov[i, i], 0)) < max_initial_std):
            bad.add(names[i])
            directions.append({"combination": {names[i]: 1.0}, "log_std": None,
                               "message": f"{names[i]} is not determined by the data (std over "
                               f"{max_initial_std:g} °C): fix it, or start the run at "
                               "equilibrium and drop the estimate."})
    return Identifiability(cov, cond, directions, bad)


def _explain(members: dict[str, float], spec: ModelSpec, std: float) -> str:
    """One paragraph: which combination, why, and what to fix or measure."""
    caps = [n for n in members if n.endswith(".capacitance")]
    conds = [n for n in members if n.endswith(".conductance")]
    combo = " ".join(f"{w:+.2f}·log({n})" for n, w in members.items())
    how = f"relative std {std:.3g}" if np.isfinite(std) and std < 1e150 else "no information"
    thermal_free = [f"nodes.{n.name}.capacitance" for n in spec.nodes if not n.capacitance.fixed]
    thermal_free += [f"links.{k.key}.conductance" for k in spec.links if not k.conductance.fixed]
    thermal_free += [f"boundaries.{b.key}.conductance" for b in spec.boundaries
                     if not b.conductance.fixed]
    same_sign = all(members.get(n, 0) > 0.5 for n in thermal_free) and len(thermal_free) > 1
    if same_sign and len(caps) + len(conds) == len(members):
        return (f"All capacitances and conductances scale together ({how}): with temperature "
                "inputs only and no measured power, multiplying every C and G by the same factor "
                "leaves every temperature unchanged. Fix one capacitance (for example the "
                "housing's, from its mass and specific heat) or add a known heat input.")
    sensed = {s.node for s in spec.sensors}
    nodes = []
    for n in members:
        parts = n.split(".")
        if parts[0] == "nodes":
            nodes.append(parts[1])
        elif parts[0] == "links":
            nodes += parts[1].split("-")
    unsensed = sorted({n for n in nodes if n in spec.node_names and n not in sensed})
    text = f"The data cannot determine the combination {combo} ({how})."
    if unsensed:
        text += (f" It involves node(s) {unsensed} that no sensor sees; their dynamics are too "
                 "fast or too weakly coupled to show in the measured temperatures. Fix these "
                 "parameters from design data, put a sensor on one of these nodes, or excite the "
                 "system with faster transients (power steps, PRBS) and sample faster.")
    else:
        text += (" Fix one of these parameters from design data, or add excitation that moves "
                 "them differently (ramps at several rates, power steps).")
    return text
