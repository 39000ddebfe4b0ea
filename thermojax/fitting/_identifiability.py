"""What the data can and cannot tell: the Fisher information in plain words.

The fit's parameters are logs of positive quantities, so the Fisher
information `F` (Gauss-Newton `JᵀJ` of the weighted residuals, or the Kalman
likelihood's Fisher information from innovation sensitivities) is scale-free: `1/sqrt(μ)` along an eigenvector is the
relative uncertainty of that combination of parameters. A direction whose
relative std exceeds `max_log_std` (default 1: the data cannot pin it within
a factor e ≈ 2.7) is unidentifiable; the parameters that make it up get no
standard error, and the report names the combination and what would fix it.
Initial temperatures (°C) are marginalized out first (Schur complement).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..model._network import local_time_constants
from ..model._spec import ModelSpec


@dataclass
class Identifiability:
    covariance: np.ndarray  # pseudo-inverse of F on the identifiable subspace (theta units)
    condition_number: float
    directions: list[dict] = field(default_factory=list)  # unidentifiable combinations
    unidentifiable_parameters: set[str] = field(default_factory=set)
    # Std of each free parameter (theta units: log for positive parameters), inf where a
    # truncated direction leaves it undetermined; None: the covariance's diagonal.
    stds: np.ndarray | None = None

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
                    sample_period: float | None = None, powered: bool | None = None
                    ) -> Identifiability:
    """Analyse a Fisher information matrix `info` over the free parameters `names`.

    The truncated directions are those the solvers leave out (`TruncatedGaussNewton`'s
    `min_singular_value` and `TruncatedNewton`'s `min_curvature` default to the same
    threshold, a std of `max_log_std`). Every parameter with a non-negligible loading on
    one (over `_LOADING` of the direction's largest) is named and gets no std; the others'
    stds include what the truncated directions add. Directions that share parameters are
    reported together, as one subspace with one message, whose cause is structural (the
    model's transfer function does not change along it: no sensor can separate them),
    sampling (an unsensed node faster than `sample_period`, s) or practical (too little
    excitation), and whose advice removes the whole subspace. `powered`: whether the runs
    drive a heat input (not all zero); default: whether the model has one. Without
    power the common scale of every C and G is named as such, with the advice to add a
    known heat input.
    """
    powered = bool(spec.heat_inputs) if powered is None else bool(powered)
    info = 0.5 * (np.asarray(info, float) + np.asarray(info, float).T)
    k = len(names)
    if k == 0:
        return Identifiability(np.zeros((0, 0)), 1.0, stds=np.zeros(0))
    # Initial temperatures (°C) are marginalized out; every other parameter (logs of
    # positive ones, signed effect parameters on their own scale) is judged.
    marg = np.array([n.endswith(".initial") for n in names])
    lg, ini = np.flatnonzero(~marg), np.flatnonzero(marg)
    # Marginal information of the judged block: F_ll - F_li F_ii^+ F_il.
    F_ll = info[np.ix_(lg, lg)]
    if ini.size:
        F_li = info[np.ix_(lg, ini)]
        F_ll = F_ll - F_li @ np.linalg.pinv(info[np.ix_(ini, ini)]) @ F_li.T
    mu, V = np.linalg.eigh(0.5 * (F_ll + F_ll.T))
    mu_max = max(float(mu.max()) if mu.size else 1.0, 1e-300)
    cond = mu_max / max(float(mu.min()), 1e-300) if mu.size else 1.0
    weak = (mu < 1.0 / max_log_std ** 2) | (mu < 1e-12 * mu_max)
    # Stds of the judged block: the kept directions' inverse plus the truncated ones'
    # share (a direction without information adds an infinite one).
    with np.errstate(divide="ignore"):
        inv_mu = np.where(mu > 1e-14 * mu_max, 1.0 / np.maximum(mu, 1e-300), np.inf)
    loading = np.abs(V) / np.maximum(np.abs(V).max(axis=0, keepdims=True), 1e-300)
    with np.errstate(invalid="ignore"):
        trunc_var = np.where(weak[None, :] & (loading > 1e-9), V ** 2 * inv_mu[None, :],
                             0.0).sum(axis=1)
    kept_var = (V[:, ~weak] ** 2 * inv_mu[None, ~weak]).sum(axis=1)
    involved = (loading[:, weak] > _LOADING).any(axis=1)
    del trunc_var  # below `_LOADING` a loading is treated as roundoff of the eigenvectors
    stds = np.full(k, np.inf)
    stds[lg] = np.where(involved, np.inf, np.sqrt(kept_var))
    groups: list[dict] = []  # directions sharing parameters, merged
    for j in np.flatnonzero(weak):
        v = V[:, j] / np.max(np.abs(V[:, j]))
        v = v * np.sign(v[np.argmax(np.abs(v))])
        # the direction itself, every loading to 3 decimals: one below `_LOADING` names no
        # parameter (`members`), but left out it would move the direction off the null
        # space (by up to a tenth where a subspace's basis, arbitrary within it, has one)
        order = np.argsort(-np.abs(v))
        combination = {names[lg[i]]: round(float(v[i]), 3) for i in order
                       if round(float(v[i]), 3) != 0.0}
        members = {names[lg[i]]: combination[names[lg[i]]] for i in order
                   if abs(v[i]) > _LOADING}
        std = 1.0 / np.sqrt(max(mu[j], 1e-300))
        entry = {"combination": combination, "log_std": _finite(std) if std < 1e150 else None,
                 "cause": _cause(spec, {names[lg[i]]: float(v[i]) for i in range(len(lg))},
                                 sample_period, mu[j] < 1e-12 * mu_max)}
        touching = [g for g in groups if set(g["parameters"]) & set(members)]
        merged = {"parameters": sorted(set(members).union(*[g["parameters"] for g in touching])),
                  "directions": [entry] + [d for g in touching for d in g["directions"]],
                  "columns": [j] + [c for g in touching for c in g["columns"]]}
        groups = [g for g in groups if g not in touching] + [merged]
    directions, bad = [], {names[lg[i]] for i in np.flatnonzero(involved)}
    lg_names = [names[i] for i in lg]
    # the common scale of every C and G may span several groups: said once, in the group
    # holding most of the capacitances and conductances
    scaled = None
    if groups and _has_scale(V[:, weak], lg_names, spec, powered):
        thermal = set(_thermal_free(spec))
        scaled = max(range(len(groups)),
                     key=lambda i: len(thermal & set(groups[i]["parameters"])))
    for i_group, g in enumerate(groups):
        bad.update(g["parameters"])
        basis = V[:, g["columns"]]
        msg, cause, to_fix = _explain_group(g, basis, lg_names, spec, sample_period,
                                            i_group == scaled)
        for d in g["directions"]:
            d.pop("cause", None)
        directions.append({"parameters": g["parameters"], "dimension": len(g["directions"]),
                           "directions": g["directions"], "cause": cause, "fix": to_fix,
                           "message": msg})
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
        stds[i] = np.sqrt(max(cov[i, i], 0.0))
        if on_null[i] or not (stds[i] < max_initial_std):
            stds[i] = np.inf
            bad.add(names[i])
            directions.append({"parameters": [names[i]], "dimension": 1,
                               "directions": [{"combination": {names[i]: 1.0}, "log_std": None}],
                               "cause": "practical", "fix": [names[i]],
                               "message": f"{names[i]} is not determined by the data (std over "
                               f"{max_initial_std:g} °C): fix it, or start the run at "
                               "equilibrium and drop the estimate."})
    for i, n in enumerate(names):
        if n in bad:
            stds[i] = np.inf
    return Identifiability(cov, cond, directions, bad, stds)


# A truncated direction's loading on a parameter (relative to its largest loading) above
# which the parameter takes part in it: it is named, and its std is infinite.
_LOADING = 0.1


def _is_positive(name: str) -> bool:
    from ._problem import _is_log

    return _is_log(name)


def _thermal_matrices(spec: ModelSpec, values: dict[str, float]):
    """`(A, B, Cy)` of `spec`'s network (NumPy) with the physical `values` by name."""
    idx = {n: i for i, n in enumerate(spec.node_names)}
    n = len(idx)
    cols = list(dict.fromkeys([b.input for b in spec.boundaries]
                              + [h.input for h in spec.heat_inputs]))
    C = np.array([values.get(f"nodes.{nd.name}.capacitance", nd.capacitance.value)
                  for nd in spec.nodes])
    K, B = np.zeros((n, n)), np.zeros((n, max(len(cols), 1)))
    for lk in spec.links:
        g = values.get(f"links.{lk.key}.conductance", lk.conductance.value)
        a, b = idx[lk.between[0]], idx[lk.between[1]]
        K[a, a] += g
        K[b, b] += g
        K[a, b] -= g
        K[b, a] -= g
    for bd in spec.boundaries:
        g = values.get(f"boundaries.{bd.key}.conductance", bd.conductance.value)
        K[idx[bd.node], idx[bd.node]] += g
        B[idx[bd.node], cols.index(bd.input)] += g
    for h in spec.heat_inputs:
        B[idx[h.node], cols.index(h.input)] += values.get(f"heat_inputs.{h.key}.gain",
                                                          h.gain.value)
    Cy = np.zeros((len(spec.sensors), n))
    for r, s in enumerate(spec.sensors):
        Cy[r, idx[s.node]] = 1.0
    return -K / C[:, None], B / C[:, None], Cy


def _structural(spec: ModelSpec, direction: dict[str, float]) -> bool:
    """Whether moving the parameters along `direction` (theta units) leaves the network's
    transfer function from every input to every sensor unchanged at every frequency: an
    exact invariance of the model, which no amount of data of this kind resolves. Only
    capacitances, conductances and heat gains are judged (False when the direction loads
    anything else: an effect, a noise)."""
    thermal = (".capacitance", ".conductance", ".gain")

    def is_thermal(n: str) -> bool:
        return n.split(".")[0] in ("nodes", "links", "boundaries", "heat_inputs") \
            and n.endswith(thermal)

    if any(abs(w) > _LOADING and not is_thermal(n) for n, w in direction.items()):
        return False
    direction = {n: w for n, w in direction.items() if is_thermal(n) and abs(w) > 1e-9}
    if not direction:
        return False
    try:
        base = {n: _value(spec, n) for n in direction}
        A0, _, _ = _thermal_matrices(spec, base)
        rates = np.abs(np.linalg.eigvals(A0))
        rates = rates[rates > 0]
        if not rates.size:
            return False
        omegas = np.concatenate([[0.0], np.geomspace(0.1 * rates.min(), 10 * rates.max(), 25)])
        h = 1e-5

        def response(step: float, w_map) -> np.ndarray:
            vals = {n: base[n] * np.exp(step * w_map.get(n, 0.0)) for n in base}
            A, B, Cy = _thermal_matrices(spec, vals)
            eye = np.eye(A.shape[0])
            return np.stack([Cy @ np.linalg.solve(1j * om * eye - A, B) for om in omegas])

        g0 = np.abs(response(0.0, {})).max()
        along = np.abs(response(h, direction) - response(-h, direction)).max() / (2 * h)
        single = max(np.abs(response(h, {n: 1.0}) - response(-h, {n: 1.0})).max() / (2 * h)
                     for n, w in direction.items() if abs(w) > _LOADING)
        return bool(along <= 1e-6 * max(single, 1e-300 * g0))
    except (np.linalg.LinAlgError, KeyError, ValueError, ZeroDivisionError):
        return False


def _value(spec: ModelSpec, name: str) -> float:
    from ..model._parameters_by_name import spec_parameters

    return float(spec_parameters(spec)[name].value)


def _cause(spec: ModelSpec, direction: dict[str, float], sample_period: float | None,
           null: bool) -> str:
    """`"structural"`, `"sampling"` or `"practical"` for one truncated direction."""
    if _structural(spec, direction):
        return "structural"
    members = [n for n, w in direction.items() if abs(w) > _LOADING]
    if _fast_unsensed(spec, members, sample_period):
        return "sampling"
    return "practical"


def _nodes_of(spec: ModelSpec, members) -> list[str]:
    nodes = []
    for n in members:
        parts = n.split(".")
        if parts[0] in ("nodes", "heat_inputs", "boundaries"):
            nodes.append(parts[1].split("-")[0])
        elif parts[0] == "links":
            nodes += parts[1].split("-")
    return [n for n in dict.fromkeys(nodes) if n in spec.node_names]


def _fast_unsensed(spec: ModelSpec, members, sample_period: float | None) -> dict[str, float]:
    if sample_period is None:
        return {}
    sensed = {s.node for s in spec.sensors}
    unsensed = [n for n in _nodes_of(spec, members) if n not in sensed]
    return {n: tau for n, tau in local_time_constants(spec).items()
            if n in unsensed and tau < 2 * sample_period}


def _to_fix(basis: np.ndarray, names: list[str]) -> list[str]:
    """`dimension` parameters whose fixing removes the whole subspace spanned by `basis`
    (params, dimension): the rows a pivoted QR picks (capacitances preferred)."""
    import scipy.linalg

    weight = np.array([1.5 if n.endswith(".capacitance") else 1.0 for n in names])
    _, _, piv = scipy.linalg.qr((basis * weight[:, None]).T, pivoting=True)
    return [names[i] for i in piv[:basis.shape[1]]]


def _explain_group(g: dict, basis: np.ndarray, names: list[str], spec: ModelSpec,
                   sample_period: float | None, scale: bool) -> tuple[str, str, list[str]]:
    """The message, cause and parameters to fix of one merged group of directions."""
    dim = len(g["directions"])
    causes = [d["cause"] for d in g["directions"]]
    cause = ("structural" if all(c == "structural" for c in causes)
             else "sampling" if "sampling" in causes else "practical")
    to_fix = _to_fix(basis, names)
    first = g["directions"][0]
    std = first["log_std"] if first["log_std"] is not None else float("inf")
    if dim == 1:
        named = {p: w for p, w in first["combination"].items() if p in g["parameters"]}
        msg = _explain(named, spec, std, sample_period, cause=cause, to_fix=to_fix)
    else:
        msg = _explain({p: 1.0 for p in g["parameters"]}, spec, std, sample_period,
                       subspace=dim, cause=cause, to_fix=to_fix, scale=scale)
    if scale and cause == "sampling":
        cause = "practical"   # a missing excitation, which faster data does not supply
    return msg, cause, to_fix


def _thermal_free(spec: ModelSpec) -> list[str]:
    out = [f"nodes.{n.name}.capacitance" for n in spec.nodes if not n.capacitance.fixed]
    out += [f"links.{k.key}.conductance" for k in spec.links if not k.conductance.fixed]
    out += [f"boundaries.{b.key}.conductance" for b in spec.boundaries if not b.conductance.fixed]
    return out


def _has_scale(basis: np.ndarray, names: list[str], spec: ModelSpec, powered: bool) -> bool:
    """Whether the common scale of every free C and G lies in the span of `basis` (only
    possible when the runs drive no heat input)."""
    free = _thermal_free(spec)
    if len(free) < 2 or powered:
        return False
    ones = np.array([1.0 if n in free else 0.0 for n in names])
    if ones.sum() < len(free):
        return False
    Q, _ = np.linalg.qr(basis)
    return bool(np.linalg.norm(ones - Q @ (Q.T @ ones)) < 0.05 * np.linalg.norm(ones))


def _explain(members: dict[str, float], spec: ModelSpec, std: float,
             sample_period: float | None = None, subspace: int = 1, cause: str = "practical",
             to_fix: list[str] | None = None, scale: bool = False) -> str:
    """One paragraph: which combination(s), why (`cause`), and what removes them all."""
    to_fix = list(to_fix or members)[:subspace]
    caps = [n for n in members if n.endswith(".capacitance")]
    conds = [n for n in members if n.endswith(".conductance")]
    if subspace > 1:
        combo = f"{subspace} independent combinations of {', '.join(members)}"
    else:
        combo = "the combination " + " ".join(
            f"{w:+.2f}·{'log(' + n + ')' if _is_positive(n) else n}" for n, w in members.items())
    how = f"relative std {std:.3g}" if np.isfinite(std) and std < 1e150 else "no information"
    thermal_free = _thermal_free(spec)
    same_sign = all(members.get(n, 0) > 0.5 for n in thermal_free) and len(thermal_free) > 1
    if subspace == 1 and same_sign and len(caps) + len(conds) == len(members):
        return (f"All capacitances and conductances scale together ({how}): with temperature "
                "inputs only and no measured power, multiplying every C and G by the same factor "
                "leaves every temperature unchanged. Fix one capacitance (from a part's mass and specific "
                "heat) or add a known heat input (a measured power).")
    fix = (f"Fix {'one' if subspace == 1 else subspace} of these parameters"
           f" ({' and '.join(to_fix)}, for example)" if subspace > 1 else
           "Fix one of these parameters")
    sensed = {s.node for s in spec.sensors}
    unsensed = sorted(n for n in _nodes_of(spec, members) if n not in sensed)
    text = f"The data cannot determine {combo} ({how})."
    if scale:
        text += (" One of them is the common scale of every C and G: with temperature inputs "
                 "only and no measured power, multiplying every C and G by the same factor "
                 "leaves every temperature unchanged. That one is a missing excitation, not "
                 "a sampling or sensor problem: the runs drive no heat input (their power "
                 "columns are all zero); add a known heat input (a heater step, or the "
                 "unit's own dissipation, measured) or fix one capacitance from design data.")
        if cause == "sampling":
            cause = "practical"   # the scale is no sampling matter; faster data won't fix it
    if cause == "structural":
        where = f" on node(s) {unsensed}" if unsensed else ""
        text += (" This is structural: the model's response from every input to every sensor "
                 "does not change along " + ("it" if subspace == 1 else "them") + ", so no "
                 "sensor of this kind can separate these parameters and more or faster data "
                 f"will not help. {fix} from design data (a part's mass and specific heat, a "
                 f"contact's conductance), or add a sensor{where} or a known heat input.")
    elif cause == "sampling":
        fast = _fast_unsensed(spec, members, sample_period)
        listing = ", ".join(f"{n} ~{tau:.2g} s" for n, tau in fast.items())
        text += (f" It involves node(s) {unsensed} that no sensor sees. Local time constant(s) "
                 f"{listing} are shorter than twice the sample period ({sample_period:g} s): "
                 f"these dynamics fall between samples; sample faster than "
                 f"{2 / min(fast.values()):.2g} Hz (two samples per time constant) to see "
                 f"them, or {fix[0].lower() + fix[1:]} "
                 "from design data.")
    else:
        if unsensed:
            text += (f" It involves node(s) {unsensed} that no sensor sees; their dynamics are "
                     "too weakly excited or too weakly coupled to show in the measured "
                     "temperatures.")
        text += (f" The runs excite these parameters too little to separate them. {fix} "
                 "from design data, or add excitation that moves them differently (ramps at "
                 "several rates, power steps, PRBS)"
                 + (", or put a sensor on one of these nodes." if unsensed else "."))
    return text
