"""A fit too large for the memory at hand is refused before any work, naming the size
and what to do; a long one says so first (thermojax.fitting._size)."""

from __future__ import annotations

import json

import pytest

from thermojax.cli import main
from thermojax.fitting import _size


def _chain(path, n):
    lines = ['name = "chain"']
    for i in range(n):
        lines += ["[[nodes]]", f'name = "n{i}"', f"capacitance = {1.0 + 0.01 * i}"]
    for i in range(n - 1):
        lines += ["[[links]]", f'between = ["n{i}", "n{i + 1}"]', "conductance = 0.5"]
    lines += ["[[boundaries]]", 'node = "n0"', 'input = "T_amb"', "conductance = 0.3",
              "[[sensors]]", f'node = "n{n - 1}"', 'column = "T_end"', "noise = 0.01"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_cost_grows_as_measured():
    # the figures the constants were fitted to (benchmarks/README.md, "Large networks")
    assert _size.fit_cost(80, 161).bytes == pytest.approx(1.19e9, rel=0.05)
    assert _size.fit_cost(40, 81).bytes == pytest.approx(0.72e9, rel=0.1)
    assert _size.fit_cost(80, 161).seconds == pytest.approx(381.0)
    assert _size.fit_cost(200, 401).bytes > 8.9e9   # where the unguarded fit was seen


def test_refused_before_work_when_memory_is_short(tmp_path, monkeypatch, capsys):
    model = _chain(tmp_path / "chain.toml", 30)
    assert main(["simulate", "--model", str(model), "--profile", "ramp5", "--dt", "60",
                 "--noise", "--out", str(tmp_path / "d.csv"), "--quiet"]) == 0
    # 29 conductances and the boundary's, 30 capacitances, and 30 starts estimated from
    # the run (no node of the file has `initial`)
    need = _size.fit_cost(30, 90).bytes
    monkeypatch.setattr(_size, "available_memory", lambda: need)   # 80 % is too little
    assert main(["fit", "--model", str(model), "--data", str(tmp_path / "d.csv"),
                 "--out", str(tmp_path / "f"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "90 free parameters of a 30-state network" in err and "fixed = true" in err
    assert not (tmp_path / "f").exists()


def test_small_fit_passes_the_guard():
    cost = _size.check_fit_size(6, 12, available=24e9)
    assert cost.bytes < 1e9 and cost.seconds < 1.0


def test_a_long_log_costs_its_jacobian_as_measured():
    # the six-node IMU's output-error fit (3 sensors, 22 free parameters), peak resident
    # memory measured on the development machine (the module docstring): 1.85 GB at
    # 10⁶ samples, 3.22 GB at 2·10⁶
    assert _size.fit_cost(6, 22, 3 * 10**6).bytes == pytest.approx(1.85e9, rel=0.1)
    assert _size.fit_cost(6, 22, 6 * 10**6).bytes == pytest.approx(3.22e9, rel=0.1)
    assert _size.fit_cost(6, 22).jacobian_bytes == 0.0


def test_a_log_too_long_for_the_memory_is_refused_naming_its_readings(tmp_path, monkeypatch,
                                                                      capsys):
    model = _chain(tmp_path / "chain.toml", 3)
    n = 20_000
    rows = ["time_s,T_amb,T_end"] + [f"{i:.1f},25.0,25.0" for i in range(n)]
    (tmp_path / "long.csv").write_text("\n".join(rows) + "\n")
    # 3 capacitances, 2 conductances, the boundary's and 3 starts on 20,000 readings:
    # the Jacobian's 3.7 MB outweigh the network's sensitivities
    need = _size.fit_cost(3, 9, n)
    assert need.jacobian_bytes > need.bytes - _size.BASE_BYTES - need.jacobian_bytes
    monkeypatch.setattr(_size, "available_memory", lambda: need.bytes)
    # a Kalman fit holds the Jacobian: refused before the work
    assert main(["fit", "--model", str(model), "--data", str(tmp_path / "long.csv"),
                 "--likelihood", "kalman", "--out", str(tmp_path / "f"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "20,000 sensor readings" in err and "every k-th row" in err
    assert "chain.toml" in err
    assert not (tmp_path / "f").exists()
    # output error on a linear model sums its normal equations over stretches instead
    assert main(["fit", "--model", str(model), "--data", str(tmp_path / "long.csv"),
                 "--out", str(tmp_path / "oe"), "--quiet"]) == 0
    report = json.loads((tmp_path / "oe" / "report.json").read_text())
    assert report["method"].startswith("Gauss-Newton on normal equations")
