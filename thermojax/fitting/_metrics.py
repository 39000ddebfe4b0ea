"""Goodness of fit, as docs/formats.md §2 and MATLAB's `compare` define it."""

from __future__ import annotations

import numpy as np


def rmse(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Root mean square of `y - y_hat` over the finite entries of `y` (same units)."""
    ok = np.isfinite(y)
    return float(np.sqrt(np.mean((y[ok] - y_hat[ok]) ** 2))) if ok.any() else float("nan")


def fit_percent(y: np.ndarray, y_hat: np.ndarray) -> float:
    """`100 (1 - ‖y - ŷ‖ / ‖y - mean(y)‖)` over the finite entries of `y` (100 is perfect)."""
    ok = np.isfinite(y)
    if not ok.any():
        return float("nan")
    y, y_hat = y[ok], y_hat[ok]
    denom = np.linalg.norm(y - y.mean())
    return float(100.0 * (1.0 - np.linalg.norm(y - y_hat) / denom)) if denom > 0 else float("nan")


def fit_metrics(columns, experiments, predictions) -> dict:
    """Per-column RMSE and fit % pooled over runs, and the same per run.

    `experiments[r].outputs` (times, columns) with NaN for missing samples;
    `predictions[r]` the model's free-run outputs of the same shape.
    """
    pooled_y = np.concatenate([e.outputs for e in experiments], axis=0)
    pooled_p = np.concatenate(list(predictions), axis=0)
    out = {"rmse": {}, "fit_percent": {}, "per_run": []}
    for j, c in enumerate(columns):
        out["rmse"][c] = rmse(pooled_y[:, j], pooled_p[:, j])
        out["fit_percent"][c] = fit_percent(pooled_y[:, j], pooled_p[:, j])
    for e, p in zip(experiments, predictions):
        out["per_run"].append({
            "run": e.name,
            "rmse": {c: rmse(e.outputs[:, j], p[:, j]) for j, c in enumerate(columns)},
            "fit_percent": {c: fit_percent(e.outputs[:, j], p[:, j])
                            for j, c in enumerate(columns)},
        })
    return out
