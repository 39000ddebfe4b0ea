"""One model of the missing-physics loop (`_investigate`): fitted to the runs with its
bias channels and measured (`evaluate`: the figures of docs/formats.md §5 and the
plots' traces), and confirmed at its optimum from several starts before it is scored
(`confirmed_optimum`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..fitting._fit import FitResult, fit, standardized_innovations
from ..fitting._residual_analysis import ljung_box, long_run_variance_ratio
from ..measurements._data import Experiment
from ..measurements._telemetry import Telemetry
from ..model._spec import ModelSpec


N_STARTS = 3  # output-error starts confirming each step's optimum before it is scored
MULTISTART_TOL = 1e-3  # −log L a perturbed start must gain to replace the fit


@dataclass
class Step:
    """One fitted model of the loop and its evidence."""

    spec: ModelSpec
    result: FitResult
    biases: dict  # column -> BiasFit
    record: dict  # the step's report.json entry
    traces: list[dict] = field(repr=False, default_factory=list)
    lrv: dict = field(default_factory=dict)  # column -> long-run variance ratio of residuals
    starts: int = 1  # how many fits from distinct starts `result` is the best of
    fit_seconds: float = 0.0  # wall time of the fit that made it, s (a refit's: `_refits`)
    # `(likelihood, Future)` of `scoring_inputs`, computed ahead (`score_ahead`)
    scoring: tuple | None = field(default=None, repr=False)

    def deflation(self, white_p: float) -> float:
        """The long-run variance ratio that deflates statistics: the largest over the
        columns whose residuals are not white at `white_p` (1 when all are white)."""
        bad = [c for c, p in self.record["whiteness_p"].items()
               if p is None or not p > white_p]
        return float(max([self.lrv.get(c, 1.0) for c in bad], default=1.0))

    @property
    def thermal_nll(self) -> float:
        """−log L of the thermal model alone: a Kalman fit's record adds its bias
        channels' (`fitting._summary`)."""
        kalman = self.result.likelihood == "kalman"
        return self.record["nll"] - (sum(b.nll for b in self.biases.values()) if kalman
                                     else 0.0)


def _experiments(spec: ModelSpec, runs: list[Telemetry]) -> list[Experiment]:
    return [Experiment.from_telemetry(spec, t, name=t.path or f"run{i}")
            for i, t in enumerate(runs)]


def _bias_runs(result, runs, bias):
    """`(runs, node rates)` for `fitting._bias` on the fitted model's free-run node
    temperatures: per run `(ts, node temperatures, bias column)` and the exact `dT/dt`."""
    from ..fitting._bias_residuals import node_temperatures

    x, xdot = (np.asarray(a) for a in node_temperatures(
        result.model, result.problem.data, result.state.run_initial))
    return ([(np.asarray(t.ts), x[r, :len(t.ts)], t.column(bias.column))
             for r, t in enumerate(runs)], [xdot[r, :len(t.ts)] for r, t in enumerate(runs)])


def evaluate(spec: ModelSpec, runs: list[Telemetry], likelihood: str, progress=None,
             holdout: int | None = None, n_starts: int = 1,
             nested_nll: float | None = None, polish: bool = True,
             restart_unconverged: bool = True) -> Step:
    """Fit `spec` to the runs, its bias channels with it (docs/formats.md §4), and measure
    the fit (docs/formats.md §5 keys). `n_starts` > 1 adds perturbed output-error starts;
    `nested_nll`: −log L of the model `spec` extends; `polish` and `restart_unconverged`
    as `fit`'s."""
    # Plateau restarts (`fitting._plateau`) stay with `fit`: here a candidate's node
    # beyond the data is evidence against it, and each step's fit is compared as it is.
    result = fit(spec, _experiments(spec, runs), likelihood=likelihood, progress=progress,
                 holdout=holdout, n_starts=n_starts, restart_plateaus=False,
                 nested_nll=nested_nll, polish=polish,
                 restart_unconverged=restart_unconverged)
    biases = result.biases
    spec_out = result.spec
    nll, n_params, n = result.nll, result.n_params, result.n_samples
    rmse = dict(result.rmse)
    # whiteness: free-run residuals (output error) or standardized innovations (Kalman)
    cols = list(spec.sensor_columns)
    if likelihood == "kalman":
        seq = standardized_innovations(result)
    else:
        exps = _experiments(spec, runs)
        seq = [e.outputs - p for e, p in zip(exps, result.predictions)]
    tests = {c: ljung_box([s[:, j] for s in seq]) for j, c in enumerate(cols)}
    tests.update({c: ljung_box(f.residuals) for c, f in biases.items()})
    white = {c: p for c, (_, p, _) in tests.items()}
    lags = {c: lag for c, (_, _, lag) in tests.items()}
    params = dict(result.parameters)
    record = {
        "added": None, "n_params": int(n_params), "rmse": rmse,
        "nll": float(nll), "aic": float(2 * n_params + 2 * nll),
        "bic": float(n_params * math.log(n) + 2 * nll),
        "whiteness_p": white, "whiteness_lags": lags, "candidates": [],
        "fit_percent": dict(result.fit_percent), "n_samples": int(n),
        "parameters": params, "converged": bool(result.converged),
    }
    if not (np.isfinite(record["nll"]) and np.isfinite(record["bic"])):
        raise FloatingPointError(f"the fit's −log L is not finite ({record['nll']})")
    # Deflation for autocorrelated residuals (`Step.deflation`): free-run residuals only.
    # The Kalman likelihood's innovations are whitened by the model itself, and its
    # likelihood-ratio test is used as the field uses it (Bacher & Madsen; CTSM-R): on
    # PRBS1 a deflation of 4 (the innovations of an incomplete model) hid the solar gain
    # on the envelope (LR 34) that the paper's selection keeps.
    lrv = {c: 1.0 if likelihood == "kalman" else
           long_run_variance_ratio([s[:, j] for s in seq]) for j, c in enumerate(cols)}
    lrv.update({c: long_run_variance_ratio(f.residuals) for c, f in biases.items()})
    step = Step(spec_out, result, biases, record, lrv=lrv)
    step.traces = _traces(spec, runs, result, biases)
    return step


def _traces(spec, runs, result, biases) -> list[dict]:
    """Measured and modelled columns per run, for plots (`_diagnostics.RunTrace`)."""
    out = []
    cols = list(spec.sensor_columns)
    inputs = list(spec.input_columns)
    for r, t in enumerate(runs):
        meas = [t.column(c) for c in cols] + [t.column(c) for c in biases]
        pred = [result.predictions[r][:, j] for j in range(len(cols))] + \
               [biases[c].predictions[r] for c in biases]
        out.append({"name": t.path or f"run{r}", "ts": np.asarray(t.ts),
                    "measured": np.stack(meas, 1), "predicted": np.stack(pred, 1),
                    "inputs": np.stack([t.column(c) for c in inputs], 1) if inputs
                    else np.zeros((len(t.ts), 0))})
    return out


def confirmed_optimum(step: Step, runs, likelihood, say) -> Step:
    """`step`, or a better fit of its model from `N_STARTS` output-error starts (the first
    at its fitted values, the others perturbed): a step is scored only from a fit that
    is not a local optimum. The gain goes into the record (`multistart_gain`, −log L).

    A step whose fit is already the best of `N_STARTS - 1` or more starts (the refit of
    the candidate it added: from the fitted values with the effect, the user's values,
    the score's time constant) has had its check: on PRBS1 the check of such a step
    never gained (at most 6e-6 at steps 1-3, under `MULTISTART_TOL`) and cost 8 s of
    the loop, 6 s at its first nonlinear model (an output-error program of its own)."""
    if step.starts >= N_STARTS - 1:
        return step
    try:
        again = evaluate(step.spec, runs, likelihood, n_starts=N_STARTS)
    except Exception as err:  # the step's own fit stands
        say(f"multi-start check failed: {type(err).__name__}: {err}")
        return step
    gain = step.record["nll"] - again.record["nll"]
    if gain > MULTISTART_TOL:
        say(f"multi-start: a better optimum, −log L lower by {gain:.3f}")
        again.record.update({k: step.record[k] for k in ("added", "hold_changes")
                             if k in step.record})
        step = again
    step.record["multistart_gain"] = float(max(gain, 0.0))
    return step
