"""The README's Python snippet runs as written, on the files `thermojax demo` writes."""

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_readme_snippet_runs(tmp_path, capsys):
    from thermojax.cli import main
    from thermojax.cli._demo import demo_runs
    from thermojax.measurements import write_telemetry

    code = re.search(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S).group(1)
    # what `thermojax demo` writes: the IMU calibration run and the two chamber runs
    assert main(["demo", "--quick", "--out", str(tmp_path / "thermojax_demo")]) == 0
    for i, (ts, columns) in enumerate(demo_runs()):
        write_telemetry(tmp_path / "thermojax_demo" / f"chamber_run{i}.csv", ts, columns)
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    cwd = os.getcwd()
    os.chdir(tmp_path)
    try:
        exec(compile(code, "README.md", "exec"), {})
    finally:
        os.chdir(cwd)
    out = capsys.readouterr().out
    assert "T_housing" in out and "'value'" in out
