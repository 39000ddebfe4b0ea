"""A Monte Carlo study's results summarized for its report: per method the percentiles of
every metric and the fraction of units within the bias specification, the sensitivity
ranking of the varied parameters, and the per-unit fit's parameter errors."""

from __future__ import annotations

import numpy as np

from ._study import METHODS, METRICS


PERCENTILES = (50, 90, 95, 99)


def summarize(results: dict[str, np.ndarray], names, logdev: np.ndarray, spec_limit: float,
              bias_units: str) -> dict:
    """Percentiles, fraction within the bias specification, sensitivity ranking, and the
    per-unit fit's parameter errors (for the methods present in `results`)."""
    methods = {m: label for m, label in METHODS.items() if f"{m}_bias_peak" in results}
    out = {"n_units": int(len(results["unit"])), "bias_limit": spec_limit,
           "bias_units": bias_units, "methods": methods, "percentiles": {},
           "fraction_within_bias_spec": {}}
    for m in methods:
        out["percentiles"][m] = {
            k: {**{f"p{p}": float(np.percentile(results[f"{m}_{k}"], p)) for p in PERCENTILES},
                "max": float(np.max(results[f"{m}_{k}"])),
                "mean": float(np.mean(results[f"{m}_{k}"]))} for k in METRICS}
        out["fraction_within_bias_spec"][m] = float(np.mean(results[f"{m}_bias_peak"]
                                                            <= spec_limit))
    out["sensitivity"] = sensitivity(results["nominal_bias_peak"], names, logdev)
    if "fitted_log_deviation" in results:
        err = results["fitted_log_deviation"] - logdev
        z = err / results["fitted_log_std"]
        out["fit"] = {
            "fit_rms_median": float(np.median(results["fit_rms"])),
            "parameters": [{"parameter": n, "prior_std": float(np.std(logdev[:, j])),
                            "error_rms": float(np.sqrt(np.mean(err[:, j] ** 2))),
                            "posterior_std_median": float(np.median(
                                results["fitted_log_std"][:, j])),
                            "z_rms": float(np.sqrt(np.mean(z[:, j] ** 2)))}
                           for j, n in enumerate(names)]}
    return out


def sensitivity(error: np.ndarray, names, logdev: np.ndarray) -> list[dict]:
    """Rank the varied parameters by how much of the error's spread each explains:
    standardized least-squares coefficients of `error` on the log-deviations (per
    standard deviation of the parameter, in the error's units), with each one's
    correlation; ranked by |coefficient|."""
    if logdev.shape[1] == 0 or len(error) < 3:
        return []
    X = logdev - logdev.mean(axis=0)
    sd = X.std(axis=0)
    keep = sd > 0
    Z = X[:, keep] / sd[keep]
    e = error - error.mean()
    coef, *_ = np.linalg.lstsq(Z, e, rcond=None)
    rows = []
    kept = [n for n, k in zip(names, keep) if k]
    for j, name in enumerate(kept):
        denom = np.std(Z[:, j]) * np.std(e)
        r = float(np.mean(Z[:, j] * e) / denom) if denom > 0 else 0.0
        rows.append({"parameter": name, "coefficient_per_sd": float(coef[j]),
                     "correlation": r})
    rows.sort(key=lambda r: -abs(r["coefficient_per_sd"]))
    return rows
