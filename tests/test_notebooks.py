"""Every notebook in notebooks/ (Jupytext percent format) executes without error, in its
quick mode (``DIFFGYRO_NOTEBOOK_QUICK``: smaller batches, same steps), in the test
process (:mod:`notebook_runner`); each notebook's own asserts are part of the run. Notebook 02 runs in
tests/recipes/test_recipe_notebook.py, which also checks its output."""

from __future__ import annotations

from pathlib import Path

import pytest
from notebook_runner import run_notebook

NOTEBOOKS = sorted(p for p in (Path(__file__).parent.parent / "notebooks").glob("*.py")
                   if p.name != "02_published_methods.py")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, monkeypatch):
    monkeypatch.setenv("DIFFGYRO_NOTEBOOK_QUICK", "1")
    run_notebook(path, monkeypatch)
