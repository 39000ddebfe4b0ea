"""The held-out check of a candidate the likelihood-ratio rule supports
(`_selection.holdout_verdict`): the folds (`holdout_folds`), each model fitted without
a fold (`_fit_without`, kept for the next step by `HeldOutFits`), each fold's vote
(`_thermal_fold_votes`, `_viscoelastic_fold_votes`), and the first supported candidate
the check does not reject (`_choose`)."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ._candidates import Candidate
from ._selection import FoldVote, fold_vote, holdout_verdict
from ._step import Step, _bias_runs, _experiments, evaluate
from ..fitting._bias import fit_bias, viscoelastic_candidate
from ..fitting._initial_states import fitted_starts
from ..fitting._fit import fit
from ..fitting._side_by_side import side_by_side
from ..fitting._solver import TruncatedGaussNewton
from ..measurements._telemetry import Telemetry


N_BLOCKS = 4  # held-out folds when there are fewer than three runs


def holdout_folds(runs: list[Telemetry], n_blocks: int = N_BLOCKS) -> list[tuple]:
    """The held-out folds: `(run, None)` for each run with three runs or more, else
    `(run, (start, stop))` sample spans cutting the runs into about `n_blocks` contiguous
    blocks in all (blocked cross-validation)."""
    if len(runs) >= 3:
        return [(r, None) for r in range(len(runs))]
    per = -(-n_blocks // len(runs))
    out = []
    for r, t in enumerate(runs):
        edges = np.linspace(0, len(t.ts), per + 1).astype(int)
        out += [(r, (int(a), int(b))) for a, b in zip(edges[:-1], edges[1:]) if b > a]
    return out


def _held_rows(fold, n: int) -> slice:
    return slice(0, n) if fold[1] is None else slice(*fold[1])


# A held-out fit starts at the fit to all the data (`spec`'s values): a warm start, whose
# first Gauss-Newton steps are already good, so its damping starts a thousand times
# lower than a cold start's (on imu6 the folds take 2-4 steps fewer each).
_WARM_START = TruncatedGaussNewton(initial_damping=1e-6)


def _fit_without(spec, experiments, fold, starts=None, likelihood="output_error"):
    """Fit of `spec` (its values those of the fit to all the data) with the fold's
    measurements masked; its predictions still cover them (the free run, or the filter,
    goes through the held-out block). A Kalman fold fit ends after its scoring steps (no
    polish: from that warm start it would walk the full fit's valleys again for a few
    0.1 of −log L, most of a loop's time on PRBS1). A warm start that does not converge
    is tried once more with the default solver; a fit that still does not converge is
    returned as it is (`fold_vote` sets its fold aside).

    The block is masked in the likelihood, not in the data, and each run's estimated
    start begins at `starts` (node -> per-run °C: the fit to all the data's), since data
    after a held-out first block cannot determine it: a start taken from the first
    reading after the block gave a true sensor lag a held-out gain of −310 on its first
    block, and the loop rejected it."""
    r, span = fold
    holdout = r if span is None else (r, tuple(span))
    for solver in ((_WARM_START, None) if likelihood == "output_error" else (None,)):
        res = fit(spec, experiments, likelihood=likelihood, holdout=holdout, solver=solver,
                  restart_plateaus=False, polish=False, starts=starts)
        if res.converged:
            break
    if not np.isfinite(res.nll) or not all(np.all(np.isfinite(p)) for p in res.predictions):
        raise FloatingPointError("the held-out fit went non-finite")
    return res


def held_out_terms(res, experiments, fold, rows, sigma, likelihood) -> np.ndarray:
    """Per held-out sample, its −log L term under a fit made without the fold: half the
    squared free-run residuals over `sigma` summed over the outputs (output error; the
    constant terms cancel between models), or, under the Kalman likelihood, the filter run
    through every sample with those parameters and each held-out sample's one-step
    predictive term (prequential). Missing readings contribute nothing."""
    r = fold[0]
    if likelihood == "kalman":
        from ..fitting._likelihood import kalman_sample_nll
        from ..measurements._data import Dataset

        data = Dataset.from_experiments(experiments)
        per = np.asarray(kalman_sample_nll(res.model, data, res.state.run_initial))
        return per[r, :len(experiments[r].ts)][rows]
    e = (experiments[r].outputs[rows] - res.predictions[r][rows]) / sigma[None, :]
    return 0.5 * np.nansum(e ** 2, axis=1)


def _unconverged(res) -> str:
    return "" if getattr(res, "converged", True) else \
        f"a held-out fit did not converge ({getattr(res, 'message', '')})"


class HeldOutFits:
    """`_fit_without` of one loop's runs, kept: the model a step adds is the next step's
    base, held out on the same folds, so its fits are made once. A fit that raised is
    kept as its exception."""

    def __init__(self):
        self._done: list[tuple] = []  # (spec, fold, likelihood, FitResult or exception)

    def _kept(self, spec, fold, likelihood):
        for s, f, lk, res in self._done:
            if f == fold and lk == likelihood and s == spec:
                return res
        return None

    def __call__(self, spec, experiments, fold, likelihood, starts=None):
        res = self._kept(spec, fold, likelihood)
        if res is None:
            self.make([(spec, experiments, fold, starts)], likelihood)
            res = self._kept(spec, fold, likelihood)
        return res

    def make(self, wanted: list[tuple], likelihood) -> None:
        """Make the fits `(spec, experiments, fold, starts)` of `wanted` not made yet,
        side by side (`fitting._side_by_side`); a fit that raises is kept as its
        exception. `starts`: the full fit's per-run starts (`_fit_without`)."""
        missing = [w for w in wanted if self._kept(w[0], w[2], likelihood) is None]

        def attempt(*args):
            try:
                return _fit_without(*args)
            except Exception as err:  # the fold is inconclusive, not the candidate
                return err

        made = side_by_side([functools.partial(attempt, *w, likelihood) for w in missing])
        self._done += [(s, fold, likelihood, res) for (s, _, fold, _), res in zip(missing, made)]


def _thermal_fold_votes(spec_base, spec_ext, runs, sigma, folds, say, likelihood,
                        fits: HeldOutFits, starts=(None, None)) -> list[FoldVote]:
    """Each fold's vote between the model without the effect and with it; `starts`: the
    two full fits' per-run starts (`fitting._initial_states.fitted_starts`)."""
    experiments = {id(s): _experiments(s, runs) for s in (spec_base, spec_ext)}
    fits.make([(s, experiments[id(s)], fold, st) for fold in folds
               for s, st in zip((spec_base, spec_ext), starts)], likelihood)
    votes = []
    for fold in folds:
        rows = _held_rows(fold, len(runs[fold[0]].ts))
        terms = []
        for s in (spec_base, spec_ext):
            res = fits(s, experiments[id(s)], fold, likelihood)
            why = "" if isinstance(res, Exception) else _unconverged(res)
            terms.append(res if isinstance(res, Exception) else RuntimeError(why) if why else
                         held_out_terms(res, experiments[id(s)], fold, rows, sigma,
                                        likelihood))
        votes.append(fold_vote(fold, *terms))
        _say_vote(say, votes[-1])
    return votes


def _say_vote(say, v: FoldVote) -> None:
    say(f"held-out fold {v.fold}: −log L change {-v.gain:.1f}" +
        (f" (inconclusive: {v.inconclusive})" if v.inconclusive else ""))


def _viscoelastic_fold_votes(current: Step, c: Candidate, runs, folds, say) -> list[FoldVote]:
    """Held-out gains of a viscoelastic term, fitted on its bias channel with the fold's
    bias samples masked (a whole held-out run keeps its first sample), on the current
    thermal states."""
    bias = next(b for b in current.spec.biases if b.column == c.where[1])
    base_runs, rates = _bias_runs(current.result, runs, bias)
    node_names = list(current.result.lowered_spec.node_names)
    sigma = float(current.biases[bias.column].sigma)
    votes = []
    for fold in folds:
        r = fold[0]
        rows = _held_rows(fold, len(runs[r].ts))
        masked = list(base_runs)
        ts, x, y = masked[r]
        ym = np.array(y, float)
        ym[rows] = np.nan
        if fold[1] is None:
            ym[0] = y[0]
        masked[r] = (ts, x, ym)
        try:
            before = fit_bias(bias, list(current.spec.effects), masked, node_names, rates)
            after, _ = viscoelastic_candidate(bias, list(current.spec.effects), masked,
                                              node_names, c.where[0], node_rates=rates)
        except Exception as err:  # this fold is inconclusive, not the candidate
            votes.append(fold_vote(fold, err, err))
            _say_vote(say, votes[-1])
            continue
        terms = [0.5 * np.nan_to_num(((y[rows] - f.predictions[r][rows]) / sigma) ** 2,
                                     nan=0.0, posinf=np.inf)
                 for f in (before, after)]
        votes.append(fold_vote(fold, *terms))
        _say_vote(say, votes[-1])
    return votes


def check_holdout(c: Candidate, current: Step, runs, likelihood, say,
                  fits: HeldOutFits) -> None:
    """The held-out check of a candidate that passed the likelihood-ratio rule
    (`_selection.holdout_verdict`): its fold votes, summed gain and verdict go into `c`;
    a rejected candidate is marked unsupported with the reason."""
    folds = holdout_folds(runs)
    if c.kind == "viscoelastic":
        votes = _viscoelastic_fold_votes(current, c, runs, folds, say)
    else:
        sigma = np.array([current.record["parameters"].get(
            f"sensors.{s}.noise", {"value": 0.01})["value"]
            for s in current.spec.sensor_columns])
        votes = _thermal_fold_votes(current.spec, c.result.spec, runs, sigma,
                                    folds, say, likelihood, fits,
                                    (fitted_starts(current.result),
                                     fitted_starts(c.result.result)))
    ok, c.holdout_gain, why = holdout_verdict(votes)
    c.holdout_votes = votes
    scheme = "leave one run out" if folds[0][1] is None else f"{len(folds)} contiguous blocks"
    if ok is False:
        c.supported = False
        c.add_note(f"held-out check against it ({scheme}): {why}", first=True)
    else:
        c.add_note(f"{why} ({scheme})", first=True)


def _choose(cands: list[Candidate], current: Step, runs, likelihood, holdout_check: bool,
            say, fits: HeldOutFits, checking=None) -> Candidate | None:
    """The first supported candidate that (with `holdout_check`) the held-out check does
    not reject (`check_holdout`) and whose extended model could be built; the others it
    tries are marked unsupported, with the reason. On return `chosen.result` holds the
    extended step. `fits`: the loop's held-out fits so far; `checking(c)`: called as the
    held-out check of a refitted candidate starts (its figures are drawn meanwhile)."""
    for c in cands:
        if not c.supported:
            continue
        try:
            if holdout_check:
                if checking is not None and isinstance(c.result, Step):
                    checking(c)  # a thermal candidate's extended step
                check_holdout(c, current, runs, likelihood, say, fits)
                if not c.supported:
                    continue
            if c.kind == "viscoelastic":
                c.result = _viscoelastic_step(current, c, runs, likelihood)
        except Exception as err:  # a failed extended fit rejects the candidate
            c.supported = False
            c.note = f"held-out or extended fit failed: {type(err).__name__}: {err}"[:300]
            continue
        return c
    return None


def _viscoelastic_step(current: Step, c: Candidate, runs, likelihood) -> Step:
    from ..model._spec import Effect, Parameter

    eff = Effect("viscoelastic", c.where, {k: Parameter(v) for k, v in c.parameters.items()})
    return evaluate(current.spec.replace(effects=current.spec.effects + (eff,)), runs,
                    likelihood)
