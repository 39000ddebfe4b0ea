"""The command line every study in experiments/ shares: `--out`, `--force`, `--quick`,
`--seed`, a fresh results folder, and its `results.json`."""

from __future__ import annotations

import argparse
import json
import sys
from datetime import datetime, timezone
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def study_parser(name: str, doc: str, quick_help: str) -> argparse.ArgumentParser:
    """The shared arguments of study `name` (its module docstring `doc` describes it)."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=None,
                        help=f"results folder (default: results/{name}-<UTC time>/)")
    parser.add_argument("--force", action="store_true",
                        help="write into an existing results folder (files of the same name "
                             "are replaced)")
    parser.add_argument("--quick", action="store_true", help=quick_help)
    parser.add_argument("--seed", type=int, default=0)
    return parser


def results_folder(name: str, out: Path | None, force: bool) -> Path:
    """`out`, or `results/<name>-<UTC time>/`, created; an existing folder without
    `force` ends the study with exit 2 and a message."""
    folder = out
    if folder is None:
        stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
        folder = ROOT / "results" / f"{name}-{stamp}"
    if folder.exists() and not force:
        print(f"error: {folder} exists; choose another --out or pass --force to replace it.",
              file=sys.stderr)
        raise SystemExit(2)
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def write_results(folder: Path, res: dict, text: str, table_name: str) -> None:
    """The Markdown table `text` as `table_name` and `res` (keys starting with `_`, plot
    data, left out) as `results.json`; the table is printed too."""
    (folder / table_name).write_text(text)
    public = {k: v for k, v in res.items() if not k.startswith("_")}
    (folder / "results.json").write_text(json.dumps(public, indent=2, default=float))
    print(text)
    print(f"results in {folder}")
