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

from ..model._spec import ModelSpec


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
                    max_log_std: float = 1.0, max_initial_std: float = 10.0,
                    sample_period: float | None = None) -> Identifiability:
    """Analyse a Fisher information matrix `info` over the free parameters `names`.

    Unidentifiable eigen-directions that share parameters are reported together,
    as one subspace with one message. `sample_period` (s) lets the message say
    when a node is faster than the sampling.
    """
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
    groups: list[dict] = []  # directions sharing parameters, merged
    for j in np.flatnonzero(weak):
        v = V[:, j] / np.max(np.abs(V[:, j]))
        v = v * np.sign(v[np.argmax(np.abs(v))])
        members = {names[lg[i]]: round(float(v[i]), 3) for i in np.argsort(-np.abs(v))
                   if abs(v[i]) > 0.2}
        std = 1.0 / np.sqrt(max(mu[j], 1e-300))
        entry = {"combination": members, "log_std": _finite(std) if std < 1e150 else None}
        touching = [g for g in groups if set(g["parameters"]) & set(members)]
        merged = {"parameters": sorted(set(members).union(*[g["parameters"] for g in touching])),
                  "directions": [entry] + [d for g in touching for d in g["directions"]]}
        groups = [g for g in groups if g not in touching] + [merged]
    directions, bad = [], set()
    for g in groups:
        bad.update(g["parameters"])
        first = g["directions"][0]
        std = first["log_std"] if first["log_std"] is not None else float("inf")
        if len(g["directions"]) == 1:
            msg = _explain(first["combination"], spec, std, sample_period)
        else:
            msg = _explain({p: 1.0 for p in g["parameters"]}, spec, std, sample_period,
                           subspace=len(g["directions"]))
        directions.append({"parameters": g["parameters"], "dimension": len(g["directions"]),
                           "directions": g["directions"], "message": msg})
    # Covariance: pseudo-inverse over the identifiable directions of the full matrix.
    w, U = np.linalg.eigh(info)
    keep = w > max(1e-12 * max(w.max(), 1e-300), 1.0 / max_log_std ** 2 * 1e-6)
    cov = (U[:, keep] / w[keep]) @ U[:, keep].T
    # An initial temperature on a dropped (null) direction has no finite std, although the
    # pseudo-inverse gives it a small one: flag it like a log parameter of such a direction.
    null = U[:, ~keep]
    on_null = (np.abs(null) > 0.2 * np.max(np.abs(null), axis=0)).any(axis=1) if null.size \
        else np.zeros(k, bool)
    for i in ini:
        if on_null[i] or not (np.sqrt(max(cov[i, i], 0)) < max_initial_std):
            bad.add(names[i])
            directions.append({"parameters": [names[i]], "dimension": 1,
                               "directions": [{"combination": {names[i]: 1.0}, "log_std": None}],
                               "message": f"{names[i]} is not determined by the data (std over "
                               f"{max_initial_std:g} °C): fix it, or start the run at "
                               "equilibrium and drop the estimate."})
    return Identifiability(cov, cond, directions, bad)


def _explain(members: dict[str, float], spec: ModelSpec, std: float,
             sample_period: float | None = None, subspace: int = 1) -> str:
    """One paragraph: which combination, why, and what to fix or measure."""
    caps = [n for n in members if n.endswith(".capacitance")]
    conds = [n for n in members if n.endswith(".conductance")]
    if subspace > 1:
        combo = f"any of {subspace} independent combinations of {', '.join(members)}"
    else:
        combo = "the combination " + " ".join(f"{w:+.2f}·log({n})" for n, w in members.items())
    how = f"relative std {std:.3g}" if np.isfinite(std) and std < 1e150 else "no information"
    thermal_free = [f"nodes.{n.name}.capacitance" for n in spec.nodes if not n.capacitance.fixed]
    thermal_free += [f"links.{k.key}.conductance" for k in spec.links if not k.conductance.fixed]
    thermal_free += [f"boundaries.{b.key}.conductance" for b in spec.boundaries
                     if not b.conductance.fixed]
    same_sign = all(members.get(n, 0) > 0.5 for n in thermal_free) and len(thermal_free) > 1
    if same_sign and len(caps) + len(conds) == len(members):
        return (f"All capacitances and conductances scale together ({how}): with temperature "
                "inputs only and no measured power, multiplying every C and G by the same factor "
                "leaves every temperature unchanged. Fix one capacitance (from a part's mass and specific "
                "heat) or add a known heat input (a measured power).")
    sensed = {s.node for s in spec.sensors}
    nodes = []
    for n in members:
        parts = n.split(".")
        if parts[0] == "nodes":
            nodes.append(parts[1])
        elif parts[0] == "links":
            nodes += parts[1].split("-")
    unsensed = sorted({n for n in nodes if n in spec.node_names and n not in sensed})
    text = f"The data cannot determine {combo} ({how})."
    if unsensed:
        text += (f" It involves node(s) {unsensed} that no sensor sees; their dynamics are too "
                 "fast or too weakly coupled to show in the measured temperatures.")
        fast = {n: tau for n, tau in _local_time_constants(spec).items()
                if n in unsensed and sample_period is not None and tau < 2 * sample_period}
        if fast:
            listing = ", ".join(f"{n} ~{tau:.2g} s" for n, tau in fast.items())
            text += (f" Local time constant(s) {listing} are shorter than twice the sample "
                     f"period ({sample_period:g} s): these dynamics fall between samples; "
                     f"sample faster than {1 / min(fast.values()):.2g} Hz to see them.")
        text += (" Fix these parameters from design data, put a sensor on one of these nodes, "
                 "or excite the system with faster transients (power steps, PRBS).")
    else:
        text += (" Fix one of these parameters from design data, or add excitation that moves "
                 "them differently (ramps at several rates, power steps).")
    return text


def _local_time_constants(spec: ModelSpec) -> dict[str, float]:
    """Each node's own time constant `C_i / Σ G` (s) from the spec's values."""
    total = {n.name: 0.0 for n in spec.nodes}
    for k in spec.links:
        for n in k.between:
            total[n] += k.conductance.value
    for b in spec.boundaries:
        total[b.node] += b.conductance.value
    return {n.name: n.capacitance.value / total[n.name] for n in spec.nodes if total[n.name] > 0}
