"""The command line in a user's words: rates as typed (`1/1800`), built-in model names
when a name is not found, usage lines that show what is required, help that says when
to use each likelihood and what each command does with `--outliers`, and warnings
printed as the tool's own lines."""

from __future__ import annotations

import argparse
import json
from fractions import Fraction
from pathlib import Path

import pytest

import thermojax
from thermojax.cli import main
from thermojax.cli._arguments import rate_hz
from thermojax.cli._main import build_parser

from test_compensate_certainty import DETERMINED, HOUSE


def run(capsys, *argv):
    capsys.readouterr()
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:  # argparse's own refusals
        rc = e.code
    out, err = capsys.readouterr()
    return rc, out, err


def _sub(name):
    action = next(a for a in build_parser()._actions
                  if isinstance(a, argparse._SubParsersAction))
    return action.choices[name]


@pytest.mark.parametrize("typed", ["1/1800", "0.000555555555556", "5.55555555556e-4",
                                   "0.5/900"])
def test_export_records_the_period_meant(tmp_path, capsys, typed):
    """A half-hourly building observer: every way of typing one sample per 1800 s
    records dt_s = 1800 exactly (not 1799.99999999856)."""
    model = tmp_path / "house.toml"
    model.write_text(HOUSE.format(**DETERMINED))
    rc, out, err = run(capsys, "export", "--model", model, "--rate", typed, "--out",
                       tmp_path / "obs", "--quiet")
    assert rc == 0, err
    meta = json.loads((tmp_path / "obs" / "observer.json").read_text())
    assert meta["dt_s"] == 1800.0
    assert meta["rate_hz"] == pytest.approx(1 / 1800, rel=1e-15)
    assert "dt 1800 s" in out


@pytest.mark.parametrize("typed,period", [
    ("20", Fraction(1, 20)), ("3", Fraction(1, 3)), ("0.5", Fraction(2)),
    ("0.333333333", Fraction(3)),                       # nine digits of 1/3 Hz: 3 s
    ("0.0001234567", Fraction(10**10, 1234567)),        # no round period near: as typed
    ("2.5", Fraction(2, 5)),
])
def test_a_rate_is_read_as_typed_or_as_a_rounded_round_period(typed, period):
    assert 1 / rate_hz(typed) == period


@pytest.mark.parametrize("typed", ["0", "-20", "1/0", "abc", "nan", "inf", "1/x"])
def test_a_bad_rate_is_refused_by_name(capsys, typed, tmp_path):
    rc, _, err = run(capsys, "export", "--model", "rtd2", "--rate", typed, "--out",
                     tmp_path / "obs")
    assert rc == 2 and "--rate" in err and "Traceback" not in err


def test_an_unknown_model_name_lists_the_built_in_ones(capsys, tmp_path):
    names = sorted(p.stem for p in (Path(thermojax.__file__).parent / "data").glob("*.toml"))
    assert {"imu6", "rtd2"} <= set(names)
    rc, _, err = run(capsys, "simulate", "--model", "rtd3", "--profile", "shock", "--out",
                     tmp_path / "x.csv")
    assert rc == 2 and "Traceback" not in err
    assert "rtd3" in err and "--model" in err and "no built-in model" in err
    for name in names:
        assert name in err, name


def test_exports_usage_shows_its_required_flags():
    usage = _sub("export").format_usage()
    assert "thermojax export --model M --rate HZ --out DIR" in usage
    assert "thermojax export --check DIR" in usage
    for flag in ("--model", "--rate", "--out"):
        assert f"[{flag}" not in usage


def test_likelihood_help_says_when_to_use_each():
    for command in ("fit", "diagnose", "investigate"):
        text = " ".join(_sub(command).format_help().split())
        assert "output_error (default)" in text and "kalman:" in text, command
        assert "use it when" in text and "building" in text, command


def test_outliers_help_says_what_this_command_does():
    """Only `fit` refits without a sample that alone decided it."""
    helps = {c: " ".join(_sub(c).format_help().split())
             for c in ("fit", "diagnose", "investigate")}
    assert "decided the fit, and refits" in helps["fit"]
    for command in ("diagnose", "investigate"):
        assert "fit also drops" not in helps[command]
        assert "decided the fit" not in helps[command]
        assert "stop (the default" in helps[command]


def test_python_warnings_are_printed_as_the_tools_own(monkeypatch, capsys):
    import warnings

    import thermojax.cli._rate as rate_cli

    def warns(args):
        warnings.warn("the covariance is not positive definite", UserWarning)
        warnings.warn("a NumPy-style warning", RuntimeWarning)
        return 0

    monkeypatch.setattr(rate_cli, "cmd_rate", warns)
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # as a user's Python has it (the suite errors)
        rc, _, err = run(capsys, "rate", "--model", "rtd2", "--quiet")
    assert rc == 0
    assert err.splitlines() == ["warning: the covariance is not positive definite",
                                "warning: a NumPy-style warning"]


def test_rate_takes_fractions_too(tmp_path, capsys):
    model = tmp_path / "house.toml"
    model.write_text(HOUSE.format(**DETERMINED))
    rc, out, err = run(capsys, "rate", "--model", model, "--rates", "1/3600,1/1800,1/600",
                       "--quiet")
    assert rc == 0, err
    rows = [line.split()[0] for line in out.splitlines()[2:5]]
    assert [float(r) for r in rows] == pytest.approx([1 / 3600, 1 / 1800, 1 / 600], rel=1e-5)
    rc, _, err = run(capsys, "rate", "--model", model, "--rates", "1/0,1")
    assert rc == 2 and "--rates" in err and "1/1800" in err
