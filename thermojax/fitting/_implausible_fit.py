"""What a finished fit's own numbers say against the model file it started from: a
noise far above the one written (the model misses what the data hold), and every
capacitance far from its written value in the same direction (the file's clock runs at
another rate than the model assumes, as `time_s` in minutes does).

Each finding is a sentence a user can act on; the fit stands (its report carries them
under `warnings`), since a model file's values are starts, not truths.
"""

from __future__ import annotations

import numpy as np

from ..model._spec import ModelSpec

# A fitted noise std this many times the written one: the residual is mostly model error.
NOISE_FACTOR = 10.0
# Every free capacitance moved by this factor or more, all the same way: a unit, not
# physics (a wrong guess moves one capacitance, a clock moves them all).
CAPACITANCE_FACTOR = 10.0


def noise_far_above_written(written: ModelSpec, fitted: ModelSpec) -> list[str]:
    """Per sensor whose written `noise` (°C) the fit estimated at `NOISE_FACTOR` times or
    more: what that says and what to do."""
    given = {s.column: s.noise for s in written.sensors if s.noise is not None}
    out = []
    for s in fitted.sensors:
        w = given.get(s.column)
        if w is None or w.fixed or s.noise is None or not w.value > 0:
            continue
        ratio = float(s.noise.value) / float(w.value)
        if ratio >= NOISE_FACTOR:
            out.append(f"the fitted noise of {s.column} is {s.noise.value:.3g}, {ratio:.0f}× "
                       f"the {w.value:.3g} the model file states: the residual is model error, "
                       "not sensor noise. Run `thermojax diagnose` (or `investigate`) to find "
                       "the missing physics before using this model for an observer, which "
                       "would trust this sensor that little.")
    return out


def capacitances_all_scaled(written: ModelSpec, fitted: ModelSpec) -> list[str]:
    """One sentence when every free capacitance (two or more, J/K) ended `CAPACITANCE_FACTOR`
    times or more from its written value, all the same way; else none."""
    start = {n.name: n.capacitance for n in written.nodes}
    ratios = [float(n.capacitance.value) / float(start[n.name].value) for n in fitted.nodes
              if n.name in start and not start[n.name].fixed and start[n.name].value > 0]
    if len(ratios) < 2:
        return []
    ratios = np.asarray(ratios)
    if np.all(ratios <= 1 / CAPACITANCE_FACTOR):
        factor, way, unit = float(np.median(1 / ratios)), "below", "minutes make them 60×"
    elif np.all(ratios >= CAPACITANCE_FACTOR):
        factor, way, unit = float(np.median(ratios)), "above", "milliseconds make them 1000×"
    else:
        return []
    return [f"every capacitance ended {CAPACITANCE_FACTOR:g}× or more {way} its value in the "
            f"model file (the median {factor:.0f}×): the time constants the data show are "
            f"that far from the model's. Check that `time_s` is in seconds ({unit} too "
            f"{'small' if way == 'below' else 'large'}), then the written values."]


def implausible_fit(written: ModelSpec, fitted: ModelSpec) -> list[str]:
    """Every finding of this module on a fit of `written` that ended at `fitted`."""
    return noise_far_above_written(written, fitted) + capacitances_all_scaled(written, fitted)
