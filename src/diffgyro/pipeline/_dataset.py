"""Datasets larger than memory: where each device lives, and reading one chunk of devices.

A first pass reads only the device column of every Parquet row group (kept
dictionary-encoded, so a row costs four bytes) and records, per device, its
file, the row groups holding it and its number of rows. A chunk of devices
is then read row group by row group, keeping only that chunk's rows, so peak
memory is set by the chunk size and the row-group size, never by the size of
the dataset. CSV/NPZ files named explicitly are read whole by
:func:`diffgyro.io.load` (they are small by nature).

Every device of a chunk is validated on its own (finite values, strictly
increasing time, enough samples): a problem becomes a :class:`DataError` for
that device, recorded by the caller, and the other devices carry on. Problems
that concern a whole file (a missing required column, an unreadable file)
stop the run at indexing, before any fitting.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from .. import io
from ..data import OPTIONAL_SIGNALS, SIGNALS, Recording
from ..errors import DataError
from ..io import cell_problem, check_cells, check_plausible, resolve_units

PARQUET_SUFFIXES = (".parquet", ".pq")


def expand_inputs(paths: Sequence[str | os.PathLike]) -> list[Path]:
    """Files to read: directories expand to their Parquet files (recursively, sorted)."""
    out: list[Path] = []
    for p in paths:
        p = Path(p)
        if p.is_dir():
            files = sorted(
                (f for f in p.rglob("*")
                 if f.is_file() and f.suffix.lower() in PARQUET_SUFFIXES
                 and not any(part.startswith((".", "_")) for part in f.relative_to(p).parts)),
                key=lambda f: f.relative_to(p).as_posix())
            if not files:
                raise DataError("no Parquet files (*.parquet, *.pq) in the directory", file=str(p))
            out.extend(files)
        elif p.is_file():
            out.append(p)
        else:
            raise DataError("file not found", file=str(p))
    if not out:
        raise DataError("no data files given")
    seen: set[str] = set()
    unique = []
    for f in out:
        key = os.path.realpath(f)
        if key not in seen:
            seen.add(key)
            unique.append(f)
    return unique


def fingerprint(path: Path) -> dict:
    """Path, size and modification time: enough to notice a changed input on resume."""
    st = path.stat()
    return {"path": str(path.resolve()), "size": int(st.st_size), "mtime_ns": int(st.st_mtime_ns)}


@dataclass(frozen=True)
class ReadConfig:
    """How rows become recordings: column mapping, unit conversion, which signals.

    ``units`` maps signals to the files' units (:func:`diffgyro.io.resolve_units`);
    ``wanted`` lists the optional signals to read when a file has them (a
    model's needs plus the reference rate, which every fit subtracts when
    present).
    """

    columns: dict[str, str] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    drop_invalid: bool = False
    sampling_rate: float | None = None
    wanted: tuple[str, ...] = ("rate",)
    min_samples: int = 2

    @property
    def conv(self) -> dict[str, tuple[float, float]]:

        return resolve_units(self.units)

    def to_json(self) -> dict:
        return {"columns": dict(sorted(self.columns.items())),
                "units": dict(sorted(self.units.items())),
                "drop_invalid": self.drop_invalid, "sampling_rate": self.sampling_rate,
                "wanted": list(self.wanted), "min_samples": self.min_samples}

    @classmethod
    def from_json(cls, obj: dict) -> ReadConfig:
        return cls(columns=dict(obj["columns"]), units=dict(obj["units"]),
                   drop_invalid=bool(obj["drop_invalid"]), sampling_rate=obj["sampling_rate"],
                   wanted=tuple(obj["wanted"]), min_samples=int(obj["min_samples"]))


# --------------------------------------------------------------------------- columns


@dataclass(frozen=True)
class FileColumns:
    """Which standard columns one file has, under which names, and what to read."""

    present: dict[str, str]          # standard name -> column name in the file
    signals: tuple[str, ...]         # optional signals read from this file
    default_device: str              # device id when there is no device column

    @property
    def numeric(self) -> list[str]:
        cols = ["t"] if "t" in self.present else []
        return cols + [c for s in ("gyro", *self.signals) for c in SIGNALS[s]]


def resolve_columns(names: Sequence[str], file: str, stem: str, cfg: ReadConfig) -> FileColumns:
    """Map the file's column names to the standard schema (DataError for the file)."""
    names = [str(n).strip() for n in names]
    have = set(names)
    for std, name in cfg.columns.items():
        if name not in have:
            raise DataError(f"column {name!r} (given for {std}) is not in the file", file=file,
                            column=name)
    where = {std: cfg.columns.get(std, std) for std in
             ("device", "t", *[c for cols in SIGNALS.values() for c in cols])}
    present = {std: name for std, name in where.items() if name in have}
    if "t" not in present and cfg.sampling_rate is None:
        raise DataError("missing required column", file=file, column=where["t"],
                        hint="or give a sampling rate for files without t")
    for std in SIGNALS["gyro"]:
        if std not in present:
            raise DataError("missing required column", file=file, column=where[std])
    signals = []
    for sig in OPTIONAL_SIGNALS:
        got = [c for c in SIGNALS[sig] if c in present]
        if got and len(got) < len(SIGNALS[sig]):
            lacking = [c for c in SIGNALS[sig] if c not in present][0]
            raise DataError(f"incomplete {sig} group: {', '.join(got)} present but not {lacking}",
                            file=file, column=where[lacking])
        if got and sig in cfg.wanted:
            signals.append(sig)
    return FileColumns(present=present, signals=tuple(signals), default_device=stem)


def _stem(path: Path) -> str:
    return Path(path.name[: -len(path.suffix)] if path.suffix else path.name).name


# --------------------------------------------------------------------------- device ids


def _dictionary_ids(arr, file: str, column: str, row0: int) -> tuple[np.ndarray, np.ndarray]:
    """Device ids of a dictionary-encoded (or plain) Arrow column: (values, codes).

    Ids are stripped text; integer ids read as ``'7'`` (as :mod:`diffgyro.io` does).
    """

    if isinstance(arr, pa.ChunkedArray):
        arr = arr.combine_chunks() if arr.num_chunks != 1 else arr.chunk(0)
    if not pa.types.is_dictionary(arr.type):
        arr = arr.dictionary_encode()
    if arr.null_count:
        bad = int(np.flatnonzero(np.asarray(arr.is_null()))[0])
        raise DataError("missing device id", file=file, column=column, row=row0 + bad + 1)
    values = arr.dictionary
    if pa.types.is_floating(values.type):
        vals = [(str(int(v)) if float(v).is_integer() else repr(float(v))) if np.isfinite(v)
                else "" for v in values.to_numpy(zero_copy_only=False)]
    elif pa.types.is_integer(values.type) or pa.types.is_string(values.type) or \
            pa.types.is_large_string(values.type):
        vals = pc.utf8_trim_whitespace(pc.cast(values, pa.string())).to_pylist()
    elif pa.types.is_binary(values.type) or pa.types.is_large_binary(values.type):
        vals = [b.decode("utf-8", "replace").strip() for b in values.to_pylist()]
    else:
        raise DataError(f"device ids of type {values.type} are not text or integers",
                        file=file, column=column)
    vals_arr = np.array([("" if v is None else v) for v in vals], dtype=object)
    codes = arr.indices.to_numpy(zero_copy_only=False).astype(np.int64)
    empty = np.flatnonzero(vals_arr == "")
    if empty.size:
        rows = np.flatnonzero(np.isin(codes, empty))
        if rows.size:
            raise DataError("missing device id", file=file, column=column,
                            row=row0 + int(rows[0]) + 1)
    return vals_arr, codes


# --------------------------------------------------------------------------- index


@dataclass
class DatasetIndex:
    """Devices in dataset order (file order, then first appearance) and where they live.

    ``locations[device] = (file index, row groups)``; row groups are ``None`` for
    files read whole (CSV/NPZ). ``duplicates`` names devices found in more than
    one file: they are reported as failures, never fitted.
    """

    files: list[str]
    devices: list[str]
    locations: dict[str, tuple[int, tuple[int, ...] | None]]
    n_rows: dict[str, int]
    duplicates: dict[str, list[int]]
    missing_signal: dict[str, str]   # device -> signal its file lacks (that the model needs)


def _parquet_file(path: Path, device_col: str | None):

    try:
        schema = pq.read_schema(path)
        read_dict = []
        if device_col is not None and device_col in schema.names:
            typ = schema.field(device_col).type
            if pa.types.is_string(typ) or pa.types.is_large_string(typ) or pa.types.is_binary(typ):
                read_dict = [device_col]
        return pq.ParquetFile(path, read_dictionary=read_dict)
    except Exception as err:  # pyarrow raises several types for corrupt files
        raise DataError(f"cannot read as Parquet ({type(err).__name__}: {err})",
                        file=str(path)) from None


def _column_names(pf) -> list[str]:
    return [str(n) for n in pf.schema_arrow.names]


def _check_numeric(pf, cols: FileColumns, file: str) -> None:

    schema = pf.schema_arrow
    for std in cols.numeric:
        name = cols.present[std]
        typ = schema.field(name).type
        if not (pa.types.is_floating(typ) or pa.types.is_integer(typ) or pa.types.is_decimal(typ)):
            raise DataError(f"holds {typ} values, not numbers", file=file, column=name)


def index_dataset(paths: Sequence[Path], cfg: ReadConfig,
                  needed: Sequence[str] = ()) -> DatasetIndex:
    """Scan the device column of every file; DataError for file-level problems.

    ``needed`` lists optional signals the model cannot do without: a file
    lacking one makes its devices fail (recorded), and no file having it stops
    the run here.
    """

    files = [str(p) for p in paths]
    devices: list[str] = []
    locations: dict[str, tuple[int, tuple[int, ...] | None]] = {}
    n_rows: dict[str, int] = {}
    duplicates: dict[str, list[int]] = {}
    missing_signal: dict[str, str] = {}
    any_has = dict.fromkeys(needed, False)

    def add(dev: str, k: int, rgs, n: int, lacking: str | None) -> None:
        if dev in locations:
            owner = locations[dev][0]
            if owner != k:
                dup = duplicates.setdefault(dev, [owner])
                if k not in dup:
                    dup.append(k)
                return
            rg_old = locations[dev][1] or ()
            locations[dev] = (k, tuple(sorted(set(rg_old) | set(rgs or ()))))
            n_rows[dev] += n
            return
        devices.append(dev)
        locations[dev] = (k, None if rgs is None else tuple(rgs))
        n_rows[dev] = n
        if lacking:
            missing_signal[dev] = lacking

    for k, path in enumerate(paths):
        file = str(path)
        if path.suffix.lower() not in PARQUET_SUFFIXES:
            report = io.LoadReport()
            recs = io.load(path, cfg.columns, cfg.units, drop_invalid=cfg.drop_invalid,
                           sampling_rate=cfg.sampling_rate, min_samples=cfg.min_samples,
                           report=report)
            for r in recs:
                have = set(r.signals)
                lacking = next((s for s in needed if s not in have), None)
                for s in needed:
                    any_has[s] |= s in have
                add(r.device, k, None, r.n, lacking)
            continue
        pf = _parquet_file(path, cfg.columns.get("device", "device"))
        cols = resolve_columns(_column_names(pf), file, _stem(path), cfg)
        _check_numeric(pf, cols, file)
        lacking = next((s for s in needed if s not in cols.signals), None)
        for s in needed:
            any_has[s] |= s in cols.signals
        meta = pf.metadata
        if "device" not in cols.present:
            total = meta.num_rows
            if total:
                add(cols.default_device, k, range(meta.num_row_groups), total, lacking)
            continue
        for rg, dev, n in _row_group_devices(pf, cols.present["device"], file):
            add(dev, k, (rg,), n, lacking)
    for s, ok in any_has.items():
        if not ok:
            raise DataError(f"the model needs signal {s!r} ({', '.join(SIGNALS[s])}), "
                            "and no input file has it", file=files[0])
    if not devices:
        raise DataError("no data rows in the input files", file=files[0])
    return DatasetIndex(files=files, devices=devices, locations=locations, n_rows=n_rows,
                        duplicates=duplicates, missing_signal=missing_signal)


def _row_group_devices(pf, column: str, file: str):
    """(row group, device id, rows) for every device in every row group of a Parquet file,
    in order of first appearance within each group."""
    meta = pf.metadata
    row0 = 0
    for rg in range(meta.num_row_groups):
        col = pf.read_row_group(rg, columns=[column]).column(0)
        vals, codes = _dictionary_ids(col, file, column, row0)
        counts = np.bincount(codes, minlength=len(vals))
        first = np.full(len(vals), len(codes))
        np.minimum.at(first, codes, np.arange(len(codes)))
        # several dictionary entries can strip to one id: merge them in order of appearance
        merged: dict[str, int] = {}
        for j in np.argsort(first, kind="stable"):
            if counts[j]:
                merged[vals[j]] = merged.get(vals[j], 0) + int(counts[j])
        for dev, n in merged.items():
            yield rg, dev, n
        row0 += meta.row_group(rg).num_rows


# --------------------------------------------------------------------------- reading a chunk


def read_devices(files: Sequence[str], sources: Sequence[tuple[int, Sequence[int] | None]],
                 devices: Sequence[str], cfg: ReadConfig
                 ) -> tuple[dict[str, Recording], dict[str, DataError]]:
    """Recordings of ``devices`` (validated one by one) and the failures, by device.

    ``sources`` lists ``(file index, row groups)`` to read (``None``: the whole
    file through :func:`diffgyro.io.load`).
    """

    want = set(devices)
    recs: dict[str, Recording] = {}
    errors: dict[str, DataError] = {}
    for k, rgs in sources:
        path = Path(files[k])
        file = str(path)
        if rgs is None:
            try:
                loaded = io.load(path, cfg.columns, cfg.units, drop_invalid=cfg.drop_invalid,
                                 sampling_rate=cfg.sampling_rate, min_samples=cfg.min_samples)
            except DataError as err:
                for d in want - set(recs) - set(errors):
                    errors[d] = err
                continue
            for r in loaded:
                if r.device in want:
                    recs[r.device] = _only_wanted(r, cfg)
            continue
        pf = _parquet_file(path, cfg.columns.get("device", "device"))
        cols = resolve_columns(_column_names(pf), file, _stem(path), cfg)
        numeric = cols.numeric
        names = [cols.present[c] for c in numeric]
        parts: dict[str, list[np.ndarray]] = {c: [] for c in numeric}
        ids_parts, row_parts = [], []
        offsets = np.cumsum([0] + [pf.metadata.row_group(i).num_rows
                                   for i in range(pf.metadata.num_row_groups)])
        for rg in rgs:
            if "device" in cols.present:
                dcol = pf.read_row_group(rg, columns=[cols.present["device"]]).column(0)
                vals, codes = _dictionary_ids(dcol, file, cols.present["device"], int(offsets[rg]))
                keep_val = np.fromiter((v in want for v in vals), bool, len(vals))
                mask = keep_val[codes]
                if not mask.any():
                    continue
                ids = vals[codes[mask]]
            else:
                n = int(offsets[rg + 1] - offsets[rg])
                mask = np.ones(n, bool)
                ids = np.full(n, cols.default_device, dtype=object)
            table = pf.read_row_group(rg, columns=names)
            if not mask.all():

                table = table.filter(pa.array(mask))
            for c, name in zip(numeric, names):
                parts[c].append(_as_float(table.column(name)))
            ids_parts.append(ids)
            row_parts.append(np.flatnonzero(mask) + int(offsets[rg]) + 1)
            del table
        if not ids_parts:
            continue
        ids = np.concatenate(ids_parts)
        rows = np.concatenate(row_parts)
        values = {c: np.concatenate(parts[c]) for c in numeric}
        del parts

        codes, uniques = pd.factorize(ids, sort=False)
        order = np.argsort(codes, kind="stable")
        bounds = np.cumsum(np.bincount(codes, minlength=len(uniques)))[:-1]
        for dev, idx in zip(uniques.tolist(), np.split(order, bounds)):
            try:
                recs[dev] = _recording(dev, file, cols, {c: v[idx] for c, v in values.items()},
                                       rows[idx], cfg)
            except DataError as err:
                errors[dev] = err
    return recs, errors


def _as_float(col) -> np.ndarray:

    if not pa.types.is_float64(col.type):
        col = pc.cast(col, pa.float64())
    return np.asarray(col.to_numpy(), dtype=np.float64)


def _only_wanted(rec: Recording, cfg: ReadConfig) -> Recording:
    """The recording with just the signals a Parquet read would give (same fit inputs)."""
    kw = {s: (getattr(rec, s) if s in cfg.wanted else None) for s in OPTIONAL_SIGNALS}
    return Recording(t=rec.t, gyro=rec.gyro, **kw, device=rec.device, source=rec.source)


def _recording(dev: str, file: str, cols: FileColumns, values: dict[str, np.ndarray],
               rows: np.ndarray, cfg: ReadConfig) -> Recording:
    """One device's rows as a validated Recording in SI units (DataError otherwise)."""

    numeric = cols.numeric
    k_index = np.arange(rows.shape[0], dtype=np.float64)
    raw = [values[c] for c in numeric]
    si, code = check_cells(raw, numeric, cfg.conv)
    bad_rows = code.any(axis=1)
    if bad_rows.any():
        first = int(np.flatnonzero(bad_rows)[0])
        if not cfg.drop_invalid:
            j = int(np.flatnonzero(code[first])[0])
            problem, hint = cell_problem(int(code[first, j]), float(raw[j][first]), numeric[j],
                                         cfg.conv)
            raise DataError(problem, file=file, device=dev, column=cols.present[numeric[j]],
                            row=int(rows[first]), hint=hint.replace(" (drop_invalid=True)", ""))
        keep = ~bad_rows
        si, rows, k_index = si[keep], rows[keep], k_index[keep]
    values = {c: si[:, j] for j, c in enumerate(numeric)}
    n = rows.shape[0]
    if n < cfg.min_samples:
        dropped = " after dropping invalid rows" if bad_rows.any() else ""
        raise DataError(f"{n} sample{'' if n == 1 else 's'}{dropped}: fewer samples than "
                        f"loading needs ({cfg.min_samples})", file=file, device=dev)
    fields: dict[str, np.ndarray] = {}
    fields["t"] = np.ascontiguousarray(values["t"]) if "t" in values else \
        k_index / float(cfg.sampling_rate)
    fields["gyro"] = np.stack([values[c] for c in SIGNALS["gyro"]], axis=1)
    for sig in cols.signals:
        names = SIGNALS[sig]
        fields[sig] = np.ascontiguousarray(values[names[0]] if len(names) == 1 else np.stack(
            [values[c] for c in names], axis=1))
    t = fields["t"]
    step = np.diff(t)
    back = np.flatnonzero(~(step > 0))
    if back.size:
        k = int(back[0]) + 1
        if t[k] == t[k - 1]:
            problem = f"time {float(t[k])!r} s repeats row {int(rows[k - 1])} (time must strictly increase)"
        else:
            problem = (f"time goes backwards: {float(t[k])!r} s after {float(t[k - 1])!r} s on "
                       f"row {int(rows[k - 1])} (time must strictly increase)")
        raise DataError(problem, file=file, device=dev, column=cols.present.get("t", "t"),
                        row=int(rows[k]))
    rec = Recording(**fields, device=dev, source=file)
    _check_units(rec, file, cols, cfg)
    return rec


def _check_units(rec: Recording, file: str, cols: FileColumns, cfg: ReadConfig) -> None:
    """Refuse a device whose numbers are only plausible in another unit than the assumed SI
    (:mod:`diffgyro.io._plausible`, per device here: a chunk does not see the whole file;
    the warnings' lines are given where the file is read whole, by :func:`diffgyro.io.load`)."""

    assumed = {sig for sig in ("t", "gyro", "accel", "temp") if sig not in cfg.units}
    named = {sig: ", ".join(cols.present[c] for c in SIGNALS[sig])
             for sig in ("gyro", *cols.signals) if sig in ("gyro", "accel", "temp")}
    if "t" in cols.present:
        named["t"] = cols.present["t"]
    try:
        check_plausible([rec], file, assumed, named)
    except DataError as err:
        raise DataError(err.problem, file=file, device=rec.device, column=err.column,
                        hint=err.hint) from None
