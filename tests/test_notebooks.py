"""Every notebook in notebooks/ (Jupytext percent format) executes without error, in its
quick mode (``DIFFGYRO_NOTEBOOK_QUICK``: smaller batches, same steps); each notebook's own
asserts are part of the run. Most run in the test process (:mod:`notebook_runner`); one runs
the usual way, ``jupytext --to ipynb`` then ``jupyter execute`` in a kernel, so that the dev
extras are checked to hold what that needs. Notebook 02 runs in
tests/recipes/test_recipe_notebook.py, which also checks its output. Each executed notebook
is kept (``notebook_runner.outputs_dir()``) for the documentation site."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from notebook_runner import ROOT, keep, run_notebook

#: Run under Jupyter (a kernel) instead of in the test process.
KERNEL_RUN = "04_bias_dynamics.py"
NOTEBOOKS = sorted(p for p in (ROOT / "notebooks").glob("*.py")
                   if p.name not in ("02_published_methods.py", KERNEL_RUN))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.name for p in NOTEBOOKS])
def test_notebook_executes(path, monkeypatch):
    monkeypatch.setenv("DIFFGYRO_NOTEBOOK_QUICK", "1")
    run_notebook(path, monkeypatch)


def test_notebook_runs_under_jupyter(tmp_path, monkeypatch):
    """``jupytext --to ipynb NOTEBOOK.py`` and ``jupyter execute --inplace NOTEBOOK.ipynb``."""
    import nbformat

    source = ROOT / "notebooks" / KERNEL_RUN
    ipynb = tmp_path / source.with_suffix(".ipynb").name
    env = {**os.environ, "DIFFGYRO_NOTEBOOK_QUICK": "1",
           "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), os.environ.get("PYTHONPATH", "")])}
    subprocess.run([sys.executable, "-m", "jupytext", "--to", "ipynb", "--output", str(ipynb),
                    str(source)], check=True, env=env, capture_output=True)
    run = subprocess.run([sys.executable, "-m", "jupyter", "execute", "--inplace", str(ipynb)],
                         env=env, capture_output=True, text=True, cwd=source.parent)
    assert run.returncode == 0, run.stderr[-3000:]
    nb = nbformat.read(ipynb, as_version=4)
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    assert any("image/png" in o.get("data", {}) for o in outputs)  # its figures came back
    assert any(o.output_type == "stream" and "learned" in o.text for o in outputs)
    monkeypatch.setenv("DIFFGYRO_NOTEBOOK_QUICK", "1")
    keep(nb, source)
