"""Turning a column into float64 values or device ids, with errors naming the cell."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from ..errors import DataError
from .source import NA_TEXT


def label(std: str, name: str) -> str:
    """How a column is named in messages: the file's name, with the standard one if mapped."""
    if not name or name == std:
        return std
    return f"{name} ({std})"


def to_float(series: pd.Series, file: str, column: str, devices: np.ndarray) -> np.ndarray:
    """A column as float64; empty and NaN-like cells become NaN; text is an error."""
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


def device_ids(series: pd.Series, file: str, column: str) -> np.ndarray:
    """Device ids as stripped text (integers in Parquet/NPZ become '1', not '1.0')."""
    if pd.api.types.is_float_dtype(series.dtype):
        vals = series.to_numpy(dtype=np.float64, na_value=np.nan)
        cells = [None if not np.isfinite(v) else (str(int(v)) if v.is_integer() else repr(v))
                 for v in vals.tolist()]
    else:
        cells = series.to_numpy(dtype=object, na_value=None).tolist()
    ids = np.empty(len(cells), dtype=object)
    for i, cell in enumerate(cells):
        if isinstance(cell, bytes):
            cell = cell.decode("utf-8", "replace")
        if isinstance(cell, float) and math.isnan(cell):
            cell = None
        text = "" if cell is None else str(cell).strip()
        if not text:
            raise DataError("missing device id", file=file, column=column, row=i + 1)
        ids[i] = text
    return ids


