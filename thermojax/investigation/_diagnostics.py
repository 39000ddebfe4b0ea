"""How a model fails: numbers and plain-English findings from its run traces (the
plots of the same traces are in `_diagnostic_plots`).

Pure NumPy/SciPy (no JAX). A run trace is a plain dict

    {"name": str, "ts": (T,) s, "measured": (T, p) with NaN for missing,
     "predicted": (T, p), "inputs": (T, m)}

holding the model's free-run (or one-step) prediction next to the measurement. The
statistics come from `_residual_analysis` (runs pooled by summing per-run lagged
products, each run about its own mean, so a lag never straddles two runs) and the
fit figures from `fitting._metrics`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy import stats

from .._json import json_safe
from ..fitting._metrics import fit_percent, rmse
from ..fitting._residual_analysis import (PHASES, PhaseLabels, cross_correlation, cumulated_periodogram,
                                 label_phases, ljung_box, pooled_autocorrelation,
                                 residuals_by_phase)

RunTrace = dict

WHITE_P = 0.05  # Ljung-Box p at or above which a column's residual is called white
_MIN_SAMPLES = 10  # fewer finite residual samples than this: no test is attempted
_PHASE_SE = 3.0  # a phase difference is reported beyond this many standard errors ...
_PHASE_REL = 0.05  # ... and beyond this fraction of the column's RMSE
_MAX_CORR_FINDINGS = 3  # per column, strongest first


# ---------------------------------------------------------------------------
# Inputs


def _check_runs(columns, runs, input_names) -> list[dict]:
    """The traces as float arrays of consistent shapes (measured/predicted (T, p),
    inputs (T, m)); a `ValueError` naming the run and field otherwise."""
    p, m = len(columns), len(input_names)
    if not runs:
        raise ValueError("`diagnose_traces(runs=...)` got no run; pass at least one run trace.")
    out = []
    for i, run in enumerate(runs):
        name = str(run.get("name", f"run {i}"))
        try:
            ts = np.asarray(run["ts"], float).reshape(-1)
            arrays = {}
            for key, width in (("measured", p), ("predicted", p), ("inputs", m)):
                a = np.asarray(run[key], float)
                if a.ndim == 1 and width == 1:
                    a = a[:, None]
                if a.ndim == 1 and width == 0 and a.size == 0:
                    a = np.zeros((len(ts), 0))
                arrays[key] = a
        except KeyError as e:
            raise ValueError(f"`diagnose_traces(runs=...)`: run {i} ({name!r}) has no {e.args[0]!r}; "
                             "a run trace holds 'ts', 'measured', 'predicted' and 'inputs'.") from None
        for key, width in (("measured", p), ("predicted", p), ("inputs", m)):
            if arrays[key].shape != (len(ts), width):
                raise ValueError(f"`diagnose_traces(runs=...)`: run {i} ({name!r}) field {key!r} has "
                                 f"shape {arrays[key].shape}, expected {(len(ts), width)} "
                                 f"({len(ts)} times by {width} "
                                 f"{'columns' if key != 'inputs' else 'inputs'}).")
        out.append({"name": name, "ts": ts, **arrays})
    return out


def _split_inputs(input_names, boundary_inputs) -> tuple[str | None, list[str]]:
    """The chamber temperature (first boundary input) and the power inputs (the
    rest). Without boundary inputs named: the first input whose name does not start
    with "P" is the chamber, those starting with "P" are powers (the `_plots` rule)."""
    names = list(input_names)
    bset = [b for b in boundary_inputs if b in names]
    if bset:
        return bset[0], [n for n in names if n not in set(boundary_inputs)]
    temps = [n for n in names if not n.startswith("P")]
    return (temps[0] if temps else None), [n for n in names if n.startswith("P")]


def _phases(run: dict, input_names, chamber: str | None, powers: list[str]) -> PhaseLabels:
    """`label_phases` on the chamber temperature and the first power input; a jump in any
    other power input marks the following window a power step as well."""
    idx = {n: k for k, n in enumerate(input_names)}
    temp = run["inputs"][:, idx[chamber]] if chamber is not None else None
    first = run["inputs"][:, idx[powers[0]]] if powers else None
    labels = label_phases(run["ts"], temp, first).labels.copy()
    dwell, step = PHASES.index("dwell"), PHASES.index("power_step")
    for name in powers[1:]:
        extra = label_phases(run["ts"], None, run["inputs"][:, idx[name]]).labels
        labels[(extra == step) & (labels == dwell)] = step
    return PhaseLabels(labels)


def _dt(runs) -> float:
    """Median sample interval over all runs, s (NaN when no run has two samples)."""
    d = np.concatenate([np.diff(r["ts"]) for r in runs])
    return float(np.median(d)) if d.size else float("nan")


def _signals(run: dict, input_names) -> list[tuple[str, bool, np.ndarray]]:
    """Every input and its time derivative (central differences), as (name, derivative?, values)."""
    out = []
    for k, n in enumerate(input_names):
        u = run["inputs"][:, k]
        out.append((n, False, u))
        du = np.gradient(u, run["ts"]) if len(u) > 1 else np.zeros_like(u)
        out.append((n, True, du))
    return out


def _label(name: str, derivative: bool) -> str:
    return f"d({name})/dt" if derivative else name


def _n_eff(res: list[np.ndarray]) -> float:
    """Effective sample fraction under an AR(1) approximation, (1 - ρ₁)/(1 + ρ₁)."""
    rho, n = pooled_autocorrelation(res, 1)
    r1 = float(np.clip(rho[0], -0.99, 0.99)) if n > 1 else 0.0
    return (1.0 - r1) / (1.0 + r1)


def _phase_diff(res, phases, a: str, b: str, frac: float):
    """Mean residual on phase `a` minus on phase `b`, and its standard error with the
    sample counts shrunk to effective ones (`frac` from `_n_eff`)."""
    def pick(kind):
        v = np.concatenate([np.asarray(r, float)[ph.mask(kind)] for r, ph in zip(res, phases)])
        return v[np.isfinite(v)]
    va, vb = pick(a), pick(b)
    if va.size < _MIN_SAMPLES or vb.size < _MIN_SAMPLES:
        return None, None
    se = math.sqrt(va.var(ddof=1) / max(va.size * frac, 1.0) + vb.var(ddof=1) / max(vb.size * frac, 1.0))
    return float(va.mean() - vb.mean()), se


def _seconds(x: float) -> str:
    """A lag in s for a sentence: whole seconds from 10 s up (no exponent)."""
    return f"{x:.0f}" if abs(x) >= 10 else f"{x:.3g}"


def _p(p: float) -> str:
    return "< 1e-300" if p < 1e-300 else f"= {p:.2g}"


MAX_LAG_SAMPLES = 2000  # the most lags either side (each lag costs a pass over the data)
_LAGS_PER_TIME_SCALE = 2.0  # the lag span covers this many slowest time constants


def lag_span(dt: float, shortest: int, time_scale: float | None = None,
             max_lag: int | None = None) -> int:
    """The auto- and cross-correlation lags either side of zero, samples.

    `max_lag` when given (at most `shortest − 1`). Else, knowing the model's slowest
    time constant `time_scale` (s, `slowest_time_constant`), `ceil(2 τ / dt)`, so that
    a residual the slow dynamics leave behind is seen to rise and decay, capped at a
    quarter of the shortest run (`shortest` samples) and at `MAX_LAG_SAMPLES`. Without
    either, `min(30, shortest / 5)`."""
    if max_lag is not None:
        return max(0, min(int(max_lag), shortest - 1))
    if time_scale is not None and math.isfinite(time_scale) and time_scale > 0 \
            and math.isfinite(dt) and dt > 0:
        lag = math.ceil(_LAGS_PER_TIME_SCALE * time_scale / dt)
        return max(1, min(lag, shortest // 4, MAX_LAG_SAMPLES, shortest - 1))
    return max(0, min(max(1, min(30, shortest // 5)), shortest - 1))


def _split_key(key: str, firsts, seconds=None) -> tuple[str, str] | None:
    """`a-b` split at the hyphen where `a` is in `firsts` (and `b` in `seconds`, if given);
    node names may hold hyphens themselves."""
    for i, ch in enumerate(key):
        if ch == "-" and key[:i] in firsts and (seconds is None or key[i + 1:] in seconds):
            return key[:i], key[i + 1:]
    return None


def slowest_time_constant(parameters: dict) -> float | None:
    """The model's slowest time constant, s, from a fit's `parameters` (dotted name ->
    {"value", ...}; docs/formats.md §5): the largest `1/eig(C^-½ K C^-½)`
    (`model._network.time_constants`) of the capacitances `nodes.<n>.capacitance` and
    the conductances `links.<a>-<b>.conductance` and `boundaries.<n>-<input>.conductance`
    (nodes with no path to a boundary left out), or an effect's own `time_constant`
    or `tau` (a sensor lag, a viscoelastic bias) if slower. None when the parameters
    name no capacitance or no boundary."""
    from ..model._network import time_constants

    def value(p):
        v = (p or {}).get("value") if isinstance(p, dict) else None
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) else None

    caps = {k[len("nodes."):-len(".capacitance")]: value(p) for k, p in parameters.items()
            if k.startswith("nodes.") and k.endswith(".capacitance")}
    caps = {n: c for n, c in caps.items() if c is not None and c > 0}
    if not caps:
        return None
    links, bounds = [], {}
    for k, p in parameters.items():
        g = value(p)
        if not k.endswith(".conductance") or g is None or g <= 0:
            continue
        key = k.split(".", 1)[1][:-len(".conductance")]
        if k.startswith("links.") and (ab := _split_key(key, caps, caps)):
            links.append((*ab, g))
        elif k.startswith("boundaries.") and (nb := _split_key(key, caps)):
            bounds[nb[0]] = bounds.get(nb[0], 0.0) + g
    # only the nodes with a path to a boundary (the others never settle: τ = inf)
    reached, todo = set(bounds), list(bounds)
    while todo:
        n = todo.pop()
        for a, b, _ in links:
            for x, y in ((a, b), (b, a)):
                if x == n and y not in reached:
                    reached.add(y)
                    todo.append(y)
    if not reached:
        return None
    names = [n for n in caps if n in reached]
    index = {n: i for i, n in enumerate(names)}
    K = np.diag([bounds.get(n, 0.0) for n in names])
    for a, b, g in links:
        if a in index and b in index:
            i, j = index[a], index[b]
            K[i, i] += g
            K[j, j] += g
            K[i, j] -= g
            K[j, i] -= g
    taus = np.asarray(time_constants(np.array([caps[n] for n in names]), K), float)
    effect_taus = [value(p) for k, p in parameters.items() if k.startswith("effects.")
                   and k.rsplit(".", 1)[-1] in ("time_constant", "tau")]
    return float(max([taus.max(), *(t for t in effect_taus if t is not None and t > 0)]))


# ---------------------------------------------------------------------------
# Numbers, one test at a time: each returns its JSON entry and its findings,
# `(weight, sentence)` pairs (heavier first in the report)


def _fit_figures(runs, j: int) -> tuple[dict, list[np.ndarray]]:
    """Column `j`'s pooled and per-run `rmse` and `fit_percent`, and its residual per run
    (measured − predicted, (T,) each)."""
    y = [r["measured"][:, j] for r in runs]
    yhat = [r["predicted"][:, j] for r in runs]
    res = [a - b for a, b in zip(y, yhat)]
    y_all, p_all = np.concatenate(y), np.concatenate(yhat)
    n_fin = int(np.isfinite(y_all).sum())
    col = {
        "n_samples": n_fin,
        "rmse": rmse(y_all, p_all),
        "fit_percent": fit_percent(y_all, p_all),
        "mean_residual": float(np.nanmean(y_all - p_all)) if n_fin else None,
        "per_run": [{"run": r["name"], "rmse": rmse(a, b), "fit_percent": fit_percent(a, b)}
                    for r, a, b in zip(runs, y, yhat)],
    }
    return col, res


def _whiteness(c: str, res, white_p: float = WHITE_P) -> tuple[dict, tuple[float, str]]:
    """Ljung-Box over the pooled runs: its entry and its finding (white when p is at
    least `white_p`)."""
    q, p_lb, lags = ljung_box(res)
    white = p_lb >= white_p
    entry = {"q": q, "p": p_lb, "lags": lags, "white": white}
    if white:
        return entry, (0.0, f"{c}: residuals white (Ljung-Box p {_p(p_lb)}, {lags} lags)")
    return entry, (1e9, f"{c}: residuals not white (Ljung-Box p {_p(p_lb)} over {lags} lags)")


def _phase_contrast(res, phases, a: str, b: str, frac: float, scale: float):
    """`_phase_diff` of phases `a` and `b`, and whether it is reported (beyond `_PHASE_SE`
    standard errors and `_PHASE_REL` × `scale`, the column's RMSE)."""
    diff, se = _phase_diff(res, phases, a, b, frac)
    sig = diff is not None and abs(diff) > _PHASE_SE * se and abs(diff) > _PHASE_REL * scale
    return diff, se, bool(sig)


def _phase_evidence(c: str, unit: str, res, phases, col_rmse) -> tuple[dict, list]:
    """Residual mean and RMSE per chamber phase, the heating-minus-cooling asymmetry and
    the power-step-minus-dwell difference, with their findings."""
    by_phase = residuals_by_phase(res, phases)
    out = {k: {"n": v["n"], "mean": v["mean"], "rmse": v["rms"]}
           for k, v in by_phase.items() if k in PHASES}
    out["heating_minus_cooling"] = by_phase["heating_minus_cooling"]
    frac = _n_eff(res)
    scale = col_rmse if col_rmse is not None and math.isfinite(col_rmse) else 0.0
    findings = []
    diff, se, sig = _phase_contrast(res, phases, "heating_ramp", "cooling_ramp", frac, scale)
    out["asymmetry"] = {"heating_minus_cooling": diff, "std_error": se, "significant": sig}
    if sig:
        h, cc = by_phase["heating_ramp"]["mean"], by_phase["cooling_ramp"]["mean"]
        findings.append((abs(diff) / se, (
            f"{c}: heating-ramp residual {h:+.2g} {unit} vs cooling {cc:+.2g} {unit} "
            f"(asymmetry {diff:+.2g} {unit}, {abs(diff) / se:.0f} standard errors: a "
            "temperature-dependent or rate-dependent effect)")))
    diff, se, sig = _phase_contrast(res, phases, "power_step", "dwell", frac, scale)
    out["power_step_minus_dwell"] = {"difference": diff, "std_error": se, "significant": sig}
    if sig:
        findings.append((abs(diff) / se, (
            f"{c}: residual after power steps {diff:+.2g} {unit} from the dwell level "
            f"({abs(diff) / se:.0f} standard errors: a missing heat path, a lag or a "
            "power-dependent effect)")))
    return out, findings


def _cross_correlations(c: str, res, signals, lag: int, dt: float, white: bool
                        ) -> tuple[list[dict], list]:
    """Per input and derivative (`signals`, per run, from `_signals`): the largest
    |cross-correlation| with the residual over lags `-lag..lag`, its pointwise band and
    the band for the largest of all lags of all signals; findings for the strongest."""
    n_signals = len(signals[0])
    n_tests = (2 * lag + 1) * n_signals
    xc = []
    for s in range(n_signals):
        name, deriv, _ = signals[0][s]
        lags, ccf, band = cross_correlation(res, [sig[s][2] for sig in signals], lag)
        k = int(np.argmax(np.abs(ccf)))
        # The band for the largest of all 2L+1 lags of all 2m signals (Šidák): what
        # a white residual independent of the inputs stays inside 95 % of the time.
        band_all = float(stats.norm.isf((1 - 0.95 ** (1 / n_tests)) / 2) * band / 1.96)
        peak = float(ccf[k])
        xc.append({"signal": name, "derivative": deriv, "label": _label(name, deriv),
                   "peak": peak, "abs_peak": abs(peak), "lag_samples": int(lags[k]),
                   "lag_s": float(lags[k] * dt), "band": band, "band_all_lags": band_all,
                   "exceeds_band": abs(peak) > band, "significant": abs(peak) > band_all})
    strong = sorted((e for e in xc if e["significant"]), key=lambda e: -e["abs_peak"])
    findings = [(e["abs_peak"] / e["band"], (
        f"{c}: residual correlates with {e['label']} (peak {e['peak']:.2f} at lag "
        f"{_seconds(e['lag_s'])} s, lags searched ±{_seconds(lag * dt)} s, band "
        f"{e['band']:.2g}"
        + ("; at the edge of the lags searched, so the true peak may lie further)"
           if abs(e["lag_samples"]) == lag else ")")
        + ("" if white else "; the band assumes a white residual, so read it as a lead")))
        for e in strong[:_MAX_CORR_FINDINGS]]
    return xc, findings


def _periodogram(c: str, res, dt: float) -> tuple[dict | None, list]:
    """The cumulated periodogram's largest departure from the white-noise line against
    its 5 % Kolmogorov-Smirnov bound (None when no run has 4 samples)."""
    if not any(len(r) >= 4 for r in res):
        return None, []
    f, cp, bound = cumulated_periodogram(res)
    dev = cp - f
    k = int(np.argmax(np.abs(dev)))
    side = "low" if dev[k] > 0 else "high"
    entry = {"max_deviation": float(abs(dev[k])), "bound": bound,
             "at_fraction_of_nyquist": float(f[k]), "at_hz": float(f[k] / (2 * dt)),
             "excess_at": side, "exceeds": bool(abs(dev[k]) > bound)}
    if abs(dev[k]) <= bound:
        return entry, []
    what = ("slow drift or missing slow dynamics" if side == "low"
            else "fast wiggles: sensor noise model or a missing fast path")
    return entry, [(abs(dev[k]) / bound, (
        f"{c}: residual power concentrated at {side} frequencies (cumulated "
        f"periodogram off the white line by {abs(dev[k]):.2f}, 5% bound {bound:.2g}: "
        f"{what})"))]


def _tests(lb_lags, lag: int, dt: float, n_inputs: int, chamber, powers,
           time_scale: float | None = None, white_p: float = WHITE_P) -> dict:
    """How every number was computed, for the report."""
    return {
        "residuals": "measured minus predicted (as given in the run traces)",
        "pooling": "lagged products summed over runs, each run about its own mean; "
                   "a lag never straddles two runs",
        "ljung_box": {"lags": lb_lags, "lags_rule": "min(20, N/5) with N the pooled sample count",
                      "white_if_p_at_least": white_p},
        "cross_correlation": {
            "lags_samples": lag, "lags_s": lag * dt, "sample_interval_s": dt,
            "slowest_time_constant_s": time_scale,
            "lags_rule": f"ceil({_LAGS_PER_TIME_SCALE:g} × slowest time constant / dt), at "
                         f"most a quarter of the shortest run and {MAX_LAG_SAMPLES} samples"
                         if time_scale else "as given, or min(30, shortest run / 5)",
            "lag_sign": "positive lag: the input leads the residual",
            "band": "1.96/sqrt(N), pointwise 95 % for a white residual independent of the input",
            "band_all_lags": f"Šidák-corrected 95 % band for the largest of {2 * lag + 1} lags "
                             f"times {2 * n_inputs} signals; 'significant' and the "
                             "findings use it",
            "derivative": "central differences (numpy.gradient) of each input over ts"},
        "cumulated_periodogram": "Box-Jenkins; bound 1.36/sqrt(m - 1), 5 % Kolmogorov-Smirnov",
        "phases": {"chamber_input": chamber, "power_inputs": powers,
                   "labelling": "label_phases: ramp beyond 0.2 °C/min, power step 600 s after "
                                "a jump in power",
                   "asymmetry_rule": f"reported beyond {_PHASE_SE:g} standard errors (sample "
                                     "counts shrunk by the AR(1) factor (1-ρ₁)/(1+ρ₁)) and "
                                     f"beyond {_PHASE_REL:g} × the column's RMSE"},
    }


def diagnose_traces(columns: list[str], runs: list[RunTrace], input_names: list[str],
                    boundary_inputs=(), max_lag: int | None = None,
                    units: dict | None = None, time_scale: float | None = None,
                    white_p: float = WHITE_P) -> dict:
    """Describe how a model fails on its run traces, as a JSON-ready dict (no NaN).

    Per column: `rmse` and `fit_percent` (`100 (1 - ‖y - ŷ‖/‖y - mean y‖)`) pooled over
    runs and per run; Ljung-Box whiteness (runs pooled); residual mean/RMSE per
    chamber phase (`label_phases` on the first boundary input and the power inputs)
    with the heating-minus-cooling asymmetry; for every input and its time
    derivative the largest |cross-correlation| with the residual over lags
    `-max_lag..max_lag` against its 95 % band; and the cumulated periodogram's
    largest departure from the white-noise line against its 5 % Kolmogorov-Smirnov
    bound. Plus `findings`, plain-English sentences, strongest evidence first within
    each column.

    **Arguments:**

    - `columns`: the measured column names, `p` of them.
    - `runs`: run traces (see the module docstring), `measured`/`predicted` `(T, p)`,
      `inputs` `(T, m)`, `ts` in s.
    - `input_names`: the `m` input names, in the order of `inputs`' columns.
    - `boundary_inputs`: the names among `input_names` that are boundary (chamber)
      temperatures; the first one labels the ramps and dwells, the others inputs
      (not boundaries) are powers whose jumps label power steps.
    - `max_lag`: cross-correlation lags, samples (default from `time_scale`, see
      `lag_span`).
    - `units`: column -> unit for the sentences (default °C; `_plots.column_units`).
    - `time_scale`: the model's slowest time constant, s (`slowest_time_constant`):
      the lags then span two of it, so a slow residual is seen to rise and decay;
      without it, `min(30, shortest run / 5)` samples.
    - `white_p`: the Ljung-Box p at or above which a column is called white (the
      investigation's report passes its loop's threshold, so that both agree).

    **Returns:** `{"columns": {column: {...}}, "findings": [str], "tests": {...}}`.
    """
    runs = _check_runs(columns, runs, input_names)
    units = units or {}
    chamber, powers = _split_inputs(input_names, boundary_inputs)
    phases = [_phases(r, input_names, chamber, powers) for r in runs]
    dt = _dt(runs)
    lag = lag_span(dt, min(len(r["ts"]) for r in runs), time_scale, max_lag)
    signals = [_signals(r, input_names) for r in runs]

    out_cols, findings = {}, []
    lb_lags = None
    for j, c in enumerate(columns):
        col, res = _fit_figures(runs, j)
        out_cols[c] = col
        if col["n_samples"] < _MIN_SAMPLES:
            col.update({"ljung_box": None, "phases": None, "cross_correlation": [],
                        "cumulated_periodogram": None})
            findings.append(f"{c}: too few measured samples ({col['n_samples']}) to test the "
                            "residual")
            continue
        col["ljung_box"], white = _whiteness(c, res, white_p)
        lb_lags = col["ljung_box"]["lags"]
        col["phases"], by_phase = _phase_evidence(c, units.get(c, "°C"), res, phases,
                                                  col["rmse"])
        col["cross_correlation"], by_input = _cross_correlations(
            c, res, signals, lag, dt, col["ljung_box"]["white"])
        col["cumulated_periodogram"], by_frequency = _periodogram(c, res, dt)
        ranked = [white, *by_phase, *by_input, *by_frequency]
        findings += [s for _, s in sorted(ranked, key=lambda t: -t[0])]

    tests = _tests(lb_lags, lag, dt, len(input_names), chamber, powers, time_scale, white_p)
    return json_safe({"columns": out_cols, "findings": findings, "tests": tests,
                      "runs": [r["name"] for r in runs]})


# ---------------------------------------------------------------------------
# Significance when a parameter exists only under the alternative


LAG_FAMILY_CURVATURE = 0.25
"""−ρ''(0) of a score process over log τ for first-order-lag directions driven by white
excitation: the correlation of the directions at τ₁, τ₂ is sech(ln(τ₂/τ₁)/2). Smoother
excitation correlates them more, so the bound below stays conservative."""


def davies_variation(log_range: float, curvature: float = LAG_FAMILY_CURVATURE) -> float:
    """Expected total variation `V = √(2/π) √λ₂ · range` of √S(θ) over a nuisance θ (here a
    time constant's logarithm spanning `log_range`), for Davies' bound."""
    return math.sqrt(2.0 / math.pi) * math.sqrt(curvature) * max(float(log_range), 0.0)


def davies_p_value(statistic: float, df: int, variation: float) -> float:
    """Davies (1987) upper bound on `P(sup_θ S(θ) > u)` for a χ²_df process `S` whose
    parameter θ does not exist under the null (an extra node's time constant, a
    viscoelastic τ):

        P(χ²_df > u) + V u^{(df−1)/2} e^{−u/2} 2^{−df/2} / Γ(df/2)

    with `V` the total variation of √S over θ (`davies_variation`)."""
    u = max(float(statistic), 0.0)
    df = max(int(df), 1)
    if u <= 0.0:
        return 1.0
    log_term = (math.log(max(variation, 1e-300)) + 0.5 * (df - 1) * math.log(u) - 0.5 * u
                - 0.5 * df * math.log(2.0) - math.lgamma(0.5 * df))
    return float(min(1.0, stats.chi2.sf(u, df) + math.exp(log_term)))
