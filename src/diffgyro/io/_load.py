"""Loading files into recordings and batches, every cell checked."""

from __future__ import annotations

import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import OPTIONAL_SIGNALS, SIGNALS, STANDARD_COLUMNS, Batch, Recording, as_slice
from ..errors import DataError
from ..logs import log_format
from ._cells import cell_problem, check_cells
from ._columns import check_columns
from ._convert import DeviceIds, device_ids, label, to_float
from ._headers import header_units, merge_units
from ._plausible import check_plausible
from ._reports import Dropped, LoadReport, UnitNote
from ._source import COMPRESSION, Source, is_number, release_read_buffers
from ._units import resolve_units


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
    check_units: bool = True,
    channel: str = "gyro",
) -> list[Recording]:
    """Read recordings from CSV / Parquet / NPZ files in the standard schema, or logs.

    **Arguments:**

    - ``paths``: one file or many; a device id may appear in only one file.
    - ``columns``: standard name -> name in the file (``{"gx": "gyr_x"}``);
      see :func:`parse_columns` for the command-line form.
    - ``units``: signal -> unit of the file (``{"gyro": "deg/s", "temp": "K"}``),
      converted to SI at load; see :func:`resolve_units`.
    - ``drop_invalid``: skip rows with empty/NaN/inf cells (counted in
      ``report``) instead of raising.
    - ``sampling_rate``: Hz; files without a ``t`` column get ``t = k / rate``
      (k = the sample's index within its device in the file).
    - ``device``: id for files without a ``device`` column (default: file stem).
    - ``min_samples``: fewer samples in a device is an error.
    - ``report``: a :class:`LoadReport` that receives the dropped-row counts
      and the log readers' warnings (without one they are issued with
      :func:`warnings.warn`).
    - ``topic``: ROS bags: the ``sensor_msgs/msg/Imu`` topic(s), comma-separated
      (default: all).
    - ``temp_topic``: ROS bags: the ``sensor_msgs/msg/Temperature`` topic.
    - ``check_units``: check that the numbers of each signal whose unit nobody
      stated are plausible in SI (:mod:`diffgyro.io._plausible`).
    - ``channel``: the sensor to be calibrated (:mod:`diffgyro.channel`): a PX4 ULog read
      for ``accel`` gives one device per ``sensor_accel`` instance, with its own
      times, temperature and device id (:mod:`diffgyro.logs`); other files load
      the same either way.

    A table's headers may carry units, ``Gyroscope X (deg/s)`` or
    ``acc_x[g]`` (:mod:`diffgyro.io._headers`): they are converted like
    ``units``, and the column is mapped when its name is recognisable; a
    ``units`` entry that contradicts a header is an error. Each file's header
    units and each implausible signal give one line in ``report.units``.

    Logs (``.ulg``, ``.bag``, ``.mcap``, a rosbag2 folder, ``.bin``, ``.log``)
    are read by :mod:`diffgyro.logs`; ``device`` then replaces the file stem
    at the start of their device ids.

    Returns one :class:`Recording` per device, in file order, then
    first-appearance order within a file.
    """
    columns = check_columns(columns)
    resolve_units(units)  # an unknown unit fails before any file is read
    units = dict(units or {})
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
    log_options = {"topic": topic, "temp_topic": temp_topic, "channel": channel}
    for path in _as_paths(paths):
        for rec in _load_file(path, columns, units, drop_invalid, sampling_rate, device,
                              min_samples, report, log_options, check_units):
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
    check_units: bool = True,
    channel: str = "gyro",
) -> Batch:
    """:func:`load`, then :meth:`Batch.from_recordings` (padded to a bucket length).

    **Arguments:**

    - ``paths``: one file or many, as for :func:`load`.
    - ``columns``: standard name -> name in the file.
    - ``units``: signal -> unit of the file.
    - ``drop_invalid``: skip rows with invalid cells instead of raising.
    - ``sampling_rate``: Hz, for files without a ``t`` column.
    - ``device``: id for files without a ``device`` column.
    - ``min_samples``: fewer samples in a device is an error.
    - ``report``: a :class:`LoadReport` that receives the dropped rows and warnings.
    - ``length``: the padded length (default: from the longest device).
    - ``bucket``: pad to a bucket length (:func:`diffgyro.data.bucket_length`), so that
      slightly different lengths reuse compiled programs.
    - ``check_units``: check that signals in an assumed SI unit are plausible.
    - ``channel``: the sensor to be calibrated, ``"gyro"`` or ``"accel"``.
    """
    recs = load(paths, columns, units, drop_invalid, sampling_rate, device,
                min_samples=min_samples, report=report, check_units=check_units,
                channel=channel)
    return Batch.from_recordings(recs, length=length, bucket=bucket)


def _load_file(path, columns, units, drop_invalid, sampling_rate, device, min_samples,
               report, log_options=None, check_units=True) -> list[Recording]:
    """The recordings of one file: its layout found, its cells read and checked per device,
    the units of the signals nobody gave a unit for checked for plausibility."""
    src = _open(path, device, log_options, report)
    assumed: set[str] = set()
    if src.log is None:  # a log's reader gives SI units; a table may say its units
        header = header_units(src.names, columns, src.file)
        units = merge_units(header, units, src.file)
        columns = {**header.columns, **columns}
        if header.units:
            _note(report, UnitNote(src.file, "", "mapped", header.describe()))
        assumed = {sig for sig in ("t", "gyro", "accel", "temp") if sig not in units}
    conv = resolve_units(units)
    lay = _layout(src, path, columns, device, sampling_rate)
    devices, values, aux_all = _read(src, lay, columns, report)
    # group rows by device: first-appearance order, file order within a device
    order = np.argsort(devices.codes, kind="stable")
    bounds = np.cumsum(np.bincount(devices.codes, minlength=len(devices.names)))[:-1]
    recordings = [_device_recording(dev, rows, values, aux_all, lay, conv, drop_invalid,
                                    sampling_rate, min_samples, report)
                  for dev, rows in zip(devices.names, np.split(order, bounds), strict=True)]
    del values, aux_all  # may be views of the file reader's buffers
    release_read_buffers()
    if check_units and assumed:
        named = {sig: ", ".join(label(c, lay.present[c]) for c in SIGNALS[sig])
                 for sig in ("gyro", "accel", "temp") if sig in lay.signals}
        if "t" in lay.present:
            named["t"] = label("t", lay.present["t"])
        for note in check_plausible(recordings, lay.file, assumed, named):
            _note(report, note)
    return recordings


def _note(report, note: UnitNote) -> None:
    if report is not None:
        report.units.append(note)
    else:
        warnings.warn(note.message(), stacklevel=4)  # the caller of load()


def _open(path: Path, device, log_options, report) -> Source:
    """The opened file; a log reader's warnings go to ``report`` (or are issued)."""
    file = str(path)
    if not path.exists():
        raise DataError("file not found", file=file)
    if not path.is_file() and log_format(path) != "rosbag":
        raise DataError("not a file", file=file)
    if device is not None and log_format(path):
        log_options = {**(log_options or {}), "prefix": str(device).strip()}
    src = Source(path, file, log_options)
    for line in src.log.warnings if src.log is not None else []:
        _tell(report, report.warnings if report is not None else None, line)
    if src.log is not None and report is not None:
        report.device_ids.update({dev: int(meta["device_id"]) for dev, meta in
                                  src.log.metadata.items() if "device_id" in meta})
    return src


def _tell(report, lines: list[str] | None, line: str) -> None:
    if report is not None:
        lines.append(line)
    else:
        warnings.warn(line, stacklevel=5)  # the caller of load()


@dataclass(frozen=True)
class _Layout:
    """Where the standard columns are in one file and which signal groups it holds."""

    file: str
    present: dict[str, str]  # standard name -> file column
    where: dict[str, str]    # standard name -> the file column it would be read from ("" none)
    signals: list[str]       # "gyro" and the complete optional groups
    numeric: list[str]       # the standard numeric columns read, "t" first when present
    default_device: str      # the device id of a file without a device column


def _layout(src: Source, path: Path, columns: Mapping[str, str], device,
            sampling_rate) -> _Layout:
    """The file's layout; a missing required column or an incomplete group is an error."""
    file, names = src.file, set(src.names)
    found = ", ".join(n for n in src.names[:12] if n) + (" ..." if len(src.names) > 12 else "")

    def hint_for_missing() -> str:
        if len(src.names) == 1 and any(s in src.names[0] for s in (";", "\t", ",")):
            return f"the header is one column {src.names[0]!r}: check the separator"
        if src.names and all(is_number(n) for n in src.names if n):
            return "the file seems to have no header line"
        return f"columns in the file: {found}; map others with --columns std=name"

    # a file column mapped to one standard name does not also serve under its own name
    claimed = set(columns.values())
    where = {std: columns.get(std, std if std not in claimed else "") for std in STANDARD_COLUMNS}
    for std, name in columns.items():
        if name not in names:
            raise DataError(f"column {name!r} (given for {std}) is not in the file",
                            file=file, column=name, hint=hint_for_missing())
    present = {std: name for std, name in where.items() if name and name in names}
    stem = path.name
    if path.suffix.lower() in COMPRESSION:
        stem = stem[: -len(path.suffix)]
    default_device = str(device).strip() if device is not None else Path(stem).stem
    dev_label = None if "device" in present else default_device

    if "t" not in present and sampling_rate is None:
        raise DataError("missing required column", file=file, device=dev_label,
                        column=label("t", where["t"]),
                        hint=hint_for_missing() + "; or give a sampling rate for files without t")
    for std in SIGNALS["gyro"]:
        if std not in present:
            raise DataError("missing required column", file=file, device=dev_label,
                            column=label(std, where[std]), hint=hint_for_missing())
    signals = ["gyro"]
    for sig in OPTIONAL_SIGNALS:
        have = [c for c in SIGNALS[sig] if c in present]
        if have and len(have) < len(SIGNALS[sig]):
            lacking = [c for c in SIGNALS[sig] if c not in present][0]
            raise DataError(
                f"incomplete {sig} group: {', '.join(have)} present but not {lacking}",
                file=file, device=dev_label, column=label(lacking, where[lacking]),
                hint=f"{sig} needs all of {', '.join(SIGNALS[sig])}")
        if have:
            signals.append(sig)
    numeric = (["t"] if "t" in present else []) + [c for s in signals for c in SIGNALS[s]]
    return _Layout(file, present, where, signals, numeric, default_device)


def _read(src: Source, lay: _Layout, columns: Mapping[str, str], report):
    """Device id per row, the standard numeric columns (one array each, file units) and
    the numeric extra columns by name; text extra columns are ignored with one line."""
    file, present = lay.file, lay.present
    wanted_std = (["device"] if "device" in present else []) + lay.numeric
    extra, ignored = _extra_columns(src, columns, present)
    frame = src.read([present[s] for s in wanted_std] + list(extra.values()),
                     {present["device"]} if "device" in present else set())
    n = len(frame)
    if n == 0:
        raise DataError("no data rows (header only)", file=file,
                        device=None if "device" in present else lay.default_device)
    if "device" in present:
        devices = device_ids(frame[present["device"]], file, label("device", present["device"]))
    else:
        devices = DeviceIds.single(n, lay.default_device)
    values = [to_float(frame[present[std]], file, label(std, present[std]), devices)
              for std in lay.numeric]
    aux_all: dict[str, np.ndarray] = {}
    for name, col in extra.items():
        try:
            aux_all[name] = to_float(frame[col], file, col, devices)
        except DataError:  # text further down than the first rows
            ignored.append(col)
    if ignored:
        _tell(report, report.ignored if report is not None else None,
              f"ignored non-numeric column{'s' if len(ignored) > 1 else ''} "
              f"{', '.join(sorted(ignored))} in file {file}")
    return devices, values, aux_all


def _device_recording(dev: str, rows, values, aux_all, lay: _Layout, conv, drop_invalid,
                      sampling_rate, min_samples, report) -> Recording:
    """One device's recording from its rows: cells checked (or invalid rows dropped), SI
    units, the time base checked."""
    file, present, numeric = lay.file, lay.present, lay.numeric
    take = as_slice(rows)  # a device's rows are usually one run of the file: views
    own = [v[take] for v in values]
    si, code = check_cells(own, numeric, conv)
    k_index = np.arange(rows.shape[0], dtype=np.float64)  # position within the device
    bad_rows = code.any(axis=1)
    if bad_rows.any():
        first = int(np.flatnonzero(bad_rows)[0])
        if not drop_invalid:
            j = int(np.flatnonzero(code[first])[0])
            problem, hint = cell_problem(int(code[first, j]), float(values[j][rows[first]]),
                                         numeric[j], conv)
            raise DataError(problem, file=file, device=dev,
                            column=label(numeric[j], present[numeric[j]]),
                            row=int(rows[first]) + 1, hint=hint)
        if report is not None:
            report.dropped.append(Dropped(file, dev, int(bad_rows.sum()), int(rows[first]) + 1))
        keep = ~bad_rows
        si, rows, k_index = si[keep], rows[keep], k_index[keep]
    # extra columns may hold gaps: checked when a model uses them (diffgyro._aux)
    aux = {name: np.ascontiguousarray(a[rows]) for name, a in aux_all.items()}
    # every signal its own array (copied out of si, which is then freed)
    cols = {std: si[:, j] for j, std in enumerate(numeric)}
    fields: dict[str, np.ndarray] = {
        "t": np.array(cols["t"]) if "t" in cols else k_index / sampling_rate}
    for sig in lay.signals:
        members = SIGNALS[sig]
        fields[sig] = np.array(cols[members[0]]) if len(members) == 1 else \
            np.stack([cols[c] for c in members], 1)
    _check_time(fields["t"], rows, file, dev,
                label("t", present["t"]) if "t" in present else "t (from sampling rate)",
                several="device" in present)
    rec = Recording(**fields, device=dev, source=file, aux=aux)
    if rec.n < min_samples:
        dropped = " after dropping invalid rows" if drop_invalid and bad_rows.any() else ""
        raise DataError(
            f"{rec.n} sample{'' if rec.n == 1 else 's'}{dropped}: "
            f"fewer samples than loading needs ({min_samples})", file=file, device=dev)
    return rec


def _extra_columns(src: Source, columns: Mapping[str, str],
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


