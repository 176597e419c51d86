"""The project stands alone: its code, docs and notebooks name the published methods by their
recipe names and point at nothing outside the repository."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: A file outside the repository, or a method code ("S0" … "S4") the repository never defines.
OUTSIDE = re.compile(r"DESIGN\.md|SEEDS\.md|\.\./shared|(?<![\w.])/?shared/|\bS[0-4]\b")


def _texts():
    """(where, text) for every docstring of the package and every docs page, notebook, README."""
    for path in sorted((ROOT / "src" / "diffgyro").rglob("*.py")):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef):
                doc = ast.get_docstring(node, clean=False)
                if doc:
                    yield f"{path.relative_to(ROOT)}:{getattr(node, 'lineno', 1)}", doc
        # comments and strings too: an output line or a comment is read as well
        yield str(path.relative_to(ROOT)), path.read_text(encoding="utf-8")
    for pattern in ("docs/*.md", "notebooks/*.py", "README.md", "mkdocs.yml"):
        for path in sorted(ROOT.glob(pattern)):
            yield str(path.relative_to(ROOT)), path.read_text(encoding="utf-8")


def test_no_pointer_outside_the_repository():
    hits = [f"{where}: {m.group(0)!r} in {text[max(0, m.start() - 40):m.end() + 20]!r}"
            for where, text in _texts() for m in OUTSIDE.finditer(text)]
    assert not hits, "\n".join(hits)


def test_the_pattern_catches_what_it_should():
    for bad in ("see DESIGN.md §4", "(SEEDS.md)", "../shared/data", "the S2 profile", "S0, CN1"):
        assert OUTSIDE.search(bad), bad
    for good in ("s1_offset_filter", "fog-one-run", "rate_table_s2", "S20", "docs/formats.md"):
        assert not OUTSIDE.search(good), good
