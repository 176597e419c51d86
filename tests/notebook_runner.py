"""Run a Jupytext percent-format notebook inside the test process.

Its code cells execute top to bottom in one namespace, from the notebook's folder,
as a kernel would run them, but without a kernel: the JAX import and the
compiled programs are shared with the rest of the worker. Figures go to the Agg
backend and, as with Jupyter's inline backend, are captured at ``plt.show()`` and
at the end of each cell; what the cells print is returned. Effect registrations a
notebook makes are undone afterwards so later tests see the built-in vocabulary.

The executed notebook (each cell's printed text and figures) is kept as
``<OUTPUTS>/<stem>.ipynb`` (:func:`outputs_dir`) with the hash of its source, for the
documentation site to render (docs/hooks.py).
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import io
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def outputs_dir() -> Path:
    """Where executed notebooks are kept: ``DIFFGYRO_NOTEBOOK_OUTPUTS`` or .notebook-outputs/."""
    return Path(os.environ.get("DIFFGYRO_NOTEBOOK_OUTPUTS") or ROOT / ".notebook-outputs")


def source_hash(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def keep(nb, path: Path) -> None:
    """Write the executed notebook ``nb`` of ``path`` for the docs (atomically)."""
    import nbformat

    nb.metadata["diffgyro"] = {"source": Path(path).name, "source_sha256": source_hash(path),
                               "quick": bool(os.environ.get("DIFFGYRO_NOTEBOOK_QUICK"))}
    out = outputs_dir()
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{Path(path).stem}.{os.getpid()}.tmp"
    nbformat.write(nb, tmp)
    tmp.replace(out / f"{Path(path).stem}.ipynb")


def run_notebook(path: Path, monkeypatch) -> str:
    """Execute every code cell of ``path``; an exception names the cell. Returns stdout."""
    import jupytext
    import matplotlib
    import nbformat

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffgyro.internal import REGISTRY

    plt.close("all")  # a figure an earlier test left open is not this notebook's output

    registered = dict(REGISTRY)
    monkeypatch.chdir(path.parent)
    figures: list[dict] = []

    def show(*args, **kwargs):  # as the inline backend: each open figure becomes an output
        for num in plt.get_fignums():
            png = io.BytesIO()
            plt.figure(num).savefig(png, format="png", dpi=80, bbox_inches="tight")
            figures.append(nbformat.v4.new_output(
                "display_data", data={"image/png": base64.b64encode(png.getvalue()).decode()}))
        plt.close("all")

    monkeypatch.setattr(plt, "show", show)
    namespace = {"__name__": "__main__"}
    out = io.StringIO()
    nb = jupytext.read(path)
    try:
        for i, cell in enumerate(nb.cells):
            if cell.cell_type != "code":
                continue
            text = io.StringIO()
            figures.clear()
            with contextlib.redirect_stdout(text):
                exec(compile(cell.source, f"{path.name}, cell {i}", "exec"), namespace)
            show()
            out.write(text.getvalue())
            cell.outputs = ([nbformat.v4.new_output("stream", name="stdout", text=text.getvalue())]
                            if text.getvalue() else []) + list(figures)
        keep(nb, path)
    finally:
        plt.close("all")
        REGISTRY.clear()
        REGISTRY.update(registered)
    return out.getvalue()
