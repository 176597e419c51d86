"""Opening an input file of any supported format and reading some of its columns."""

from __future__ import annotations

import bz2
import gzip
import lzma
import sys
import warnings
import zlib
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..errors import DataError
from ..logs import LOG_SUFFIXES, log_format, read_log
from ._plain_csv import PlainTable, read_plain, split_plain

if TYPE_CHECKING:
    import pandas as pd

_CSV_SUFFIXES = {".csv": None, ".tsv": "\t", ".txt": None}
COMPRESSION = {".gz": "gzip", ".bz2": "bz2", ".xz": "xz"}
OPENERS = {"gzip": gzip.open, "bz2": bz2.open, "xz": lzma.open}
#: Rows of a CSV file read to tell numeric extra columns from text ones.
_PEEK_ROWS = 1000
_NA_CSV = ["", "nan", "NaN", "NAN", "-nan", "-NaN", "NA", "N/A", "n/a", "null", "NULL",
           "None", "none", "#N/A", "<NA>", "NaT"]
NA_TEXT = frozenset({"", "nan", "-nan", "+nan", "na", "n/a", "nat", "null", "none", "#n/a",
                      "<na>", "-1.#ind", "1.#qnan"})


def format_of(path: Path) -> tuple[str, str | None]:
    """(format, compression) from the file name."""
    suffixes = [s.lower() for s in path.suffixes]
    compression = None
    if suffixes and suffixes[-1] in COMPRESSION:
        compression = COMPRESSION[suffixes[-1]]
        suffixes = suffixes[:-1]
    ext = suffixes[-1] if suffixes else ""
    if compression is None and log_format(path):
        return log_format(path), None
    if ext in _CSV_SUFFIXES:
        return "csv", compression
    if compression is None and ext in (".parquet", ".pq"):
        return "parquet", None
    if compression is None and ext == ".npz":
        return "npz", None
    raise DataError(f"unknown file type {''.join(path.suffixes) or '(no extension)'!r}",
                    file=str(path),
                    hint="use .csv, .tsv, .txt (optionally .gz/.bz2/.xz), .parquet, .npz or "
                         "a log: " + ", ".join(LOG_SUFFIXES) + ", a rosbag2 folder")


def is_number(text: str) -> bool:
    """True if ``text`` reads as a float (a header of numbers is a data row)."""
    try:
        float(text)
    except ValueError:
        return False
    return True


class Source:
    """One opened input file: its column names and a reader for some of them."""

    def __init__(self, path: Path, file: str, log_options: Mapping | None = None):
        self.path, self.file = path, file
        self.format, self.compression = format_of(path)
        self.sep = ","
        self.raw_names: list[str] = []
        self.log = None
        self._plain: list[list[str]] | None = None  # a plain CSV's split lines
        if self.format in ("ulog", "rosbag", "dataflash"):  # read whole, as a frame

            self.log = read_log(path, self.format, file=file, **dict(log_options or {}))
            self.raw_names = list(self.log.frame.columns)
        elif self.format == "csv":
            self._open_csv()
        elif self.format == "parquet":
            self._open_parquet()
        else:
            self._open_npz()
        names = [str(c).strip() for c in self.raw_names]
        seen = set()
        for name in names:
            if name and name in seen:
                raise DataError("column name appears twice in the header", file=file, column=name)
            seen.add(name)
        self.names = names

    # -- CSV
    def _open_csv(self) -> None:
        opener = OPENERS[self.compression] if self.compression else open
        try:
            with opener(self.path, "rb") as fh:
                head = fh.read(65536)
        except (OSError, EOFError, lzma.LZMAError, zlib.error) as err:  # damaged compression
            raise DataError(f"cannot read file ({err})", file=self.file) from None
        if not head.strip():
            raise DataError("empty file (no header, no data)", file=self.file)
        if b"\x00" in head:
            raise DataError("binary data, not CSV text", file=self.file)
        line = head.split(b"\n", 1)[0]
        try:
            first = line.decode("utf-8-sig", errors="strict" if b"\n" in head else "ignore")
        except UnicodeDecodeError:
            raise DataError("not UTF-8 text", file=self.file,
                            hint="save the CSV as UTF-8") from None
        ext = Path(self.path.name.removesuffix(self.path.suffix)).suffix.lower() \
            if self.compression else self.path.suffix.lower()
        if _CSV_SUFFIXES.get(ext):
            self.sep = _CSV_SUFFIXES[ext]
        else:  # the separator that splits the header most: ',' ';' or tab
            counts = {s: first.count(s) for s in (",", ";", "\t")}
            self.sep = max(counts, key=lambda s: (counts[s], s == ","))
        if not first.strip():
            raise DataError("the first line is empty; expected the header line", file=self.file)
        if self.compression is None and b"\n" in head:
            self._plain = split_plain(self.path, self.sep)
        if self._plain is not None:  # read without pandas (and its import)
            self.raw_names = self._plain[0]
            return
        import pandas as pd

        try:
            frame = self._read_csv(header=None, nrows=1, dtype=str)
        except _ReadFailure as err:
            raise DataError(f"cannot parse the CSV header ({err.cause})", file=self.file) from None
        if len(frame) == 0:
            raise DataError("empty file (no header, no data)", file=self.file)
        self.raw_names = ["" if pd.isna(v) else str(v) for v in frame.iloc[0].tolist()]

    def _read_csv(self, na_filter: bool = False, **kw) -> pd.DataFrame:
        import pandas as pd  # here, not at the top: a plain CSV is read without it

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", pd.errors.ParserWarning)
                return pd.read_csv(self.path, sep=self.sep, compression=self.compression,
                                   encoding="utf-8-sig", index_col=False, na_filter=na_filter,
                                   skip_blank_lines=True, engine="c", **kw)
        except pd.errors.ParserWarning:
            raise DataError("data rows have more fields than the header", file=self.file,
                            hint="check the separator and the header line") from None
        except pd.errors.ParserError as err:
            text = str(err).replace("Error tokenizing data. C error: ", "").strip()
            raise DataError(f"cannot parse CSV: {text}", file=self.file,
                            hint="every row needs as many fields as the header") from None
        except pd.errors.EmptyDataError:
            raise DataError("empty file (no header, no data)", file=self.file) from None
        except UnicodeDecodeError:
            raise DataError("not UTF-8 text", file=self.file, hint="save the CSV as UTF-8") from None
        except (ValueError, OSError, EOFError, OverflowError, lzma.LZMAError, zlib.error) as err:
            raise _ReadFailure(err) from None

    def _read_csv_columns(self, wanted: list[str], text_cols: set[str]) -> pd.DataFrame | PlainTable:
        if self._plain is not None:
            table = read_plain(self._plain, wanted, text_cols)
            if table is not None:
                return table
        raw = {n: r for n, r in zip(self.names, self.raw_names, strict=True)}
        dtype = {raw[n]: (str if n in text_cols else np.float64) for n in wanted}
        try:  # fast path: every wanted column parses as float64 (exact, round-trip)
            frame = self._read_csv(header=0, dtype=dtype)
        except _ReadFailure:
            # slow path: columns with only numbers and NA markers still parse in C; the
            # others come back as text and are converted cell by cell (precise errors)
            na = {raw[n]: _NA_CSV for n in wanted if n not in text_cols}
            try:
                frame = self._read_csv(header=0, dtype={raw[n]: str for n in text_cols},
                                       na_filter=True, keep_default_na=False, na_values=na,
                                       low_memory=False)
            except _ReadFailure as err:
                raise DataError(f"cannot parse CSV ({err.cause})", file=self.file) from None
        frame.columns = [str(c).strip() for c in frame.columns]
        return frame[wanted]

    # -- Parquet
    def _open_parquet(self) -> None:
        import pyarrow.parquet as pq

        try:
            self._schema = pq.read_schema(self.path)  # the stored types, read once
        except Exception as err:  # pyarrow raises several types for corrupt files
            raise DataError(f"cannot read as Parquet ({type(err).__name__}: {err})",
                            file=self.file) from None
        self.raw_names = list(self._schema.names)

    # -- NPZ
    def _open_npz(self) -> None:
        try:
            with np.load(self.path, allow_pickle=False) as npz:
                self._arrays = {k: npz[k] for k in npz.files}
        except Exception as err:  # zipfile, pickle refusal, truncated arrays ...
            raise DataError(f"cannot read as NPZ ({type(err).__name__}: {err})",
                            file=self.file,
                            hint="store one 1-D array per column, device ids as text") from None
        self.raw_names = list(self._arrays)

    def text_columns(self, names: list[str]) -> set[str]:
        """Those of ``names`` that hold text, not numbers: for Parquet and NPZ from the
        stored types; for CSV from the first rows (a column that turns to text further
        down is found when it is read)."""
        if not names:
            return set()
        raw = {n: r for n, r in zip(self.names, self.raw_names, strict=True)}
        if self.format == "parquet":
            import pyarrow as pa

            kinds = {n: self._schema.field(raw[n]).type for n in names}
            return {n for n, k in kinds.items() if not (pa.types.is_integer(k) or pa.types.is_floating(k))}
        if self.format == "npz":
            return {n for n in names if self._arrays[raw[n]].dtype.kind not in "iuf"}
        if self.log is not None:
            return {n for n in names if self.log.frame[raw[n]].dtype.kind not in "iuf"}
        if self._plain is not None:
            at = {name.strip(): k for k, name in enumerate(self._plain[0])}
            head = self._plain[1:_PEEK_ROWS + 1]
            return {n for n in names if not all(is_number(r[at[n]]) or
                                                r[at[n]].strip().lower() in NA_TEXT for r in head)}
        try:
            head = self._read_csv(header=0, nrows=_PEEK_ROWS, dtype=str,
                                  usecols=[raw[n] for n in names])
        except _ReadFailure:
            return set()  # the full read reports what is wrong with the file
        head.columns = [str(c).strip() for c in head.columns]
        return {n for n in names if not all(is_number(v) or v.strip().lower() in NA_TEXT
                                            for v in head[n].tolist())}

    def read(self, wanted: list[str], text_cols: set[str]) -> pd.DataFrame | PlainTable:
        if self.log is not None:
            return self.log.frame[wanted]
        if self.format == "csv":
            return self._read_csv_columns(wanted, text_cols)
        import pandas as pd

        if self.format == "parquet":
            import pyarrow.parquet as pq

            raw = {n: r for n, r in zip(self.names, self.raw_names, strict=True)}
            try:
                # column by column (decoding buffers for one column at a time); text columns
                # (device ids) as categories: a few distinct ids, not a string per row
                text = [raw[n] for n in text_cols if _is_text(self._schema.field(raw[n]).type)]
                pf = pq.ParquetFile(self.path, read_dictionary=text)
                frame = pd.DataFrame({raw[n]: pf.read(columns=[raw[n]]).column(0).to_pandas()
                                      for n in wanted}, copy=False)
            except Exception as err:
                raise DataError(f"cannot read as Parquet ({type(err).__name__}: {err})",
                                file=self.file) from None
            frame.columns = [str(c).strip() for c in frame.columns]
            return frame
        cols = {}
        raw = {n: r for n, r in zip(self.names, self.raw_names, strict=True)}
        n_rows = None
        for name in wanted:
            arr = self._arrays[raw[name]]
            if arr.ndim != 1:
                raise DataError(f"NPZ array has shape {arr.shape}; expected one value per row",
                                file=self.file, column=name)
            if n_rows is not None and arr.shape[0] != n_rows:
                raise DataError(f"NPZ array has {arr.shape[0]} rows, others have {n_rows}",
                                file=self.file, column=name)
            n_rows = arr.shape[0]
            cols[name] = arr
        return pd.DataFrame(cols)


def release_read_buffers() -> None:
    """Hand back to the system the memory Arrow's allocator keeps for reuse after a read
    (about the size of the numeric columns read: 0.25 GB for 4 M rows of six)."""
    pa = sys.modules.get("pyarrow")
    if pa is not None:
        pa.default_memory_pool().release_unused()


def _is_text(kind) -> bool:
    import pyarrow as pa

    return pa.types.is_string(kind) or pa.types.is_large_string(kind) or \
        pa.types.is_binary(kind) or pa.types.is_large_binary(kind)


class _ReadFailure(Exception):
    def __init__(self, cause: Exception):
        super().__init__(str(cause))
        self.cause = f"{type(cause).__name__}: {cause}"


