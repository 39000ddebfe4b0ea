"""Every notebook runs top to bottom without an error, through the public API only, and
is committed with its outputs stripped (by nbstripout)."""

import re
import subprocess
import sys
from pathlib import Path

import nbformat
import pytest
from nbclient import NotebookClient

NOTEBOOKS = sorted((Path(__file__).resolve().parents[1] / "notebooks").glob("*.ipynb"))


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_runs(path):
    nb = nbformat.read(path, as_version=4)
    NotebookClient(nb, timeout=900, kernel_name="python3",
                   resources={"metadata": {"path": str(path.parent)}}).execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_committed_stripped(path):
    """`nbstripout --verify` fails when it would change the file (outputs or counts)."""
    proc = subprocess.run([sys.executable, "-m", "nbstripout", "--verify", str(path)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, f"run `nbstripout {path}` before committing: {proc.stdout}"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_uses_public_api_only(path):
    nb = nbformat.read(path, as_version=4)
    code = "\n".join(c.source for c in nb.cells if c.cell_type == "code")
    private = re.findall(r"thermojax(?:\.\w+)*\._\w+", code)
    assert private == [], f"{path.name} imports private modules {private}"
