"""What a user reads states each rule in its own terms: no pointers to documents the user
cannot read ("the seed's rule", "the second seed", "see the observer issue", "session
40"). Searched: the help of every command, docs/ and README.md (lines the shared
contract fixes verbatim excepted), every message string in the package's source, the
screen output of `rate`, and the reports a small `fit` and a tiny `investigate` write.

A random-number seed (`simulate --seed`, a study's `seed = 0`) is a user's word and
stays: only the phrases that point at a document are internal.
"""

from __future__ import annotations

import argparse
import ast
import re
from pathlib import Path

import pytest

from thermojax.cli import main
from thermojax.cli._main import build_parser

ROOT = Path(__file__).resolve().parents[1]
SHARED_SPEC = ROOT.parent / "shared" / "spec" / "formats.md"

INTERNAL = re.compile(
    r"\bseed's\b|\bseeds'|\b(?:the|a|first|second|third|our)\s+seeds?\b(?!\s*=)"
    r"|\bissues?\b|\bsessions?\b", re.IGNORECASE)


def internal_words(text: str) -> list[str]:
    """Each line of `text` holding an internal word."""
    return [line.strip() for line in text.splitlines() if INTERNAL.search(line)]


@pytest.mark.parametrize("text", [
    "pole placement by the seed's rule",
    "inside the second seed's 8–15× rule",
    "header (see the observer issue).",
    "fast (58-69 ms a call; benchmarks/README.md, session 40)",
    "as the seed asks", "Issue 14: a unit-variance study",
])
def test_the_search_finds_internal_words(text):
    assert internal_words(text) == [text]


@pytest.mark.parametrize("text", [
    "--seed N: noise seed (default 0)", "seed = 0  # unit u's numbers depend on (seed, u)",
    "the same seed gives the same units", "reseeded", "tissue", "sessional",
])
def test_a_random_seed_is_a_users_word(text):
    assert internal_words(text) == []


def _parsers(parser, name="thermojax"):
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub_name, sub in action.choices.items():
                yield from _parsers(sub, f"{name} {sub_name}")


def test_help_of_every_command():
    found = {name: internal_words(p.format_help()) for name, p in _parsers(build_parser())}
    assert len(found) > 10
    assert {n: w for n, w in found.items() if w} == {}


def test_every_option_has_help_text():
    bare = [(name, a.option_strings or a.dest) for name, p in _parsers(build_parser())
            for a in p._actions if not a.help]
    assert bare == []


def test_docs_and_readme():
    spec = (set(SHARED_SPEC.read_text().splitlines()) if SHARED_SPEC.is_file() else None)
    found = {}
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        lines = page.read_text().splitlines()
        if page.name == "formats.md" and page.parent.name == "docs":
            if spec is None:
                continue  # without the contract beside us its verbatim lines are unknown
            lines = [line for line in lines if line not in spec]
        words = internal_words("\n".join(lines))
        if words:
            found[str(page.relative_to(ROOT))] = words
    assert found == {}


def _docstrings(tree) -> set[int]:
    """ids of the string constants that are docstrings (read by developers, not shown)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
                out.add(id(body[0].value))
    return out


def test_message_strings_in_the_source():
    """Every string literal of the package (messages, warnings, help, report text; an
    f-string's literal parts included) except docstrings."""
    found = {}
    for path in sorted((ROOT / "thermojax").rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        skip = _docstrings(tree)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Constant) and isinstance(node.value, str)
                    and id(node) not in skip):
                words = internal_words(node.value)
                if words:
                    found.setdefault(f"{path.relative_to(ROOT)}:{node.lineno}", words)
    assert found == {}


def test_rate_screen_output(capsys):
    assert main(["rate", "--model", "rtd2", "--rates", "1,10", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "rule of thumb" in out
    assert internal_words(out) == []


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    """A small `fit` (helpers' rtd2h run, simulated by NumPy) and a tiny `investigate`
    (no effect added: step 0's diagnosis only) on the same run: their report.md."""
    from test_fit_cli import write_runs

    folder = tmp_path_factory.mktemp("words")
    write_runs(folder)
    mp = pytest.MonkeyPatch()
    mp.chdir(folder)
    try:
        assert main(["fit", "--model", "rtd2h.toml", "--data", "a.csv", "--out", "fit",
                     "--quiet"]) == 0
        assert main(["investigate", "--model", "rtd2h.toml", "--data", "a.csv", "--out",
                     "inv", "--max-steps", "0", "--no-network", "--quiet"]) == 0
    finally:
        mp.undo()
    return {"fit": (folder / "fit" / "report.md").read_text(),
            "investigate": (folder / "inv" / "report.md").read_text()}


@pytest.mark.parametrize("command", ["fit", "investigate"])
def test_generated_reports(reports, command):
    text = reports[command]
    assert len(text) > 500  # a report was written
    assert internal_words(text) == []
