"""A small, plain CSV file read without pandas: the common case, in a process that then
need not import pandas and pyarrow (0.2-0.35 s of a command's start).

"Plain" is narrow on purpose: UTF-8 text, uncompressed, at most :data:`MAX_BYTES`, no
quote character, no NUL, no blank line, no lone carriage return, and every line with
as many fields as the header. The numeric columns read hold only plain decimal numbers
(digits, point, sign, exponent): each cell is converted as Python's ``float`` converts
it (numpy's conversion of a list of texts, in one call), which rounds correctly, as
pandas' C parser does for such cells. Anything else (a missing
cell, an NA marker, a quoted field, a row of the wrong length, text in a numeric column)
makes :func:`read_plain` return None, and the caller reads the file with pandas, whose
messages name what is wrong; so the errors are the same either way.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

#: Larger files are read by pandas (its C parser is faster past a few megabytes).
MAX_BYTES = 8 << 20
#: Text of plain decimal numbers only (digits, point, sign, exponent).
_NUMBERS_ONLY = re.compile(r"[0-9.eE+\-]*")


class PlainTable:
    """Columns by header name (raw, as the file writes them) and the count of rows: what
    the loader reads of a frame (``len(table)``, ``table[name]``)."""

    def __init__(self, columns: dict[str, np.ndarray], n_rows: int):
        self._columns, self._n = columns, n_rows

    def __len__(self) -> int:
        return self._n

    def __getitem__(self, name: str) -> np.ndarray:
        return self._columns[name]


def split_plain(path: Path, sep: str) -> list[list[str]] | None:
    """The file's lines split at ``sep`` (the header first), or None if it is not plain."""
    try:
        if path.stat().st_size > MAX_BYTES:
            return None
        text = path.read_bytes().decode("utf-8-sig")
    except (OSError, UnicodeDecodeError):
        return None
    if '"' in text or "\x00" in text:
        return None
    if "\r" in text:
        text = text.replace("\r\n", "\n")
        if "\r" in text:
            return None
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    if not lines or not all(lines):
        return None
    rows = [line.split(sep) for line in lines]
    width = len(rows[0])
    if any(len(r) != width for r in rows):
        return None
    return rows


def read_plain(rows: list[list[str]], wanted: list[str], text_cols: set[str]) -> PlainTable | None:
    """The columns ``wanted`` (header names, stripped; unique) of the split file: those in
    ``text_cols`` as text, the others as float64; None when a numeric cell is not a plain
    number."""
    index = {name.strip(): k for k, name in enumerate(rows[0])}
    data = rows[1:]
    columns: dict[str, np.ndarray] = {}
    for name in wanted:
        cells = [r[index[name]] for r in data]
        if name in text_cols:
            columns[name] = np.asarray(cells, dtype=object)
            continue
        if _NUMBERS_ONLY.fullmatch("".join(cells)) is None:
            return None
        try:  # numpy's conversion of each text is Python's float (correctly rounded)
            values = np.array(cells, dtype=np.float64)
        except ValueError:  # an empty cell, '1e', '--1' ...
            return None
        columns[name] = values
    return PlainTable(columns, len(data))
