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
from pathlib import Path

import numpy as np

from ..errors import DataError
from .table import LogTable, require, table

_TYPES = ["IMU", "IMU2", "IMU3"]
_FIELDS = ("TimeUS", "GyrX", "GyrY", "GyrZ", "AccX", "AccY", "AccZ")


def _messages(path: Path, file: str) -> dict[int, list[tuple]]:
    dfreader = require("pymavlink.DFReader", "pymavlink", file)
    text = path.suffix.lower() == ".log"
    rows: dict[int, list[tuple]] = {}
    has_temp: dict[int, bool] = {}
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # pymavlink prints on bad data
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
    except DataError:
        raise
    except Exception as err:  # pymavlink raises struct, index, value and OS errors
        raise DataError(f"cannot read as ArduPilot DataFlash ({type(err).__name__}: {err})",
                        file=file) from None
    return {k: (v, has_temp[k]) for k, v in rows.items()}


def read(path: Path, file: str, prefix: str) -> LogTable:
    """Read ``path`` (a DataFlash log) as a :class:`LogTable`; see the module docstring."""
    found = _messages(path, file)
    if not found:
        raise DataError("no gyro data in the log (no IMU messages)", file=file)
    devices = []
    for k in sorted(found):
        rows, has_temp = found[k]
        v = np.asarray(rows, dtype=np.float64)
        dev = {"device": f"{prefix}/imu{k}", "t": v[:, 0] * 1e-6, "gyro": v[:, 1:4],
               "accel": v[:, 4:7]}
        if has_temp:
            dev["temp"] = v[:, 7]
        devices.append(dev)
    return table(devices, file)
