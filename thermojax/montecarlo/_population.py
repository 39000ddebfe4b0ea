"""Unit populations: how the thermal parameters of manufactured units scatter about the
nominal model, and a deterministic sampler of units.

A varied parameter (by its dotted report name, `links.pcb-asic.conductance`) is

    θ_u = θ_0 · exp(σ z_u − σ²/2),   σ² = log(1 + s²)

with `s` the *spread*: one standard deviation of the relative variation `θ/θ_0`
(lognormal, so a positive parameter stays positive, and `E[θ] = θ_0`). The `z_u` of the
varied parameters are standard normal with a correlation matrix `R` (identity unless
correlated groups are given: a group of correlation ρ is one shared factor, so every
pair in it has correlation ρ). Die-attach voids are a conductance loss on named links:
with probability `probability` a unit has voids on that link and loses a fraction
uniform in `[0, max_loss]` of its conductance.

Unit `u` of a study with seed `seed` draws its numbers from NumPy's generator seeded by
`(seed, u)`, so a unit's parameters depend on the seed and its index only, never on
chunking, process or device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .._errors import InputError

#: A sourcing table (unit-to-unit variance per sourcing modality),
#: as relative spreads (one standard deviation; the table's "+/- x percent" read as
#: one sigma). Every preset perturbs every `nodes.*.capacitance` (package, gel and
#: potting masses) and every `links.*.conductance` (die attach, bond line, potting,
#: grease gaps) of the model independently with that spread. Boundary conductances
#: (the chamber fixture, the same for every unit), heat-input gains and sensor noises
#: are not perturbed.
PRESETS: dict[str, dict] = {
    "asic_integrated": {
        "spread": 0.05, "title": "fully package-integrated ASIC sensor",
        "source": "internal gel mass and bond line thickness, +/- 5 percent; "
                  "usual mitigation: batch-level default matrix loading"},
    "oem_module": {
        "spread": 0.12, "title": "high-volume OEM module",
        "source": "diaphragm stiffening under pre-stress, +/- 12 percent; usual "
                  "mitigation: automated runtime parameter gain scheduling"},
    "bare_die_custom": {
        "spread": 0.18, "title": "bare MEMS die with custom packaging",
        "source": "potting compound viscosity and fill volume, +/- 18 percent; usual "
                  "mitigation: single-point dynamic end-of-line calibration"},
    "thermistor_custom_housing": {
        "spread": 0.32, "title": "discrete thermistor in a custom housing",
        "source": "thermal grease cavity air gaps, +/- 32 percent; usual mitigation: "
                  "two-point dynamic frequency sweep end-of-line test"},
}

PRESET_CLASSES = ("nodes.*.capacitance", "links.*.conductance")


@dataclass(frozen=True)
class Voids:
    """Die-attach voids on one link: with `probability` a unit loses a fraction uniform
    in `[0, max_loss]` of the link's conductance."""

    link: str  # dotted name, links.<a>-<b>.conductance
    probability: float
    max_loss: float


@dataclass(frozen=True)
class Population:
    """How units scatter: `spreads` (dotted name -> relative std), `correlation` (over
    the names in `spreads`' order), `voids`, and where it came from (`preset`)."""

    spreads: dict[str, float]
    correlation: np.ndarray = field(repr=False)
    voids: tuple[Voids, ...] = ()
    preset: str | None = None

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.spreads)

    def describe(self) -> dict:
        return {"preset": self.preset,
                "preset_source": PRESETS[self.preset]["source"] if self.preset else None,
                "distribution": "lognormal, mean = nominal, spread = relative std",
                "spreads": dict(self.spreads),
                "correlated_pairs": [[a, b, float(self.correlation[i, j])]
                                     for i, a in enumerate(self.names)
                                     for j, b in enumerate(self.names)
                                     if j > i and self.correlation[i, j] != 0.0],
                "voids": [v.__dict__ for v in self.voids]}


@dataclass(frozen=True)
class UnitParameters:
    """Sampled units: `values[u, j]` is parameter `names[j]` of unit `indices[u]` (SI);
    `log_deviation[u, j] = log(values / nominal)` (voids included)."""

    names: tuple[str, ...]
    indices: np.ndarray
    values: np.ndarray
    log_deviation: np.ndarray


def _number(value, where: str, file: str | None) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(
            value):
        raise InputError(f"expected a finite number, got {value!r}.", file=file, field=where)
    return float(value)


def _spread(value, where: str, file: str | None) -> float:
    s = _number(value, where, file)
    if s < 0:
        raise InputError(f"a spread is one standard deviation of the relative variation and "
                         f"cannot be negative, got {s}.", file=file, field=where)
    return s


def population_from_config(spec, table: dict, file: str | None = None,
                           prefix: str = "population") -> Population:
    """A `Population` from a config's `[population]` table (docs/cli.md).

    Keys: `preset` (a name of `PRESETS`), `spreads` (dotted name -> spread; overrides
    the preset), `[[groups]]` with `parameters` and `correlation`, or `correlation_matrix`
    over `spreads`' names, `[[voids]]` with `link` ("a-b"), `probability`, `max_loss`.
    Bad input raises `InputError` naming the field.
    """
    from ..model import spec_parameters

    known = spec_parameters(spec)
    if not isinstance(table, dict):
        raise InputError("expected a table.", file=file, field=prefix)
    unknown = set(table) - {"preset", "spreads", "groups", "correlation_matrix", "voids"}
    if unknown:
        raise InputError(f"unknown key(s) {sorted(unknown)}; expected preset, spreads, groups, "
                         "correlation_matrix, voids.", file=file, field=prefix)
    spreads: dict[str, float] = {}
    preset = table.get("preset")
    if preset is not None:
        if preset not in PRESETS:
            raise InputError(f"unknown preset {preset!r}; the presets are "
                             f"{', '.join(PRESETS)}.", file=file, field=f"{prefix}.preset")
        s = PRESETS[preset]["spread"]
        for name in known:
            if (name.startswith("nodes.") and name.endswith(".capacitance")) or (
                    name.startswith("links.") and name.endswith(".conductance")):
                spreads[name] = s
    for name, value in (table.get("spreads") or {}).items():
        where = f"{prefix}.spreads.{name}"
        if name not in known:
            raise InputError(f"the model has no parameter {name!r}; its parameters are "
                             f"{', '.join(known)}.", file=file, field=where)
        if known[name].value <= 0:
            raise InputError("only positive parameters can vary lognormally.", file=file,
                             field=where)
        spreads[name] = _spread(value, where, file)
    spreads = {k: v for k, v in spreads.items() if v > 0}
    names = list(spreads)
    R = np.eye(len(names))
    for g, group in enumerate(table.get("groups") or []):
        where = f"{prefix}.groups[{g}]"
        params = group.get("parameters", [])
        rho = _number(group.get("correlation"), f"{where}.correlation", file)
        if not -1.0 < rho < 1.0:
            raise InputError(f"a correlation lies strictly between -1 and 1, got {rho}.",
                             file=file, field=f"{where}.correlation")
        for p in params:
            if p not in spreads:
                raise InputError(f"{p!r} is not a varied parameter (give it a spread first); "
                                 f"varied: {', '.join(names)}.", file=file,
                                 field=f"{where}.parameters")
        idx = [names.index(p) for p in params]
        for i in idx:
            for j in idx:
                if i != j:
                    R[i, j] = rho
    if "correlation_matrix" in table:
        M = np.asarray(table["correlation_matrix"], dtype=float)
        if M.shape != R.shape or not np.allclose(M, M.T) or not np.allclose(np.diag(M), 1.0):
            raise InputError(f"expected a symmetric {len(names)}x{len(names)} matrix with a unit "
                             f"diagonal, over the varied parameters in this order: "
                             f"{', '.join(names)}.", file=file,
                             field=f"{prefix}.correlation_matrix")
        R = M
    if names and np.linalg.eigvalsh(R).min() <= 0:
        raise InputError("the correlations are not a valid (positive definite) correlation "
                         "matrix; lower them or split the groups.", file=file,
                         field=f"{prefix}.groups")
    voids = []
    for v, entry in enumerate(table.get("voids") or []):
        where = f"{prefix}.voids[{v}]"
        link = f"links.{entry.get('link')}.conductance"
        if link not in known:
            raise InputError(f"the model has no link {entry.get('link')!r}; links are "
                             + ", ".join(n[6:-12] for n in known if n.startswith("links."))
                             + ".", file=file, field=f"{where}.link")
        p = _number(entry.get("probability"), f"{where}.probability", file)
        loss = _number(entry.get("max_loss"), f"{where}.max_loss", file)
        if not 0 <= p <= 1:
            raise InputError(f"a probability lies in [0, 1], got {p}.", file=file,
                             field=f"{where}.probability")
        if not 0 <= loss < 1:
            raise InputError(f"a conductance loss is a fraction in [0, 1), got {loss}.",
                             file=file, field=f"{where}.max_loss")
        voids.append(Voids(link, p, loss))
    return Population(spreads, R, tuple(voids), preset)


def preset_population(spec, preset: str) -> Population:
    """The population of a named preset (`PRESETS`) for `spec`."""
    return population_from_config(spec, {"preset": preset}, prefix="preset")


def varied_names(population: Population) -> tuple[str, ...]:
    """Every parameter a unit may differ in: the varied ones, then void links not in them."""
    extra = tuple(v.link for v in population.voids if v.link not in population.spreads)
    return population.names + tuple(dict.fromkeys(extra))


def sample_units(spec, population: Population, indices, seed: int = 0) -> UnitParameters:
    """The parameters of units `indices` (an int n means units 0..n-1).

    Deterministic by `(seed, unit index)`: unit `u`'s numbers come from
    `numpy.random.default_rng([seed, u])` (its correlated normals first, then two
    uniforms per void entry), whatever else is sampled with it.
    """
    from ..model import spec_parameters

    if isinstance(indices, (int, np.integer)):
        indices = np.arange(int(indices))
    indices = np.asarray(indices, dtype=np.int64)
    if int(seed) < 0:
        raise InputError(f"`seed` must be a whole number, 0 or more, got {seed}.", field="seed")
    known = spec_parameters(spec)
    names = varied_names(population)
    nominal = np.array([known[n].value for n in names], dtype=float)
    k = len(population.names)
    s = np.array([population.spreads[n] for n in population.names])
    sigma = np.sqrt(np.log1p(s ** 2))
    chol = np.linalg.cholesky(population.correlation) if k else np.zeros((0, 0))
    logdev = np.zeros((len(indices), len(names)))
    for row, u in enumerate(indices):
        rng = np.random.default_rng([int(seed), int(u)])
        z = chol @ rng.standard_normal(k) if k else np.zeros(0)
        logdev[row, :k] = sigma * z - 0.5 * sigma ** 2
        for v in population.voids:
            hit, frac = rng.random(2)
            if hit < v.probability:
                logdev[row, names.index(v.link)] += math.log1p(-frac * v.max_loss)
    return UnitParameters(names, indices, nominal[None, :] * np.exp(logdev), logdev)


def log_prior(population: Population) -> tuple[np.ndarray, np.ndarray]:
    """Mean (k,) and covariance (k, k) of the log-deviations `log(θ/θ₀)` of
    `varied_names(population)`: `−σ²/2` and `diag(σ) R diag(σ)` from the spreads, plus
    each void entry's mean and variance of `log(1 − f·max_loss)` (with probability
    `probability`, `f` uniform; midpoint rule over 2000 points) on its link. The
    per-unit fit's Gaussian prior."""
    names = varied_names(population)
    k = len(population.names)
    s = np.array([population.spreads[n] for n in population.names])
    sigma = np.sqrt(np.log1p(s ** 2))
    mean = np.zeros(len(names))
    cov = np.zeros((len(names), len(names)))
    mean[:k] = -0.5 * sigma ** 2
    cov[:k, :k] = sigma[:, None] * population.correlation * sigma[None, :]
    f = (np.arange(2000) + 0.5) / 2000
    for v in population.voids:
        j = names.index(v.link)
        loss = np.log1p(-f * v.max_loss)
        m1, m2 = v.probability * loss.mean(), v.probability * (loss ** 2).mean()
        mean[j] += m1
        cov[j, j] += m2 - m1 ** 2
    # a void entry that never happens leaves a zero variance: keep the matrix invertible
    cov[np.diag_indices_from(cov)] = np.maximum(np.diag(cov), 1e-12)
    return mean, cov
