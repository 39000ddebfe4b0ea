"""Telemetry is checked for plausibility before any work (issue 32, item 1): a cell the
model's units and the other samples rule out is named by file, line and column, and the
user chooses to stop (the default, exit 2) or drop it (`--outliers drop`); a kelvin
column and a time column in milliseconds are named as such; after dropping, one glitch
no longer decides the fit.

The data are helpers' rtd2h runs (simulated by NumPy from a known truth) written as CSV
with one bad cell injected; the CLI runs in-process from the folder holding them, so the
fit reuses the compilation of tests/test_fit_cli.py's runs of the same names and shapes.
"""

import numpy as np
import pytest

from thermojax import write_telemetry
from thermojax._errors import InputError
from thermojax.cli import main
from thermojax.measurements import Telemetry, read_telemetry
from thermojax.measurements._plausibility import check_plausibility

from helpers import RTD2H_NAMES, RTD2H_TEXT, RTD2H_TRUTH, rtd2h_data, rtd2h_spec

ROW = 205  # 0-based data row of the injected cell: mid-way through a heater block
LINE = ROW + 2  # its line in the file: the header is line 1, no comments


def run(capsys, *argv):
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # argparse usage errors
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def assert_refused(rc, err, *fragments):
    assert rc == 2, err
    assert "Traceback" not in err
    for fragment in fragments:
        assert fragment in err, (fragment, err)


def channels_of(run_data):
    ts, U, Y, *_ = run_data
    return ts, {"T_fluid": U[:, 0].copy(), "P_heater": U[:, 1].copy(),
                "T_core": Y[:, 0].copy(), "T_sheath": Y[:, 1].copy()}


def write_runs(folder, edit=None, scale_time=1.0):
    """a.csv and b.csv of rtd2h in `folder`, each passed through `edit(channels)`."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "rtd2h.toml").write_text(RTD2H_TEXT)
    for name, data in zip(RTD2H_NAMES, rtd2h_data(1)):
        ts, channels = channels_of(data)
        if edit is not None:
            edit(channels)
        write_telemetry(folder / name, ts * scale_time, channels)
    return folder


def glitch(column, value, row=ROW):
    def edit(channels):
        channels[column][row] = value
    return edit


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    return write_runs(tmp_path_factory.mktemp("clean"))


# ---------------------------------------------------------------------------
# the check alone (no fit)


def test_clean_runs_pass_unchanged(clean):
    spec = rtd2h_spec()
    for name in RTD2H_NAMES:
        t = read_telemetry(clean / name)
        checked, dropped = check_plausibility(spec, t)
        assert checked is t and dropped == []


@pytest.mark.parametrize("column, value, words", [
    ("T_core", 1e300, "1e+300"), ("T_core", 1e6, "above 5000 °C"),
    ("T_core", -400.0, "below absolute zero"), ("T_sheath", 1e6, "1e+06"),
    ("T_fluid", 1e300, "1e+300"), ("P_heater", 1e300, "1e+300"),
    ("P_heater", 1e6, "far outside the rest of the column"),
])
def test_one_bad_cell_is_named_by_line_and_column(tmp_path, column, value, words):
    folder = write_runs(tmp_path, glitch(column, value))
    with pytest.raises(InputError) as e:
        check_plausibility(rtd2h_spec(), read_telemetry(folder / "a.csv"))
    assert (e.value.line, e.value.field) == (LINE, column)
    message = str(e.value)
    for fragment in (f"line {LINE}", f"column '{column}'", words, "--outliers drop"):
        assert fragment in message, (fragment, message)


def test_kelvin_column_is_named_as_kelvin(tmp_path):
    def kelvin(channels):
        channels["T_core"] += 273.15

    folder = write_runs(tmp_path, kelvin)
    with pytest.raises(InputError, match=r"'T_core' looks like kelvin.*subtract 273\.15") as e:
        check_plausibility(rtd2h_spec(), read_telemetry(folder / "a.csv"))
    assert e.value.field == "T_core"


def test_milliseconds_are_named_as_milliseconds(tmp_path):
    folder = write_runs(tmp_path, scale_time=1000.0)
    with pytest.raises(InputError, match="milliseconds.*divide it by 1000") as e:
        check_plausibility(rtd2h_spec(), read_telemetry(folder / "a.csv"))
    assert e.value.field == "time_s"


def telemetry(ts, **channels):
    return Telemetry(ts=np.asarray(ts, float), channels=channels)


ONE_NODE = """
name = "one"
[[nodes]]
name = "n"
capacitance = 1e6
[[boundaries]]
node = "n"
input = "Ta"
conductance = 200.0
[[heat_inputs]]
node = "n"
input = "P"
hold = "zoh"
gain = { value = 1.0, fixed = true }
[[sensors]]
node = "n"
column = "T"
"""


def test_legitimate_data_never_trigger():
    """Switched power, one short pulse, a quantized sensor stuck on one value but for one
    step, an hourly building log over a year, an oven at 250 °C: nothing is flagged."""
    import thermojax as tj

    spec = tj.parse_model(ONE_NODE, source="one.toml")
    rng = np.random.default_rng(0)
    n = 2000
    ts = 300.0 * np.arange(n)
    cases = {
        "prbs": dict(Ta=5 + rng.standard_normal(n), P=5000.0 * rng.integers(0, 2, n),
                     T=21 + 0.1 * rng.standard_normal(n)),
        "pulse": dict(Ta=np.full(n, 20.0), P=np.where(np.arange(n) == 700, 3000.0, 0.0),
                      T=np.round(21 + 0.01 * rng.standard_normal(n), 1)),
        "quantized": dict(Ta=np.full(n, 20.0), P=np.zeros(n),
                          T=np.where(np.arange(n) == 900, 20.5, 20.0)),
        "oven": dict(Ta=np.full(n, 20.0), P=np.full(n, 2e4),
                     T=250 + np.sin(np.arange(n) / 50.0)),
    }
    for name, channels in cases.items():
        t = telemetry(ts, **channels)
        assert check_plausibility(spec, t) == (t, []), name
    hourly = telemetry(3600.0 * np.arange(24 * 365), Ta=np.full(24 * 365, 10.0),
                       P=np.zeros(24 * 365), T=np.full(24 * 365, 20.0))
    assert check_plausibility(spec, hourly)[1] == []


def test_drop_makes_a_sensor_cell_missing_and_fills_an_input_by_its_hold():
    spec = rtd2h_spec()
    ts, channels = channels_of(rtd2h_data(1)[0])
    truth = {k: v.copy() for k, v in channels.items()}
    channels["T_core"][ROW] = 1e300
    channels["P_heater"][ROW] = 1e6  # zoh: the previous value
    channels["T_fluid"][ROW + 1] = -1e300  # foh: the line between its neighbours
    t = telemetry(ts, **channels)
    checked, dropped = check_plausibility(spec, t, outliers="drop")
    assert sorted((o.column, o.row) for o in dropped) == [
        ("P_heater", ROW), ("T_core", ROW), ("T_fluid", ROW + 1)]
    assert np.isnan(checked.channels["T_core"][ROW])
    assert checked.channels["P_heater"][ROW] == truth["P_heater"][ROW - 1]
    assert checked.channels["T_fluid"][ROW + 1] == pytest.approx(
        0.5 * (truth["T_fluid"][ROW] + truth["T_fluid"][ROW + 2]))
    untouched = np.ones(len(ts), bool)
    untouched[[ROW, ROW + 1]] = False
    for name in truth:
        np.testing.assert_array_equal(checked.channels[name][untouched],
                                      truth[name][untouched])


# ---------------------------------------------------------------------------
# the command line


@pytest.mark.parametrize("command", ["fit", "diagnose", "investigate"])
def test_commands_stop_before_work_and_name_the_cell(capsys, tmp_path, command):
    folder = write_runs(tmp_path, glitch("T_core", 1e300))
    rc, _, err = run(capsys, command, "--model", folder / "rtd2h.toml", "--data",
                     folder / "a.csv", "--out", tmp_path / "out")
    assert_refused(rc, err, "a.csv", f"line {LINE}", "'T_core'", "--outliers drop")
    assert not (tmp_path / "out").exists()


def test_unused_columns_are_checked_for_absurd_cells_only(capsys, tmp_path):
    """diagnose offers unused columns as candidate inputs: 1e300 there is refused, a
    status column with one odd code is not (its meaning is unknown)."""
    spec = rtd2h_spec()
    ts, channels = channels_of(rtd2h_data(1)[0])
    status = np.zeros(len(ts))
    status[ROW] = 255.0
    t = telemetry(ts, **channels, status=status)
    assert check_plausibility(spec, t, others=True) == (t, [])
    folder = write_runs(tmp_path, lambda c: c.update(spare=np.where(
        np.arange(len(c["T_core"])) == ROW, 1e300, 1.0)))
    assert check_plausibility(spec, read_telemetry(folder / "a.csv"))[1] == []
    rc, _, err = run(capsys, "diagnose", "--model", folder / "rtd2h.toml", "--data",
                     folder / "a.csv", "--out", tmp_path / "out")
    assert_refused(rc, err, f"line {LINE}", "'spare'")


@pytest.mark.parametrize("scale_time, edit, words", [
    (1.0, lambda c: c.__setitem__("T_core", c["T_core"] + 273.15), "kelvin"),
    (1000.0, None, "milliseconds"),
])
def test_fit_names_the_unit_mistake_even_when_dropping(capsys, tmp_path, scale_time, edit,
                                                        words):
    folder = write_runs(tmp_path, edit, scale_time)
    rc, _, err = run(capsys, "fit", "--model", folder / "rtd2h.toml", "--data",
                     folder / "a.csv", "--out", tmp_path / "out", "--outliers", "drop")
    assert_refused(rc, err, "a.csv", words)


SPIKE_ROW = 305  # a plausible 100 K spike (T_sheath spans about 16-40 °C): no unit rules it out


def _glitched_runs(folder, *edits):
    write_runs(folder)
    for name, edit in edits:
        t = read_telemetry(folder / name)
        channels = {k: np.array(v) for k, v in t.channels.items()}
        edit(channels)
        write_telemetry(folder / name, t.ts, channels)


def _spike(channels):
    channels["T_sheath"][SPIKE_ROW] += 100.0


def test_fit_after_dropping_recovers_the_truth(capsys, tmp_path, monkeypatch):
    """A 1e300 sensor cell and a plausible 100 K spike in a.csv and a 1e6 W heater cell in
    b.csv, dropped (the spike after the fit finds it alone carries the sensor's error): the
    fit finds the parameters that generated the data and says, on stderr and in
    report.json, what it dropped."""
    import json

    folder = tmp_path / "data"
    _glitched_runs(folder, ("a.csv", lambda c: (glitch("T_core", 1e300)(c), _spike(c))),
                   ("b.csv", glitch("P_heater", 1e6)))
    monkeypatch.chdir(folder)
    rc, out, err = run(capsys, "fit", "--model", "rtd2h.toml", "--data", "a.csv", "--data",
                       "b.csv", "--out", tmp_path / "out", "--outliers", "drop", "--quiet")
    assert rc == 0, err
    assert "a.csv: dropped 1 implausible cell" in err and f"line {LINE}" in err
    assert "b.csv: dropped 1 implausible cell" in err
    assert f"a.csv: dropped line {SPIKE_ROW + 2}, column 'T_sheath'" in err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    for name, value in RTD2H_TRUTH.items():
        assert report["parameters"][name]["value"] == pytest.approx(value, rel=0.05), name
    assert report["rmse"]["T_core"] < 0.02
    assert report["converged"] and report["dominant_samples"] == []
    cells = sorted((c["file"], c["line"], c["column"]) for c in report["dropped_cells"])
    assert cells == [("a.csv", LINE, "T_core"), ("a.csv", SPIKE_ROW + 2, "T_sheath"),
                     ("b.csv", LINE, "P_heater")]


def test_a_fit_that_follows_one_sample_is_not_converged(capsys, tmp_path, monkeypatch):
    """Without --outliers drop, the plausible spike is kept and the least-squares fit
    follows it: exit 0 with the fit written, but not "converged", the sample named."""
    import json

    folder = tmp_path / "data"
    _glitched_runs(folder, ("a.csv", _spike))
    monkeypatch.chdir(folder)
    rc, out, err = run(capsys, "fit", "--model", "rtd2h.toml", "--data", "a.csv", "--data",
                       "b.csv", "--out", tmp_path / "out", "--quiet")
    assert rc == 0, err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert not report["converged"]
    (d,) = report["dominant_samples"]
    assert (d["run_name"], d["column"], d["row"]) == ("a.csv", "T_sheath", SPIKE_ROW)
    assert d["share"] > 0.9 and d["residual"] == pytest.approx(100.0, abs=5.0)
    assert f"data row {SPIKE_ROW + 1}" in report["message"]  # 1-based, as every message
    assert "--outliers drop" in report["message"]
    assert "**not converged**" in (tmp_path / "out" / "report.md").read_text()
    assert report["dropped_cells"] == []


def test_gaussian_noise_and_model_error_never_dominate_but_a_spike_does():
    """`dominant_samples` on residuals built by hand: white noise over 200-2000 samples,
    a first-order lag misfit after one step (the error of a missed lag of 8 and of 1
    sample periods: 22 % and 86 % of the squared sum in one sample) and one spike."""
    from thermojax.fitting._dominance import MIN_SAMPLES, dominant_samples
    from thermojax.measurements._data import Experiment

    rng = np.random.default_rng(3)

    def runs(residual):
        n = residual.size
        ts = np.arange(n, dtype=float)
        e = Experiment(ts, np.zeros((n, 1)), (20.0 + residual)[:, None], name="r.csv")
        return [e], [np.full((n, 1), 20.0)]

    for n in (MIN_SAMPLES, 500, 2000):
        for _ in range(20):
            assert dominant_samples(["T"], *runs(rng.standard_normal(n))) == []
    k = np.arange(1000.0)
    for tau in (8.0, 1.0):  # a missed lag of tau samples after one step: no glitch
        lag = np.where(k >= 400, 5.0 * np.exp(-(k - 400) / tau), 0.0)
        assert dominant_samples(["T"], *runs(lag + 0.01 * rng.standard_normal(1000))) == []
    spiked = 0.05 * rng.standard_normal(1000)
    spiked[123] = 3.0  # 60 sigma
    (d,) = dominant_samples(["T"], *runs(spiked))
    assert (d.row, d.column, d.time_s) == (123, "T", 123.0)
    assert d.share == pytest.approx(9.0 / np.sum(spiked ** 2))
    few = 0.05 * rng.standard_normal(MIN_SAMPLES - 1)
    few[0] = 3.0
    assert dominant_samples(["T"], *runs(few)) == []  # too few samples to judge


def test_bursts_and_scattered_glitches_dominate_together_but_offsets_and_lags_do_not():
    """Glitches that no single sample makes decisive: a connector reading 3 K off for 5
    samples (each 18 % of the squared sum), five 1.5 K spikes over the run (each 14 %);
    and what must stay a model error: the same 3 K lasting 40 samples (an offset the
    model lacks), a 3 K missed lag of 3 samples, a sinusoidal misfit with spikes small
    beside it."""
    from thermojax.fitting._dominance import dominant_samples
    from thermojax.measurements._data import Experiment

    rng = np.random.default_rng(5)

    def found(residual):
        n = residual.size
        e = Experiment(np.arange(n, dtype=float), np.zeros((n, 1)),
                       (20.0 + residual)[:, None], name="r.csv")
        return sorted(d.row for d in dominant_samples(["T"], [e], [np.full((n, 1), 20.0)]))

    noise = lambda: 0.05 * rng.standard_normal(2000)  # noqa: E731
    burst = noise()
    burst[700:705] += 3.0
    assert found(burst) == [700, 701, 702, 703, 704]
    scattered = noise()
    rows = [150, 600, 1111, 1500, 1900]
    scattered[rows] += 1.5
    assert found(scattered) == rows
    assert found(noise()) == []
    lasting = noise()
    lasting[700:740] += 3.0
    assert found(lasting) == []
    k = np.arange(2000.0)
    assert found(noise() + np.where(k >= 700, 3.0 * np.exp(-(k - 700) / 3.0), 0.0)) == []
    wavy = noise() + 0.5 * np.sin(k / 50.0)
    wavy[rows] += 1.0
    assert found(wavy) == []  # glitches there, but not what decides the fit


# ---------------------------------------------------------------------------
# thermojax run CONFIG: the same checks, chosen by `options.outliers`


def _config(folder, outliers=None):
    option = "" if outliers is None else f'outliers = "{outliers}"'
    path = folder / "cfg.toml"
    path.write_text(f'name = "glitch"\nmodel = "rtd2h.toml"\nout = "results"\n'
                    f'data = ["a.csv", "b.csv"]\n\n[options]\n{option}\n')
    return path


def test_run_config_refuses_before_making_a_folder(capsys, tmp_path):
    folder = tmp_path / "data"
    _glitched_runs(folder, ("a.csv", glitch("T_core", 1e300)))
    rc, _, err = run(capsys, "run", _config(folder))
    assert_refused(rc, err, "a.csv", f"line {LINE}", "'T_core'", "--outliers drop")
    assert not (folder / "results").exists()
    rc, _, err = run(capsys, "run", _config(folder, "sometimes"))
    assert_refused(rc, err, "cfg.toml", "options.outliers", '"drop"')


def test_run_config_drops_what_it_is_told_to_and_records_it(capsys, tmp_path):
    import json

    folder = tmp_path / "data"
    _glitched_runs(folder, ("a.csv", lambda c: (glitch("T_core", 1e300)(c), _spike(c))))
    rc, out, err = run(capsys, "run", _config(folder, "drop"))
    assert rc == 0, err
    (result,) = (folder / "results").iterdir()
    report = json.loads((result / "report.json").read_text())
    cells = sorted((c["line"], c["column"]) for c in report["dropped_cells"])
    assert cells == [(LINE, "T_core"), (SPIKE_ROW + 2, "T_sheath")]
    assert report["converged"]
    for name, value in RTD2H_TRUTH.items():
        assert report["parameters"][name]["value"] == pytest.approx(value, rel=0.05), name
