"""Mapping file columns to the standard schema (``--columns``)."""

from __future__ import annotations

import re
from collections.abc import Mapping

from ..data import STANDARD_COLUMNS
from ..errors import DataError


def parse_columns(text: str | None) -> dict[str, str]:
    """Parse the command-line mapping ``"gx=gyr_x,gy=gyr_y"`` (standard=name in file).

    A left-hand name that is not a standard column renames an extra column:
    ``vdd=Supply V`` keeps the file's ``Supply V`` as the extra column ``vdd``
    (letters, digits, ``_`` and ``.``, starting with a letter or ``_``; the
    name an ``aux(vdd)`` term uses).

    **Arguments:**

    - ``text``: the mapping as the command line gives it (None: no mapping).
    """
    out: dict[str, str] = {}
    if text is None or not text.strip():
        return out
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        if "=" not in item:
            raise DataError(f"column mapping item {item!r} has no '='",
                            hint="write standard=name_in_file, e.g. gx=gyr_x,gy=gyr_y")
        std, _, name = (s.strip() for s in item.partition("="))
        _check_mapping_pair(std, name)
        if std in out:
            raise DataError(f"column mapping gives {std} twice")
        out[std] = name
    return out


#: Names an extra column may take (the column argument of an ``aux(NAME)`` term).
AUX_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_.]*")


def _check_mapping_pair(std: str, name: str) -> None:
    if std not in STANDARD_COLUMNS and not AUX_NAME.fullmatch(std):
        raise DataError(f"unknown standard column {std!r} in column mapping",
                        hint="valid: " + ", ".join(STANDARD_COLUMNS) + "; another name renames "
                             "an extra column (letters, digits, _ and ., e.g. vdd=Supply V)")
    if not name:
        raise DataError(f"column mapping for {std} names no column")


def check_columns(columns: Mapping[str, str] | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for std, name in dict(columns or {}).items():
        name = str(name).strip()
        _check_mapping_pair(std, name)
        other = next((s for s, n in out.items() if n == name), None)
        if other is not None:
            raise DataError(f"column mapping gives file column {name!r} to both {other} and {std}")
        out[std] = name
    return out


