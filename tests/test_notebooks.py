"""Every notebook in notebooks/ (Jupytext percent format) executes without error, in its
quick mode (``DIFFGYRO_NOTEBOOK_QUICK``: smaller batches, same steps). Notebook 02 runs in
tests/recipes/test_recipe_notebook.py, which also checks its output."""

from __future__ import annotations

from pathlib import Path

import pytest

NOTEBOOKS = sorted(p for p in (Path(__file__).parent.parent / "notebooks").glob("*.py")
                   if p.name != "02_published_methods.py")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, tmp_path, monkeypatch):
    monkeypatch.setenv("DIFFGYRO_NOTEBOOK_QUICK", "1")
    jupytext = pytest.importorskip("jupytext")
    nbclient = pytest.importorskip("nbclient")
    nb = jupytext.read(path)
    client = nbclient.NotebookClient(
        nb, timeout=600, kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute()
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", [])
              if o.get("output_type") == "error"]
    assert not errors, errors
