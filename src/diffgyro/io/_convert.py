"""Turning a column into float64 values or device ids, with errors naming the cell."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..errors import DataError
from ._source import NA_TEXT

if TYPE_CHECKING:
    import pandas as pd


def label(std: str, name: str) -> str:
    """How a column is named in messages: the file's name, with the standard one if mapped."""
    if not name or name == std:
        return std
    return f"{name} ({std})"


def to_float(series: pd.Series, file: str, column: str, devices: DeviceIds) -> np.ndarray:
    """A column as float64; empty and NaN-like cells become NaN; text is an error. A numpy
    float64 column (a plain CSV's, :mod:`._plain_csv`) is already that."""
    if isinstance(series, np.ndarray) and series.dtype == np.float64:
        return series
    import pandas as pd  # a frame's column: pandas is loaded already

    if pd.api.types.is_bool_dtype(series.dtype):
        raise DataError("holds true/false values, not numbers", file=file,
                        device=str(devices[0]), column=column, row=1)
    if pd.api.types.is_numeric_dtype(series.dtype) and not pd.api.types.is_complex_dtype(
            series.dtype):
        return series.to_numpy(dtype=np.float64, na_value=np.nan)
    if not (pd.api.types.is_string_dtype(series.dtype) or series.dtype == object):
        raise DataError(f"holds {series.dtype} values, not numbers", file=file,
                        device=str(devices[0]), column=column, row=1)
    cells = series.to_numpy(dtype=object, na_value=None)
    if series.dtype == object:  # mixed columns: text, numbers (exact via repr) or missing
        fixed = np.empty(cells.shape[0], dtype=object)
        for i, cell in enumerate(cells):
            if cell is None or isinstance(cell, str):
                fixed[i] = cell
            elif isinstance(cell, (int, float, np.integer, np.floating)) and not isinstance(
                    cell, (bool, np.bool_)):
                fixed[i] = repr(float(cell))
            else:
                raise DataError(f"non-numeric value of type {type(cell).__name__}", file=file,
                                device=str(devices[i]), column=column, row=i + 1)
        cells = fixed
    stripped = pd.Series(cells, dtype="string").str.strip()
    missing = (stripped.isna() | stripped.str.lower().isin(NA_TEXT)).to_numpy(bool)
    out = np.full(cells.shape[0], np.nan)
    good = np.flatnonzero(~missing)
    if good.size:
        values = stripped.to_numpy(dtype=object)[good]
        try:
            if stripped.str.contains("_", regex=False).any():  # float() takes 1_000; we do not
                raise ValueError
            out[good] = values.astype(np.float64)  # Python float(): correctly rounded
        except (ValueError, TypeError, OverflowError):
            for i, v in zip(good.tolist(), values.tolist(), strict=True):
                try:
                    if "_" in v:
                        raise ValueError
                    out[i] = float(v)
                except (ValueError, TypeError, OverflowError):
                    shown = str(cells[i])
                    shown = shown if len(shown) <= 40 else shown[:37] + "..."
                    raise DataError(f"non-numeric text {shown!r}", file=file,
                                    device=str(devices[i]), column=column, row=i + 1) from None
    return out


@dataclass(frozen=True)
class DeviceIds:
    """Each row's device id: ``names[codes[row]]``, names in order of first appearance."""

    codes: np.ndarray
    names: list[str]

    def __getitem__(self, row: int) -> str:
        return self.names[int(self.codes[row])]

    @classmethod
    def single(cls, n: int, name: str) -> DeviceIds:
        return cls(np.zeros(n, np.intp), [name])


def _id_text(cell, numeric: bool) -> str:
    """A device id cell as stripped text ('' when missing); in a float column, whole
    numbers read as integers (Parquet/NPZ ids 1, 2 become '1', '2', not '1.0')."""
    if isinstance(cell, bytes):
        cell = cell.decode("utf-8", "replace")
    if cell is None or (isinstance(cell, float) and math.isnan(cell)):
        return ""
    if numeric:
        cell = float(cell)
        if not math.isfinite(cell):
            return ""
        return str(int(cell)) if cell.is_integer() else repr(cell)
    return str(cell).strip()


def device_ids(series: pd.Series, file: str, column: str) -> DeviceIds:
    """Device ids as stripped text, made once per distinct cell value (a column of
    millions of rows holds a few ids); cells that read the same (' a', 'a') are one
    device. A missing or empty id is an error naming its first row. A numpy column of
    text (a plain CSV's) has no missing cell, only empty ones."""
    if isinstance(series, np.ndarray) and series.dtype == object:
        raw, distinct = _factorize(series.tolist())
        numeric = False
    else:
        import pandas as pd  # a frame's column: pandas is loaded already

        raw, distinct = pd.factorize(series, sort=False)  # missing cells: -1
        numeric = pd.api.types.is_float_dtype(series.dtype)
    texts = np.asarray([_id_text(c, numeric) for c in distinct.tolist()] + [""], dtype=object)
    raw = np.where(raw < 0, len(texts) - 1, raw)
    blank = (texts == "")[raw]
    if blank.any():
        raise DataError("missing device id", file=file, column=column,
                        row=int(np.argmax(blank)) + 1)
    merged, names = _factorize(texts[:-1].tolist())  # first-appearance order kept
    return DeviceIds(np.asarray(merged, np.intp)[raw], [str(x) for x in names])


def _factorize(values: list) -> tuple[np.ndarray, np.ndarray]:
    """(code of each value, the distinct values in order of first appearance); the
    values are hashable and none is missing."""
    first: dict = {}
    codes = np.fromiter((first.setdefault(v, len(first)) for v in values), np.intp, len(values))
    return codes, np.asarray(list(first), dtype=object)
