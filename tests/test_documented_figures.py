"""Figures the docs state are the figures the code prints (issue 65 item 3): each one is
checked here against the command or the table that produces it, so a change that moves
it fails until the docs move with it."""

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _squash(text: str) -> str:
    """`text` with every run of white space one space (the docs wrap lines anywhere)."""
    return re.sub(r"\s+", " ", text)


@pytest.fixture(scope="module")
def imu6_rate():
    """`thermojax rate` on the built-in imu6 with the documented anti-alias filter."""
    out = subprocess.run(
        [sys.executable, "-m", "thermojax", "rate", "--model", "imu6", "--quiet",
         "--anti-alias", "2", "5", "--no-cache"],
        capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert out.returncode == 0, out.stderr
    text = out.stdout
    enough = re.search(r"enough: ([0-9.]+) Hz.*?\(([0-9.]+)× the bandwidth.*?asks "
                       r"([0-9.]+)–([0-9.]+) Hz", text)
    bandwidth = re.search(r"closed-loop bandwidth ([0-9.]+) Hz", text)
    delay = re.search(r"group delay ([0-9.]+) s;.*?up to ([0-9.]+) °C", text)
    assert enough and bandwidth and delay, text
    return {"enough_hz": enough.group(1), "ratio": enough.group(2),
            "rule": (enough.group(3), enough.group(4)), "bandwidth_hz": bandwidth.group(1),
            "delay_ms": round(float(delay.group(1)) * 1e3),
            "ramp_mK": round(float(delay.group(2)) * 1e3, 2)}


def test_cli_page_states_imu6s_rate_as_the_command_prints_it(imu6_rate):
    r = imu6_rate
    text = _squash((ROOT / "docs" / "cli.md").read_text())
    assert (f"imu6: enough at {r['enough_hz']} Hz ({r['ratio']}× its "
            f"{r['bandwidth_hz']} Hz bandwidth; the 8–15× rule asks "
            f"{float(r['rule'][0]):g}–{float(r['rule'][1]):g} Hz)") in text
    assert f"delays {r['delay_ms']} ms and adds {r['ramp_mK']:g} mK" in text


def test_benchmarks_table_states_imu6s_rate_as_the_command_prints_it(imu6_rate):
    r = imu6_rate
    text = (ROOT / "benchmarks" / "README.md").read_text()
    row = next(line for line in text.splitlines() if line.startswith("| imu6 (3 sensors)"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == f"{r['bandwidth_hz']} Hz", row
    assert cells[2] == f"{r['enough_hz']} Hz ({r['ratio']}× the bandwidth)", row


def test_extensions_page_counts_the_fixed_point_formats():
    from thermojax.reference import FORMATS

    words = {2: "two", 3: "three", 4: "four", 5: "five", 6: "six"}
    text = _squash((ROOT / "docs" / "extensions.md").read_text())
    counts = re.findall(r"all (\w+) formats", text)
    assert counts, "extensions.md no longer says how many formats the fixed point has"
    assert set(counts) == {words[len(FORMATS)]}, counts


def test_observer_page_contents_list_every_section():
    text = (ROOT / "docs" / "observer.md").read_text()
    headings = re.findall(r"^## (\d+)\. (.+)$", text, flags=re.M)
    contents = re.findall(r"^(\d+)\. \[(.+?)\]\(#", text, flags=re.M)
    assert contents == headings


def test_experiments_out_is_the_results_folder_itself(tmp_path):
    sys.path.insert(0, str(ROOT / "experiments"))
    try:
        from _study_cli import results_folder
    finally:
        sys.path.remove(str(ROOT / "experiments"))
    assert results_folder("x", tmp_path / "mine", force=False) == tmp_path / "mine"
    text = _squash((ROOT / "experiments" / "README.md").read_text())
    assert "`--out DIR` names that folder itself" in text
    assert "PARENT" not in text
    for study in (ROOT / "experiments").glob("*.py"):
        assert "--out PARENT" not in study.read_text(), study.name


def test_benchmarks_page_is_a_reference():
    """benchmarks/README.md: under 600 lines, every script a section with its command and
    one current table, dated (the diary it replaced is in the history)."""
    text = (ROOT / "benchmarks" / "README.md").read_text()
    assert len(text.splitlines()) < 600
    sections = re.split(r"^## ", text, flags=re.M)[1:]
    scripts = sorted(p.name for p in (ROOT / "benchmarks").glob("*.py")
                     if not p.name.startswith("_"))
    for script in scripts:
        mine = [s for s in sections if f"`{script}`" in s.splitlines()[0]]
        assert len(mine) == 1, f"{script}: no section of its own in benchmarks/README.md"
        body = mine[0]
        assert f"python benchmarks/{script}" in body, script
        tables = re.findall(r"^\|[-:| ]+\|$", body, flags=re.M)
        assert len(tables) == 1, f"{script}: {len(tables)} tables, expected one current one"
        assert re.search(r"20\d\d-\d\d-\d\d", body), f"{script}: its table is not dated"
        assert "Tried, not kept" in body, script
