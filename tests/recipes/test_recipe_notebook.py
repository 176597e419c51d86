"""notebooks/02_published_methods.py runs top to bottom (Jupytext percent format)."""

from __future__ import annotations

from pathlib import Path

from notebook_runner import run_notebook

NOTEBOOK = Path(__file__).resolve().parents[2] / "notebooks" / "02_published_methods.py"


def test_published_methods_notebook_executes(monkeypatch):
    text = run_notebook(NOTEBOOK, monkeypatch)
    # every recipe ran and the side-by-side table was printed
    for name in ("binned-thermal", "static-kalman", "fog-one-run", "attitude-reference"):
        assert name in text
    assert "38 static poses" in text and "max |Δ| vs imucal" in text
