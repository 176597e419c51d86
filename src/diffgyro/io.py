"""Reading and writing recordings: CSV, Parquet and NPZ in the standard schema; logs.

The standard schema is DESIGN.md §3: ``device, t, gx, gy, gz`` plus the
optional groups ``temp``, ``temp_ext``, ``ax..az``, ``mx..mz``, ``rx..rz`` and
``qw..qz``, in SI units (s, rad/s, m/s², °C). One file may hold many devices
in long format (a ``device`` column); without it the device id is the file
stem. Other column names and units are mapped at load time
(:func:`parse_columns`, ``units=``). PX4 ULog, ROS bags and ArduPilot
DataFlash logs are read by :mod:`diffgyro.logs` into the same schema and then
checked like any table.

Bad input raises :class:`~diffgyro.errors.DataError` naming file, device,
column and row. **Row convention:** ``row N`` is the N-th data row of the
file counted from 1 after the header line (blank lines are not rows); Parquet
and NPZ rows are numbered the same way (row 1 = first record). Rows are never
reordered: a device's samples keep their file order, devices keep the order of
their first appearance. Nothing is dropped unless ``drop_invalid=True``, and
then only rows with invalid cells, with the count reported in a
:class:`LoadReport`.

**Invalid cells** are empty, NaN or infinite values, values that overflow in
the unit conversion, and values no instrument gives (:data:`LIMITS`, in SI
units after conversion): a rate (``gx..gz``, ``rx..rz``) or a specific force
(``ax..az``) beyond ±10⁸, a temperature (``temp``, ``temp_ext``) below
absolute zero (−273.15 °C) or above 500 °C. The rate and force limits lie far
above physics (the fastest rotors turn at ~10⁴ rad/s, shock accelerometers
read ~10⁶ m/s²) and above a 24-bit converter's full scale (8.4·10⁶), so raw
ADC counts, which the multi- and six-position recipes calibrate, still load.
Each is refused like NaN, naming file, device, column and row.

Writing (:func:`save`) uses the shortest round-trip decimal form for float64,
so loading a saved file gives bitwise identical values.
"""

from __future__ import annotations

import bz2
import gzip
import lzma
import math
import os
import re
import warnings
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from .data import COLUMN_TO_SIGNAL, OPTIONAL_SIGNALS, SIGNALS, STANDARD_COLUMNS, Batch, Recording
from .errors import DataError
from .jsonio import AtomicFile
from .logs import LOG_SUFFIXES, log_format

__all__ = [
    "UNITS",
    "Dropped",
    "LIMITS",
    "LoadReport",
    "cell_problem",
    "check_cells",
    "check_min_samples",
    "load",
    "load_batch",
    "parse_columns",
    "resolve_units",
    "save",
]

# ---------------------------------------------------------------------------
# units

_DEG = math.pi / 180.0
_G0 = 9.80665  # standard gravity, m/s²

# kind -> canonical unit -> (scale, offset): SI = scale * value + offset
UNITS: dict[str, dict[str, tuple[float, float]]] = {
    "time": {"s": (1.0, 0.0), "ms": (1e-3, 0.0), "us": (1e-6, 0.0), "ns": (1e-9, 0.0),
             "min": (60.0, 0.0), "h": (3600.0, 0.0)},
    "rate": {"rad/s": (1.0, 0.0), "mrad/s": (1e-3, 0.0), "urad/s": (1e-6, 0.0),
             "deg/s": (_DEG, 0.0), "mdeg/s": (_DEG * 1e-3, 0.0),
             "deg/min": (_DEG / 60.0, 0.0), "deg/h": (_DEG / 3600.0, 0.0),
             "rad/h": (1.0 / 3600.0, 0.0), "rpm": (2.0 * math.pi / 60.0, 0.0),
             "rev/s": (2.0 * math.pi, 0.0)},
    "accel": {"m/s^2": (1.0, 0.0), "g": (_G0, 0.0), "mg": (_G0 * 1e-3, 0.0),
              "ug": (_G0 * 1e-6, 0.0)},
    "temp": {"C": (1.0, 0.0), "K": (1.0, -273.15), "F": (5.0 / 9.0, -32.0 * 5.0 / 9.0)},
}
_ALIASES = {
    "sec": "s", "second": "s", "seconds": "s", "msec": "ms", "µs": "us", "μs": "us",
    "usec": "us", "hour": "h", "hr": "h", "minute": "min",
    "rad/sec": "rad/s", "dps": "deg/s", "°/s": "deg/s", "deg/sec": "deg/s",
    "mdps": "mdeg/s", "m°/s": "mdeg/s", "°/h": "deg/h", "deg/hr": "deg/h", "dph": "deg/h",
    "°/min": "deg/min", "µrad/s": "urad/s", "μrad/s": "urad/s", "r/min": "rpm",
    "m/s2": "m/s^2", "m/s²": "m/s^2", "m/s/s": "m/s^2", "µg": "ug", "μg": "ug",
    "c": "C", "°c": "C", "degc": "C", "celsius": "C", "k": "K", "kelvin": "K",
    "f": "F", "°f": "F", "degf": "F", "fahrenheit": "F",
}
# which unit table each signal uses (None: any unit, no conversion)
_SIGNAL_KIND: dict[str, str | None] = {"t": "time", "gyro": "rate", "rate": "rate",
                                       "accel": "accel", "temp": "temp", "temp_ext": "temp",
                                       "mag": None}
# how a user sets each unit (for messages)
_UNIT_OPTION = {"t": "--time-unit", "gyro": "--gyro-unit", "accel": "--acc-unit",
                "temp": "--temp-unit"}


def _canonical_unit(kind: str, text: str) -> str | None:
    table = UNITS[kind]
    raw = str(text).strip()
    if raw in table:
        return raw
    key = raw.replace(" ", "").lower()
    key = _ALIASES.get(key, key).lower()
    for name in table:
        if name.lower() == key:
            return name
    return None


def resolve_units(units: Mapping[str, str] | None) -> dict[str, tuple[float, float]]:
    """Map ``{"gyro": "deg/s", ...}`` to ``{signal: (scale, offset)}`` into SI.

    Keys are signal names: ``t, gyro, rate, accel, temp, temp_ext, mag``.
    ``rate`` (reference rate) follows ``gyro`` and ``temp_ext`` follows
    ``temp`` unless given. ``mag`` accepts any unit and is not converted.
    Unknown signals or units raise :class:`DataError` listing valid ones.
    """
    units = dict(units or {})
    for key in units:
        if key not in _SIGNAL_KIND:
            raise DataError(f"unknown signal {key!r} in units",
                            hint="valid: " + ", ".join(_SIGNAL_KIND))
    if "gyro" in units and "rate" not in units:
        units["rate"] = units["gyro"]
    if "temp" in units and "temp_ext" not in units:
        units["temp_ext"] = units["temp"]
    out: dict[str, tuple[float, float]] = {}
    for sig, text in units.items():
        kind = _SIGNAL_KIND[sig]
        if kind is None or text is None:
            continue
        name = _canonical_unit(kind, text)
        if name is None:
            how = _UNIT_OPTION.get(sig, f"units[{sig!r}]")
            if sig in _UNIT_OPTION:
                how += f" / units[{sig!r}]"
            raise DataError(f"unknown {sig} unit {str(text)!r} (option {how})",
                            hint="valid: " + ", ".join(UNITS[kind]))
        scale, offset = UNITS[kind][name]
        if scale != 1.0 or offset != 0.0:
            out[sig] = (scale, offset)
    return out


# ---------------------------------------------------------------------------
# column mapping


def parse_columns(text: str | None) -> dict[str, str]:
    """Parse the command-line mapping ``"gx=gyr_x,gy=gyr_y"`` (standard=name in file).

    A left-hand name that is not a standard column renames an extra column:
    ``vdd=Supply V`` keeps the file's ``Supply V`` as the extra column ``vdd``
    (letters, digits, ``_`` and ``.``, starting with a letter or ``_``; the
    name an ``aux(vdd)`` term uses)."""
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


def _check_columns(columns: Mapping[str, str] | None) -> dict[str, str]:
    out: dict[str, str] = {}
    for std, name in dict(columns or {}).items():
        name = str(name).strip()
        _check_mapping_pair(std, name)
        other = next((s for s, n in out.items() if n == name), None)
        if other is not None:
            raise DataError(f"column mapping gives file column {name!r} to both {other} and {std}")
        out[std] = name
    return out


# ---------------------------------------------------------------------------
# physical limits

#: Closed interval of physically possible values (SI units) per signal; a value
#: outside is refused at load like NaN (see the module notes).
LIMITS: dict[str, tuple[float, float]] = {
    "gyro": (-1e8, 1e8), "rate": (-1e8, 1e8),          # rad/s (or raw counts)
    "accel": (-1e8, 1e8),                              # m/s² (or raw counts)
    "temp": (-273.15, 500.0), "temp_ext": (-273.15, 500.0),  # °C
}
_SI_UNIT = {"gyro": "rad/s", "rate": "rad/s", "accel": "m/s²", "temp": "°C",
            "temp_ext": "°C", "t": "s"}
_WHAT = {"gyro": "gyro", "rate": "reference rate", "accel": "accelerometer",
         "temp": "temperature", "temp_ext": "external temperature"}
NAN, INF, OVERFLOW, BEYOND = 1, 2, 3, 4


def check_cells(raw: np.ndarray, numeric: Sequence[str],
                conv: Mapping[str, tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Values of the standard columns ``numeric`` (rows × columns) in SI units, and a
    code per cell: 0 valid, else :data:`NAN`, :data:`INF`, :data:`OVERFLOW` (in the unit
    conversion) or :data:`BEYOND` (outside :data:`LIMITS`)."""
    si = np.array(raw, dtype=np.float64, copy=True)
    code = np.zeros(si.shape, np.int8)
    code[np.isnan(si)] = NAN
    code[np.isinf(si)] = INF
    for j, std in enumerate(numeric):
        sig = "t" if std == "t" else COLUMN_TO_SIGNAL[std]
        if sig in conv:
            scale, offset = conv[sig]
            with np.errstate(over="ignore", invalid="ignore"):
                si[:, j] = si[:, j] * scale + offset
            code[(code[:, j] == 0) & ~np.isfinite(si[:, j]), j] = OVERFLOW
        if sig in LIMITS:
            lo, hi = LIMITS[sig]
            with np.errstate(invalid="ignore"):
                out = (si[:, j] < lo) | (si[:, j] > hi)
            code[(code[:, j] == 0) & out, j] = BEYOND
    return si, code


def cell_problem(code: int, raw: float, std: str, conv: Mapping) -> tuple[str, str]:
    """The problem and the hint of an invalid cell (a :func:`check_cells` code)."""
    drop = "use --drop-invalid (drop_invalid=True) to skip such rows; the count is reported"
    if code == NAN:
        return "missing or NaN value", drop
    if code == INF:
        return "infinite value", drop
    if code == OVERFLOW:
        return "value overflows in unit conversion", drop
    sig = COLUMN_TO_SIGNAL[std]
    lo, hi = LIMITS[sig]
    scale, offset = conv.get(sig, (1.0, 0.0))
    unit = _SI_UNIT[sig]
    value = f"{raw * scale + offset:.6g} {unit}" + ("" if sig not in conv else f" (read {raw:.6g})")
    if sig.startswith("temp"):
        bound = f"below absolute zero, {lo} {unit}" if raw * scale + offset < lo else \
            f"above {hi:g} {unit}"
    else:
        bound = f"beyond ±{hi:g} {unit}"
    option = {"gyro": "--gyro-unit", "rate": "--gyro-unit", "accel": "--acc-unit"}.get(
        sig, "--temp-unit")
    return (f"{_WHAT[sig]} value {value} is not physical ({bound})",
            f"check the unit ({option}) and the column mapping; or {drop}")


# ---------------------------------------------------------------------------
# drop report


@dataclass(frozen=True)
class Dropped:
    """Rows skipped by ``drop_invalid`` for one device of one file."""

    file: str
    device: str
    rows: int
    first_row: int

    def message(self) -> str:
        s = "" if self.rows == 1 else "s"
        return (f"dropped {self.rows} row{s} with empty, NaN, inf or non-physical cells "
                f"in file {self.file} "
                f"device {self.device} (first: row {self.first_row})")


@dataclass
class LoadReport:
    """What :func:`load` skipped or noticed; pass one in as ``report=`` to receive it."""

    dropped: list[Dropped] = field(default_factory=list)
    # one line each, "warning: file F: ..." (e.g. a log reader's fallback)
    warnings: list[str] = field(default_factory=list)
    #: One line per file that had extra columns holding text (they are not loaded).
    ignored: list[str] = field(default_factory=list)

    @property
    def n_dropped(self) -> int:
        return sum(d.rows for d in self.dropped)

    def lines(self) -> list[str]:
        return [d.message() for d in self.dropped] + list(self.warnings) + list(self.ignored)


def check_min_samples(recording: Recording, n_needed: int, why: str = "the model") -> None:
    """Raise :class:`DataError` when ``recording`` has fewer than ``n_needed`` samples."""
    if recording.n < n_needed:
        raise DataError(
            f"{recording.n} sample{'' if recording.n == 1 else 's'}: "
            f"fewer samples than {why} needs ({n_needed})",
            file=recording.source, device=recording.device)


# ---------------------------------------------------------------------------
# file formats

_CSV_SUFFIXES = {".csv": None, ".tsv": "\t", ".txt": None}
_COMPRESSION = {".gz": "gzip", ".bz2": "bz2", ".xz": "xz"}
_OPENERS = {"gzip": gzip.open, "bz2": bz2.open, "xz": lzma.open}
#: Rows of a CSV file read to tell numeric extra columns from text ones.
_PEEK_ROWS = 1000
_NA_CSV = ["", "nan", "NaN", "NAN", "-nan", "-NaN", "NA", "N/A", "n/a", "null", "NULL",
           "None", "none", "#N/A", "<NA>", "NaT"]
_NA_TEXT = frozenset({"", "nan", "-nan", "+nan", "na", "n/a", "nat", "null", "none", "#n/a",
                      "<na>", "-1.#ind", "1.#qnan"})


def _format_of(path: Path) -> tuple[str, str | None]:
    """(format, compression) from the file name."""
    suffixes = [s.lower() for s in path.suffixes]
    compression = None
    if suffixes and suffixes[-1] in _COMPRESSION:
        compression = _COMPRESSION[suffixes[-1]]
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


class _Source:
    """One opened input file: its column names and a reader for some of them."""

    def __init__(self, path: Path, file: str, log_options: Mapping | None = None):
        self.path, self.file = path, file
        self.format, self.compression = _format_of(path)
        self.sep = ","
        self.raw_names: list[str] = []
        self.log = None
        if self.format in ("ulog", "rosbag", "dataflash"):  # read whole, as a frame
            from .logs import read_log

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
        opener = _OPENERS[self.compression] if self.compression else open
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
        try:
            frame = self._read_csv(header=None, nrows=1, dtype=str)
        except _ReadFailure as err:
            raise DataError(f"cannot parse the CSV header ({err.cause})", file=self.file) from None
        if len(frame) == 0:
            raise DataError("empty file (no header, no data)", file=self.file)
        self.raw_names = ["" if pd.isna(v) else str(v) for v in frame.iloc[0].tolist()]

    def _read_csv(self, na_filter: bool = False, **kw) -> pd.DataFrame:
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

    def _read_csv_columns(self, wanted: list[str], text_cols: set[str]) -> pd.DataFrame:
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
            self.raw_names = list(pq.read_schema(self.path).names)
        except Exception as err:  # pyarrow raises several types for corrupt files
            raise DataError(f"cannot read as Parquet ({type(err).__name__}: {err})",
                            file=self.file) from None

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
            import pyarrow.parquet as pq

            schema = pq.read_schema(self.path)
            return {n for n in names if not (pa.types.is_integer(schema.field(raw[n]).type)
                                             or pa.types.is_floating(schema.field(raw[n]).type))}
        if self.format == "npz":
            return {n for n in names if self._arrays[raw[n]].dtype.kind not in "iuf"}
        if self.log is not None:
            return {n for n in names if self.log.frame[raw[n]].dtype.kind not in "iuf"}
        try:
            head = self._read_csv(header=0, nrows=_PEEK_ROWS, dtype=str,
                                  usecols=[raw[n] for n in names])
        except _ReadFailure:
            return set()  # the full read reports what is wrong with the file
        head.columns = [str(c).strip() for c in head.columns]
        return {n for n in names if not all(_is_number(v) or v.strip().lower() in _NA_TEXT
                                            for v in head[n].tolist())}

    def read(self, wanted: list[str], text_cols: set[str]) -> pd.DataFrame:
        if self.log is not None:
            return self.log.frame[wanted]
        if self.format == "csv":
            return self._read_csv_columns(wanted, text_cols)
        if self.format == "parquet":
            import pyarrow.parquet as pq

            raw = {n: r for n, r in zip(self.names, self.raw_names, strict=True)}
            try:
                table = pq.read_table(self.path, columns=[raw[n] for n in wanted])
                frame = table.to_pandas()
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


class _ReadFailure(Exception):
    def __init__(self, cause: Exception):
        super().__init__(str(cause))
        self.cause = f"{type(cause).__name__}: {cause}"


# ---------------------------------------------------------------------------
# cell conversion


def _label(std: str, name: str) -> str:
    """How a column is named in messages: the file's name, with the standard one if mapped."""
    if not name or name == std:
        return std
    return f"{name} ({std})"


def _to_float(series: pd.Series, file: str, column: str, devices: np.ndarray) -> np.ndarray:
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
    missing = (stripped.isna() | stripped.str.lower().isin(_NA_TEXT)).to_numpy(bool)
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


def _device_ids(series: pd.Series, file: str, column: str) -> np.ndarray:
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


# ---------------------------------------------------------------------------
# load


def _as_paths(paths) -> list[Path]:
    if isinstance(paths, (str, os.PathLike)):
        paths = [paths]
    out = [Path(p) for p in paths]
    if not out:
        raise DataError("no data files given")
    return out


def load(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    columns: Mapping[str, str] | None = None,
    units: Mapping[str, str] | None = None,
    drop_invalid: bool = False,
    sampling_rate: float | None = None,
    device: str | None = None,
    *,
    min_samples: int = 2,
    report: LoadReport | None = None,
    topic: str | None = None,
    temp_topic: str | None = None,
) -> list[Recording]:
    """Read recordings from CSV / Parquet / NPZ files in the standard schema, or logs.

    Args:
        paths: one file or many; a device id may appear in only one file.
        columns: standard name -> name in the file (``{"gx": "gyr_x"}``);
            see :func:`parse_columns` for the command-line form.
        units: signal -> unit of the file (``{"gyro": "deg/s", "temp": "K"}``),
            converted to SI at load; see :func:`resolve_units`.
        drop_invalid: skip rows with empty/NaN/inf cells (counted in
            ``report``) instead of raising.
        sampling_rate: Hz; files without a ``t`` column get ``t = k / rate``
            (k = the sample's index within its device in the file).
        device: id for files without a ``device`` column (default: file stem).
        min_samples: fewer samples in a device is an error.
        report: a :class:`LoadReport` that receives the dropped-row counts
            and the log readers' warnings (without one they are issued with
            :func:`warnings.warn`).
        topic: ROS bags: the ``sensor_msgs/msg/Imu`` topic(s), comma-separated
            (default: all).
        temp_topic: ROS bags: the ``sensor_msgs/msg/Temperature`` topic.

    Logs (``.ulg``, ``.bag``, ``.mcap``, a rosbag2 folder, ``.bin``, ``.log``)
    are read by :mod:`diffgyro.logs`; ``device`` then replaces the file stem
    at the start of their device ids.

    Returns one :class:`Recording` per device, in file order, then
    first-appearance order within a file.
    """
    columns = _check_columns(columns)
    conv = resolve_units(units)
    if sampling_rate is not None:
        try:
            sampling_rate = float(sampling_rate)
        except (TypeError, ValueError):
            raise DataError(f"sampling rate {sampling_rate!r} is not a number") from None
        if not (np.isfinite(sampling_rate) and sampling_rate > 0):
            raise DataError(f"sampling rate must be a positive number of Hz, got {sampling_rate}")
    if device is not None and not str(device).strip():
        raise DataError("device id given is empty")
    recordings: list[Recording] = []
    owner: dict[str, str] = {}
    log_options = {"topic": topic, "temp_topic": temp_topic}
    for path in _as_paths(paths):
        for rec in _load_file(path, columns, conv, drop_invalid, sampling_rate, device,
                              min_samples, report, log_options):
            if rec.device in owner:
                raise DataError(
                    f"device id appears in two files: {owner[rec.device]} and {rec.source}",
                    file=rec.source, device=rec.device,
                    hint="give each device a unique id (the device column or the file name)")
            owner[rec.device] = rec.source
            recordings.append(rec)
    return recordings


def load_batch(
    paths: str | os.PathLike | Sequence[str | os.PathLike],
    columns: Mapping[str, str] | None = None,
    units: Mapping[str, str] | None = None,
    drop_invalid: bool = False,
    sampling_rate: float | None = None,
    device: str | None = None,
    *,
    min_samples: int = 2,
    report: LoadReport | None = None,
    length: int | None = None,
    bucket: bool = True,
) -> Batch:
    """:func:`load`, then :meth:`Batch.from_recordings` (padded to a bucket length)."""
    recs = load(paths, columns, units, drop_invalid, sampling_rate, device,
                min_samples=min_samples, report=report)
    return Batch.from_recordings(recs, length=length, bucket=bucket)


def _load_file(path, columns, conv, drop_invalid, sampling_rate, device, min_samples,
               report, log_options=None) -> list[Recording]:
    file = str(path)
    if not path.exists():
        raise DataError("file not found", file=file)
    if not path.is_file() and log_format(path) != "rosbag":
        raise DataError("not a file", file=file)
    if device is not None and log_format(path):
        log_options = {**(log_options or {}), "prefix": str(device).strip()}
    src = _Source(path, file, log_options)
    for line in src.log.warnings if src.log is not None else []:
        if report is not None:
            report.warnings.append(line)
        else:
            warnings.warn(line, stacklevel=3)
    names = set(src.names)
    found = ", ".join(n for n in src.names[:12] if n) + (" ..." if len(src.names) > 12 else "")

    def hint_for_missing() -> str:
        if len(src.names) == 1 and any(s in src.names[0] for s in (";", "\t", ",")):
            return f"the header is one column {src.names[0]!r}: check the separator"
        if src.names and all(_is_number(n) for n in src.names if n):
            return "the file seems to have no header line"
        return f"columns in the file: {found}; map others with --columns std=name"

    # which standard columns are in the file, under which name
    # (a file column mapped to one standard name does not also serve under its own name)
    claimed = set(columns.values())
    where = {std: columns.get(std, std if std not in claimed else "") for std in STANDARD_COLUMNS}
    for std, name in columns.items():
        if name not in names:
            raise DataError(f"column {name!r} (given for {std}) is not in the file",
                            file=file, column=name, hint=hint_for_missing())
    present = {std: name for std, name in where.items() if name and name in names}
    stem = path.name
    if path.suffix.lower() in _COMPRESSION:
        stem = stem[: -len(path.suffix)]
    default_device = str(device).strip() if device is not None else Path(stem).stem
    dev_label = None if "device" in present else default_device

    if "t" not in present and sampling_rate is None:
        raise DataError("missing required column", file=file, device=dev_label,
                        column=_label("t", where["t"]),
                        hint=hint_for_missing() + "; or give a sampling rate for files without t")
    for std in SIGNALS["gyro"]:
        if std not in present:
            raise DataError("missing required column", file=file, device=dev_label,
                            column=_label(std, where[std]), hint=hint_for_missing())
    signals = ["gyro"]
    for sig in OPTIONAL_SIGNALS:
        have = [c for c in SIGNALS[sig] if c in present]
        if have and len(have) < len(SIGNALS[sig]):
            lacking = [c for c in SIGNALS[sig] if c not in present][0]
            raise DataError(
                f"incomplete {sig} group: {', '.join(have)} present but not {lacking}",
                file=file, device=dev_label, column=_label(lacking, where[lacking]),
                hint=f"{sig} needs all of {', '.join(SIGNALS[sig])}")
        if have:
            signals.append(sig)

    numeric = (["t"] if "t" in present else []) + [c for s in signals for c in SIGNALS[s]]
    wanted_std = (["device"] if "device" in present else []) + numeric
    extra, ignored = _extra_columns(src, columns, present)
    frame = src.read([present[s] for s in wanted_std] + list(extra.values()),
                     {present["device"]} if "device" in present else set())
    n = len(frame)
    if n == 0:
        raise DataError("no data rows (header only)", file=file, device=dev_label)
    if "device" in present:
        dev_col = _label("device", present["device"])
        devices = _device_ids(frame[present["device"]], file, dev_col)
    else:
        devices = np.full(n, default_device, dtype=object)

    values = np.empty((n, len(numeric)))
    for j, std in enumerate(numeric):
        values[:, j] = _to_float(frame[present[std]], file, _label(std, present[std]), devices)
    aux_all: dict[str, np.ndarray] = {}
    for name, col in extra.items():
        try:
            aux_all[name] = _to_float(frame[col], file, col, devices)
        except DataError:  # text further down than the first rows
            ignored.append(col)
    del frame
    if ignored:
        line = (f"ignored non-numeric column{'s' if len(ignored) > 1 else ''} "
                f"{', '.join(sorted(ignored))} in file {file}")
        if report is not None:
            report.ignored.append(line)
        else:
            warnings.warn(line, stacklevel=3)

    # group rows by device: first-appearance order, file order within a device
    codes, uniques = pd.factorize(devices, sort=False)
    order = np.argsort(codes, kind="stable")
    bounds = np.cumsum(np.bincount(codes, minlength=len(uniques)))[:-1]
    groups = np.split(order, bounds)

    out = []
    for dev, rows in zip(uniques.tolist(), groups, strict=True):
        dev = str(dev)
        si, code = check_cells(values[rows], numeric, conv)
        k_index = np.arange(rows.shape[0], dtype=np.float64)  # position within the device
        bad_rows = code.any(axis=1)
        if bad_rows.any():
            first = int(np.flatnonzero(bad_rows)[0])
            if not drop_invalid:
                j = int(np.flatnonzero(code[first])[0])
                problem, hint = cell_problem(int(code[first, j]), float(values[rows[first], j]),
                                             numeric[j], conv)
                raise DataError(problem, file=file, device=dev,
                                column=_label(numeric[j], present[numeric[j]]),
                                row=int(rows[first]) + 1, hint=hint)
            if report is not None:
                report.dropped.append(Dropped(file, dev, int(bad_rows.sum()),
                                              int(rows[first]) + 1))
            keep = ~bad_rows
            si, rows, k_index = si[keep], rows[keep], k_index[keep]
        # extra columns may hold gaps: checked when a model uses them (diffgyro.aux)
        aux = {name: np.ascontiguousarray(a[rows]) for name, a in aux_all.items()}
        cols = {std: si[:, j] for j, std in enumerate(numeric)}
        t = cols["t"] if "t" in cols else k_index / sampling_rate
        fields: dict[str, np.ndarray] = {}
        for sig in ["t", *signals]:
            if sig == "t":
                arr = t
            elif len(SIGNALS[sig]) == 1:
                arr = cols[SIGNALS[sig][0]]
            else:
                arr = np.stack([cols[c] for c in SIGNALS[sig]], axis=1)
            fields[sig] = np.ascontiguousarray(arr, dtype=np.float64)
        _check_time(fields["t"], rows, file, dev,
                    _label("t", present["t"]) if "t" in present else "t (from sampling rate)",
                    several="device" in present)
        rec = Recording(**fields, device=dev, source=file, aux=aux)
        if rec.n < min_samples:
            dropped = " after dropping invalid rows" if drop_invalid and bad_rows.any() else ""
            raise DataError(
                f"{rec.n} sample{'' if rec.n == 1 else 's'}{dropped}: "
                f"fewer samples than loading needs ({min_samples})", file=file, device=dev)
        out.append(rec)
    return out


def _extra_columns(src: _Source, columns: Mapping[str, str],
                   present: Mapping[str, str]) -> tuple[dict[str, str], list[str]]:
    """Extra columns to keep (name -> file column) and the text ones to ignore.

    Every named file column that is neither a standard column nor used for one
    is kept under its own name; ``columns`` entries whose key is not a standard
    name rename one (the renamed name wins over a file column of that name)."""
    used = set(present.values())
    renamed = {name: col for name, col in columns.items() if name not in STANDARD_COLUMNS}
    taken = set(renamed.values())
    extra = dict(renamed)
    for col in src.names:
        if (col and col not in used and col not in taken and col not in STANDARD_COLUMNS
                and col not in extra):
            extra[col] = col
    text = src.text_columns(list(extra.values()))
    return {k: v for k, v in extra.items() if v not in text}, sorted(text)


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _check_time(t: np.ndarray, rows: np.ndarray, file: str, device: str, column: str,
                several: bool) -> None:
    if t.shape[0] < 2:
        return
    step = np.diff(t)
    bad = np.flatnonzero(~(step > 0))
    if bad.size == 0:
        return
    k = int(bad[0]) + 1
    now, before = float(t[k]), float(t[k - 1])
    prev_row, row = int(rows[k - 1]) + 1, int(rows[k]) + 1
    if now == before:
        problem = f"time {now!r} s repeats row {prev_row} (time must strictly increase)"
    else:
        problem = (f"time goes backwards: {now!r} s after {before!r} s on row {prev_row} "
                   f"(time must strictly increase)")
    hint = None if several else "several devices in one file need a 'device' column"
    raise DataError(problem, file=file, device=device, column=column, row=row, hint=hint)


# ---------------------------------------------------------------------------
# save


def _as_recordings(data) -> list[Recording]:
    if isinstance(data, Recording):
        return [data]
    if isinstance(data, Batch):
        return data.recordings()
    recs = list(data)
    if not recs or not all(isinstance(r, Recording) for r in recs):
        raise DataError("save needs a Recording, a Batch or a non-empty list of Recordings")
    return recs


def save(data: Recording | Batch | Sequence[Recording], path: str | os.PathLike) -> Path:
    """Write recordings in the standard schema (long format) to CSV, Parquet or NPZ.

    Extra columns (``aux``) follow the standard ones under their names.

    The format follows the extension (``.csv``, ``.tsv``, ``.csv.gz``,
    ``.parquet``, ``.npz``). Values are written as float64 in the shortest
    decimal form that reads back bitwise identical. The file is written to a
    temporary name in the same folder and moved into place, so a crash never
    leaves half a file. Returns the path written.
    """
    path = Path(path)
    recs = _as_recordings(data)
    seen: set[str] = set()
    for r in recs:
        if r.device in seen:
            raise DataError("device id appears more than once", device=r.device, file=str(path))
        seen.add(r.device)
        if r.signals != recs[0].signals:
            raise DataError(
                f"devices record different signals ({', '.join(r.signals)} vs "
                f"{', '.join(recs[0].signals)} for {recs[0].device}); one long-format file "
                f"needs the same columns for all", device=r.device, file=str(path),
                hint="save them to separate files")
        if list(r.aux) != list(recs[0].aux):
            raise DataError(
                f"devices have different extra columns ({', '.join(r.aux) or 'none'} vs "
                f"{', '.join(recs[0].aux) or 'none'} for {recs[0].device}); one long-format "
                f"file needs the same columns for all", device=r.device, file=str(path),
                hint="save them to separate files")
    fmt, compression = _format_of(path)
    cols: dict[str, np.ndarray] = {
        "device": np.concatenate([np.full(r.n, r.device, dtype=object) for r in recs])}
    for sig in ("t", "gyro", *OPTIONAL_SIGNALS):
        if getattr(recs[0], sig) is None:
            continue
        names = ("t",) if sig == "t" else SIGNALS[sig]
        stacked = np.concatenate(
            [np.asarray(getattr(r, sig), dtype=np.float64).reshape(r.n, len(names))
             for r in recs])
        for k, name in enumerate(names):
            cols[name] = stacked[:, k]
    for name in recs[0].aux:
        cols[name] = np.concatenate([np.asarray(r.aux[name], dtype=np.float64) for r in recs])
    with AtomicFile(path, None) as f:
        tmp = f.tmp
        if fmt == "csv":
            _write_csv(cols, tmp, "\t" if ".tsv" in [s.lower() for s in path.suffixes] else ",",
                       compression)
        elif fmt == "parquet":
            import pyarrow as pa
            import pyarrow.parquet as pq

            table = pa.table({k: (pa.array(v.tolist(), pa.string()) if k == "device" else v)
                              for k, v in cols.items()})
            pq.write_table(table, tmp)
        else:
            arrays = {k: (np.asarray(v.tolist(), dtype=np.str_) if k == "device" else v)
                      for k, v in cols.items()}
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
    return path


def _write_csv(cols: dict[str, np.ndarray], tmp: str, sep: str, compression: str | None) -> None:
    import pyarrow as pa
    import pyarrow.csv as pcsv

    table = pa.table({k: (pa.array(v.tolist(), pa.string()) if k == "device" else v)
                      for k, v in cols.items()})
    plain = not any(ch in d for d in set(cols["device"].tolist()) for ch in (sep, '"', "\n", "\r"))
    opener = _OPENERS[compression] if compression else open
    with opener(tmp, "wb") as fh:
        fh.write((sep.join(cols) + "\n").encode())
        # Arrow formats float64 in the shortest round-trip form, ~10x faster than pandas
        pcsv.write_csv(table, fh, pcsv.WriteOptions(include_header=False, delimiter=sep,
                                                   quoting_style="none" if plain else "needed"))
