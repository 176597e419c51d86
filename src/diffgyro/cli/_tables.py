"""The command line's rich tables: a number is never split across lines.

A numeric column is ``no_wrap`` (rich never breaks its cells, and narrows the text
columns first when the table is wider than the terminal), its heading wrapped
beforehand to the width of its widest number; a text column folds (a long device name
wraps whole, never cut to "name/…"). Used by ``fit``, ``diagnose`` and ``allan``.
This module starts with ``_`` so it is not imported as a command.
"""

from __future__ import annotations

import os
import sys
import textwrap

from rich.console import Console
from rich.table import Table
from rich.text import Text

#: The kinds of column: a number (or a number with its unit) stays on one line; text folds.
NUMBER, TEXT = "number", "text"


def _width(cell: str) -> int:
    return Text.from_markup(cell).cell_len


def _heading(text: str, width: int) -> str:
    """``text`` on lines no wider than ``width`` (or its longest word), so that the
    heading does not widen a column of numbers."""
    longest = max((len(w) for w in text.split()), default=1)
    return "\n".join(textwrap.wrap(text, max(width, longest))) or text


def table(title: str, columns: list[tuple[str, str]], rows: list[list[str]], width: int, *,
          justify: dict[str, str] | None = None) -> Table:
    """A table of ``rows`` under ``columns`` (heading, :data:`NUMBER` or :data:`TEXT`) for a
    console ``width`` columns wide: numbers right-aligned and text left-aligned unless
    ``justify`` names the heading. Headings stay whole where the table fits; else a
    numeric column's heading wraps to the width of its numbers."""
    justify = justify or {}
    widest = [max((_width(r[k]) for r in rows), default=1) for k in range(len(columns))]
    natural = sum(max(w, _width(head)) + 3 for w, (head, _) in zip(widest, columns)) + 1
    out = Table(title=title)
    for k, (head, kind) in enumerate(columns):
        align = justify.get(head, "right" if kind == NUMBER else "left")
        if kind == NUMBER:
            out.add_column(head if natural <= width else _heading(head, widest[k]),
                           justify=align, no_wrap=True)
        else:
            out.add_column(head, justify=align, overflow="fold")
    for r in rows:
        out.add_row(*r)
    return out


def fit_columns(columns: list[tuple[str, str]], rows: list[list[str]], width: int,
                optional: tuple[str, ...] = ()) -> tuple[list, list, list[str]]:
    """The columns and rows to show ``width`` columns wide: a text column empty in every
    row is left out, then the ``optional`` headings in their order while the table is
    wider than ``width`` (each a column whose content the output gives elsewhere, so a
    narrow terminal folds no word of the others). Returns the columns, the rows and the
    headings of the optional columns left out."""
    def natural(keep):
        return sum(max(max((_width(r[k]) for r in rows), default=1), _width(columns[k][0])) + 3
                   for k in keep) + 1

    keep = [k for k, (_, kind) in enumerate(columns)
            if kind != TEXT or not rows or any(_width(r[k]) for r in rows)]
    dropped = []
    for head in optional:
        if natural(keep) <= width:
            break
        k = next((k for k in keep if columns[k][0] == head), None)
        if k is not None:
            keep.remove(k)
            dropped.append(head)
    return [columns[k] for k in keep], [[r[k] for k in keep] for r in rows], dropped


def console(width: int) -> Console:
    """A console as wide as the terminal (or ``COLUMNS``); ``width`` columns when stdout
    is not a terminal and ``COLUMNS`` is not set (pipes, logs, tests)."""
    if sys.stdout.isatty() or os.environ.get("COLUMNS", "").isdigit():
        return Console()
    return Console(width=width)
