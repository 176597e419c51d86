"""Run a Jupytext percent-format notebook inside the test process.

Its code cells execute top to bottom in one namespace, from the notebook's folder,
as a kernel would run them, but without a kernel: the JAX import and the
compiled programs are shared with the rest of the worker. Figures go to the Agg
backend; what the cells print is returned. Effect registrations a notebook makes
are undone afterwards so later tests see the built-in vocabulary.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path


def run_notebook(path: Path, monkeypatch) -> str:
    """Execute every code cell of ``path``; an exception names the cell. Returns stdout."""
    import jupytext
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffgyro.effects import base

    registered = dict(base._REGISTRY)
    monkeypatch.chdir(path.parent)
    monkeypatch.setattr(plt, "show", lambda *a, **k: None)
    namespace = {"__name__": "__main__"}
    out = io.StringIO()
    try:
        with contextlib.redirect_stdout(out):
            for i, cell in enumerate(jupytext.read(path).cells):
                if cell.cell_type == "code":
                    exec(compile(cell.source, f"{path.name}, cell {i}", "exec"), namespace)
    finally:
        plt.close("all")
        base._REGISTRY.clear()
        base._REGISTRY.update(registered)
    return out.getvalue()
