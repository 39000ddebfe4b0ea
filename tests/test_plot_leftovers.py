"""The plots issue 32 found misleading: an autocorrelation on a fixed ±1 axis, an empty
"power step" slot, calibration axes in "(channel unit)", Monte Carlo histograms whose
blended overlaps match no legend entry."""

from __future__ import annotations

import pathlib

import numpy as np

from thermojax.investigation._diagnostic_plots import _acf_figure, _phases_figure


def test_autocorrelation_axis_fits_the_data_and_names_the_test():
    rng = np.random.default_rng(0)
    e = rng.standard_normal(3000)
    r = e.copy()
    r[1:] += 0.08 * e[:-1]                     # a small, significant lag-1 correlation
    fig = _acf_figure(["T_a"], [[r]], 1.0, 100, 60, "t")
    ax = fig.axes[0]
    lo, hi = ax.get_ylim()
    assert hi < 0.2 and lo == -hi              # not ±1: the correlation is visible
    # the title's Ljung–Box p, recomputed here from its formula
    n, lags = r.size, 20
    x = r - r.mean()
    rho = np.array([np.dot(x[:-k], x[k:]) for k in range(1, lags + 1)]) / np.dot(x, x)
    q = n * (n + 2) * np.sum(rho ** 2 / (n - np.arange(1, lags + 1)))
    import scipy.stats

    p = scipy.stats.chi2.sf(q, lags)
    assert f"p = {p:.2g}" in ax.get_title() and "Ljung–Box" in ax.get_title()
    # the verdict is the report's, at the loop's threshold, once per step: a title that
    # judged at 5 % contradicted a loop judging at 1 %
    assert "white" not in ax.get_title()


def test_phases_without_samples_are_not_drawn():
    ts = np.arange(2000.0)
    T = 25 + np.clip((ts - 500) / 60 * 2, 0, 20)           # a heating ramp, then a dwell
    run = {"ts": ts, "inputs": np.stack([T, np.zeros_like(ts)], 1)}
    res = [[0.01 * np.random.default_rng(1).standard_normal(ts.size)]]
    fig = _phases_figure(["T_a"], [run], res, ["T_chamber", "P_asic"], ["T_chamber"],
                         {"T_a": "°C"}, "t")
    labels = [t.get_text() for t in fig.axes[0].get_xticklabels()]
    assert labels == ["heating ramp", "dwell"]
    assert "power step" in fig._suptitle.get_text()          # said, not drawn empty


def test_montecarlo_histograms_are_outlines(tmp_path):
    from thermojax.montecarlo._report import _plots

    rng = np.random.default_rng(0)
    methods = {"nominal": "nominal matrices", "fitted": "per-unit fit"}
    results = {f"{m}_{k}": np.exp(rng.normal(-i, 0.5, 200)) for i, m in enumerate(methods)
               for k in ("bias_peak", "temp_peak")}
    r = {"methods": methods, "bias_units": "deg/h", "temperature_node": "proof_mass",
         "bias_limit": 0.5, "n_units": 200}
    seen = {}

    def atomic_write(path, data):
        pathlib.Path(path).write_bytes(data)
        seen[path.name] = len(data)

    import thermojax._plots as plots

    figures, original = [], plots.new_figure

    def keep(**kw):                       # the figures `_plots` draws, to inspect
        figures.append(original(**kw))
        return figures[-1]

    plots.new_figure = keep
    try:
        names = _plots(tmp_path, results, r, atomic_write)
    finally:
        plots.new_figure = original
    assert set(names) == set(seen) and len(figures) == 2
    for fig in figures:
        patches = fig.axes[0].patches
        assert patches and all(not p.get_fill() for p in patches)   # outlines only
        legend = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert legend[:2] == ["nominal matrices", "per-unit fit"]
