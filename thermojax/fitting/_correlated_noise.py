"""Parameter stds of an output-error fit when its residuals are correlated in time.

The fit's stds come from the Gauss-Newton information `JᵀJ` of residuals weighted by
each column's noise std, which assumes every sample's noise independent. Low-passed,
decimated data (the calibration pipeline's conditioning) or a model that misses fast
content between samples leave residuals correlated from sample to sample, and those
stds are then too small. The Newey-West estimator (heteroskedasticity and
autocorrelation consistent, HAC) keeps the fit and corrects the stds: with the
per-sample score `s_k = Σ_c J_kcᵀ r_kc` (summed over the columns, so correlation
between columns counts too),

    Cov = F⁻¹ M F⁻¹,   M = Γ_0 + Σ_{l=1..L} (1 − l/(L+1)) (Γ_l + Γ_lᵀ),
    Γ_l = Σ_runs Σ_k s_k s_{k−l}ᵀ,

`F⁻¹` the fit's covariance (its pseudo-inverse on the identifiable subspace). White
residuals give `M ≈ F` and the fit's own stds back. Newey & West (1987), Econometrica
55, 703; the default `L = ⌊4 (T/100)^(2/9)⌋` is their 1994 rule of thumb (T samples per
run).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._residual_analysis import newey_west_lags, pooled_autocorrelation


def hac_covariance(scores: np.ndarray, bread: np.ndarray, lags: int) -> np.ndarray:
    """`bread @ M @ bread`, the Newey-West covariance.

    - `scores`: `(runs, times, params)` each sample's score contribution `Jᵀr` (zero
      where a sample is missing); lags never cross from one run into the next.
    - `bread`: `(params, params)` the inverse information.
    - `lags`: `L ≥ 0`, the Bartlett-weighted lags kept (0: White's estimator).
    """
    s = np.asarray(scores, dtype=float)
    M = np.einsum("rta,rtb->ab", s, s)
    for lag in range(1, min(int(lags), s.shape[1] - 1) + 1):
        G = np.einsum("rta,rtb->ab", s[:, lag:], s[:, :-lag])
        M += (1.0 - lag / (lags + 1.0)) * (G + G.T)
    return bread @ M @ bread


@dataclass(frozen=True)
class CorrelatedNoiseStds:
    """A fit's parameter stds under correlated residuals.

    - `stds`: parameter name -> HAC std in the parameter's units (None where the fit
      reports none).
    - `ratio`: parameter name -> HAC std / the fit's std.
    - `lags`: the truncation lag `L` used.
    - `autocorrelation`: column -> lag-1 autocorrelation of its weighted residuals
      (pooled over runs; about 0 for white residuals).
    """

    stds: dict[str, float | None]
    ratio: dict[str, float]
    lags: int
    autocorrelation: dict[str, float]


def correlated_noise_stds(result, lags: int | None = None) -> CorrelatedNoiseStds:
    """The Newey-West stds of the free parameters of an output-error `FitResult`
    (`thermojax.fit`), at its fitted values.

    Each reported std is the fit's times `sqrt(Cov_HAC_jj / Cov_jj)` (both in the fit's
    own coordinates, log for positive parameters, so the ratio carries over to the
    physical units unchanged). The noise stds and bias coefficients (solved by variable
    projection) are not among the free parameters and are not corrected here.

    **Arguments:** `result` (output error, at least one free parameter); `lags` (default
    `newey_west_lags` of the longest run).
    """
    from ._output_error import weighted_residuals_and_jacobian

    if result.likelihood != "output_error":
        raise ValueError("correlated_noise_stds corrects output-error fits; a Kalman fit's "
                         "innovations are already whitened by the filter (check their "
                         "whiteness instead).")
    if result.theta is None or len(result.theta) == 0:
        raise ValueError("the fit has no free parameters to correct.")
    r, J, _ = weighted_residuals_and_jacobian(result.theta, result.problem)
    n_times = int(max(np.asarray(result.problem.data.lengths)))
    L = newey_west_lags(n_times) if lags is None else int(lags)
    if L < 0:
        raise ValueError(f"lags must be >= 0, got {L}.")
    bread = np.asarray(result.identifiability.covariance)
    cov = hac_covariance(np.einsum("rtca,rtc->rta", J, r), bread, L)
    white = np.diag(bread)
    ratio = np.sqrt(np.clip(np.diag(cov), 0, None) / np.where(white > 0, white, np.nan))
    stds, ratios = {}, {}
    for name, q in zip(result.free_names, ratio):
        entry = result.parameters.get(name)
        if entry is None:
            continue
        ratios[name] = float(q)
        ok = entry["std"] is not None and np.isfinite(q)
        stds[name] = float(entry["std"] * q) if ok else None
    columns = list(result.spec.sensor_columns) + [b.column for b in result.spec.biases]
    r = np.where(_observed(result.problem, r.shape[1]), r, np.nan)
    lengths = np.asarray(result.problem.data.lengths)
    rho = {c: float(pooled_autocorrelation([r[i, :n, j] for i, n in enumerate(lengths)], 1)[0][0])
           for j, c in enumerate(columns)}
    return CorrelatedNoiseStds(stds, ratios, L, rho)


def _observed(problem, n_times: int) -> np.ndarray:
    """(runs, times, sensors + bias columns) True where a sample was measured."""
    mask = np.asarray(problem.data.mask)[:, :n_times]
    if problem.bias is not None:
        b = np.asarray(problem.bias.mask)
        mask = np.concatenate([mask, b.reshape(b.shape[0], -1, b.shape[-1])[:, :n_times]], 2)
    return mask
