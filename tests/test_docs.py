"""docs/ ships with the repository and stays in step with the code and the contract."""

import argparse
from pathlib import Path

import pytest

from thermojax.cli._main import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SHARED_SPEC = ROOT.parent / "shared" / "spec" / "formats.md"


def subcommands():
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return action.choices


def test_formats_page_keeps_every_line_of_the_contract():
    """docs/formats.md may only grow: every line of the shared contract is in it, in order.
    The contract lives beside the repository (CI checks out `shared/` next to it)."""
    if not SHARED_SPEC.is_file():
        pytest.skip(f"the shared contract is not beside this checkout ({SHARED_SPEC})")
    ours = (DOCS / "formats.md").read_text().splitlines()
    it = iter(ours)
    missing = [line for line in SHARED_SPEC.read_text().splitlines()
               if not any(line == mine for mine in it)]
    assert missing == []


def test_formats_page_names_every_section():
    text = (DOCS / "formats.md").read_text()
    for heading in ("## 1. Telemetry: CSV", "## 2. Model: TOML", "## 3. Effects",
                    "## 4. Bias channels", "## 5. Command line"):
        assert heading in text


def test_every_command_and_flag_is_documented():
    text = (DOCS / "cli.md").read_text()
    for name, sub in subcommands().items():
        assert f"thermojax {name}" in text, name
        for action in sub._actions:
            for flag in action.option_strings:
                if flag.startswith("--") and flag != "--help":
                    assert flag in text, (name, flag)


def test_every_effect_kind_is_in_the_vocabulary_page():
    from thermojax.model.effects import KINDS

    text = (DOCS / "formats.md").read_text()
    for kind in KINDS:
        assert f"`{kind}`" in text, kind


def test_docs_index_links_resolve():
    import re

    for page in DOCS.glob("*.md"):
        for target in re.findall(r"\]\(([^)#]+\.md)\)", page.read_text()):
            assert (DOCS / target).is_file(), (page.name, target)
