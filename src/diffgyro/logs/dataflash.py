"""ArduPilot DataFlash logs (binary ``.bin`` and text ``.log``) via pymavlink.

Each IMU instance is the device ``<stem>/imu<k>``: the ``I`` field of
``IMU`` messages gives k (older logs write ``IMU``, ``IMU2``, ``IMU3`` for
k = 0, 1, 2). ``GyrX, GyrY, GyrZ`` (rad/s) → ``gx, gy, gz``, ``AccX, AccY,
AccZ`` (m/s²) → ``ax, ay, az``, ``T`` (°C) → ``temp``, ``TimeUS`` (µs since
boot) → ``t`` in s. Samples are kept as logged.
"""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import numpy as np

from ..errors import DataError
from .table import LogTable, cut_at, require, table, truncated

_TYPES = ["IMU", "IMU2", "IMU3"]
_HEAD = b"\xa3\x95"  # every binary message starts with these
_FIELDS = ("TimeUS", "GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ")


def _binary_cut(log) -> int | None:
    """Where a binary log's last message is cut off (``None``: it ends after a whole one).

    pymavlink indexes every message header it finds (``offsets`` by type) and stops at
    the end without a word; the last indexed message must end exactly at the file's end.
    """
    last = max(((offs[-1], t) for t, offs in enumerate(log.offsets) if offs), default=None)
    if last is None or last[1] not in log.formats:
        return None
    start, end = last[0], last[0] + log.formats[last[1]].len
    if end > log.data_len:
        return start
    rest = bytes(log.data_map[end:end + 2])
    # bytes after the last whole message: a cut-off header, or padding pymavlink ignores
    return end if rest and _HEAD.startswith(rest) else None


def _text_cut(path: Path) -> int | None:
    """Where a text log's last line is cut off: it has no line end (pymavlink skips it)."""
    with open(path, "rb") as fh:
        size = fh.seek(0, 2)
        fh.seek(max(0, size - 65536))
        tail = fh.read()
    if not tail or tail.endswith(b"\n"):
        return None
    at = tail.rfind(b"\n")
    return size - len(tail) + at + 1 if at >= 0 else (0 if size <= 65536 else None)


@contextlib.contextmanager
def _quiet_fd(fd: int):
    """Send what is written to file descriptor ``fd`` to the null device meanwhile."""
    try:
        saved = os.dup(fd)
    except OSError:  # no such descriptor (an embedded interpreter): nothing to quiet
        yield
        return
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, fd)
        yield
    finally:
        os.dup2(saved, fd)
        os.close(saved)
        os.close(null)


def _messages(path: Path, file: str) -> tuple[dict[int, list[tuple]], int | None]:
    dfreader = require("pymavlink.DFReader", "pymavlink", file)
    text = path.suffix.lower() == ".log"
    rows: dict[int, list[tuple]] = {}
    has_temp: dict[int, bool] = {}
    try:
        # pymavlink prints on bad data (Python's stdout and stderr, and its C indexer
        # straight to file descriptor 2): our one line says it
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
                _quiet_fd(2):
            log = (dfreader.DFReader_text if text else dfreader.DFReader_binary)(
                str(path), zero_time_base=False)
            while (m := log.recv_match(type=_TYPES)) is not None:
                kind = m.get_type()
                k = int(getattr(m, "I", _TYPES.index(kind) if kind in _TYPES else 0))
                names = m.get_fieldnames()
                has_temp[k] = has_temp.get(k, True) and "T" in names
                rows.setdefault(k, []).append(
                    tuple(float(getattr(m, f)) for f in _FIELDS)
                    + (float(m.T) if "T" in names else np.nan,))
            cut = _text_cut(path) if text else _binary_cut(log)
    except DataError:
        raise
    except Exception as err:  # pymavlink raises struct, index, value and OS errors
        raise DataError(f"cannot read as ArduPilot DataFlash ({type(err).__name__}: {err})",
                        file=file) from None
    return {k: (v, has_temp[k]) for k, v in rows.items()}, cut


def read(path: Path, file: str, prefix: str) -> LogTable:
    """Read ``path`` (a DataFlash log) as a :class:`LogTable`; see the module docstring."""
    found, cut = _messages(path, file)
    size = path.stat().st_size
    if not found:
        end = (f"; the file is truncated: {cut_at(cut, size)}"
               if cut is not None else "")
        raise DataError(f"no gyro data in the log (no IMU messages{end})", file=file)
    devices = []
    for k in sorted(found):
        rows, has_temp = found[k]
        v = np.asarray(rows, dtype=np.float64)
        dev = {"device": f"{prefix}/imu{k}", "t": v[:, 0] * 1e-6, "gyro": v[:, 1:4],
               "accel": v[:, 4:7]}
        if has_temp:
            dev["temp"] = v[:, 7]
        devices.append(dev)
    return table(devices, file, [truncated(file, cut, size, devices)] if cut is not None else [])
