"""PX4 ULog (``.ulg``) via pyulog: ``sensor_gyro`` instances as devices.

Each ``sensor_gyro`` instance (``multi_id`` k) is the device ``<stem>/gyro<k>``:
``x, y, z`` (rad/s) → ``gx, gy, gz``, ``temperature`` (°C) → ``temp``, time
``timestamp_sample`` (µs since boot; ``timestamp`` when absent) → ``t`` in s.
The ``sensor_accel`` instance with the same ``multi_id`` gives ``ax, ay, az``
(m/s²), linearly interpolated at the gyro's times. Samples are kept as
logged: a dropped sample stays a gap in ``t``, nothing is resampled.

When no ``sensor_gyro`` instance is logged at 10 samples/s or more (PX4 logs
it at 1 Hz by default; ``SDLOG_PROFILE`` raises it), the gyro comes from
``sensor_combined`` instead: one device ``<stem>/sensor_combined``,
``gyro_rad`` at ``timestamp`` and no temperature, with one warning line.
The sensor's ``device_id`` is kept in :attr:`LogTable.metadata`
(``{"device_id": ...}``); PX4 matches temperature-compensation slots by it.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from ..errors import DataError
from .table import LogTable, interp_join, require, table

MIN_RATE = 10.0  # samples per second below which sensor_gyro is "not logged at rate"
_TOPICS = ["sensor_gyro", "sensor_accel", "sensor_combined"]
_INVALID_RELATIVE = 2147483647  # PX4's RELATIVE_TIMESTAMP_INVALID


def _open(path: Path, file: str):
    pyulog = require("pyulog", "pyulog", file)
    try:
        with contextlib.redirect_stdout(io.StringIO()):  # pyulog prints its warnings
            ulog = pyulog.ULog(str(path), _TOPICS)
    except Exception as err:  # pyulog raises ULogException, OSError, struct/index errors
        raise DataError(f"cannot read as PX4 ULog ({type(err).__name__}: {err})",
                        file=file) from None
    return ulog


def _seconds(d) -> np.ndarray:
    key = "timestamp_sample" if "timestamp_sample" in d.data else "timestamp"
    return np.asarray(d.data[key], dtype=np.float64) * 1e-6


def _rate(t: np.ndarray) -> float:
    return (t.size - 1) / (t[-1] - t[0]) if t.size > 1 and t[-1] > t[0] else 0.0


def _xyz(d, names) -> np.ndarray:
    return np.stack([np.asarray(d.data[n], dtype=np.float64) for n in names], axis=1)


def _gyro_devices(ulog, prefix: str) -> tuple[list[dict], dict, list]:
    gyros = sorted((d for d in ulog.data_list if d.name == "sensor_gyro"),
                   key=lambda d: d.multi_id)
    accels = {d.multi_id: d for d in ulog.data_list if d.name == "sensor_accel"}
    devices, meta, slow = [], {}, []
    for d in gyros:
        t = _seconds(d)
        if _rate(t) < MIN_RATE:
            slow.append((d.multi_id, _rate(t)))
            continue
        name = f"{prefix}/gyro{d.multi_id}"
        dev = {"device": name, "t": t, "gyro": _xyz(d, "xyz")}
        if "temperature" in d.data:
            dev["temp"] = np.asarray(d.data["temperature"], dtype=np.float64)
        acc = accels.get(d.multi_id)
        if acc is not None and _rate(_seconds(acc)) >= MIN_RATE:
            dev["accel"] = interp_join(t, _seconds(acc), _xyz(acc, "xyz"))
        if "device_id" in d.data and len(d.data["device_id"]):
            meta[name] = {"device_id": int(d.data["device_id"][-1])}
        devices.append(dev)
    return devices, meta, slow


def _combined(ulog, prefix: str) -> dict | None:
    d = next((d for d in ulog.data_list if d.name == "sensor_combined"), None)
    if d is None or len(d.data["timestamp"]) == 0:
        return None
    t = np.asarray(d.data["timestamp"], dtype=np.float64) * 1e-6
    dev = {"device": f"{prefix}/sensor_combined", "t": t,
           "gyro": _xyz(d, [f"gyro_rad[{k}]" for k in range(3)])}
    rel = np.asarray(d.data.get("accelerometer_timestamp_relative", []), dtype=np.int64)
    if rel.size == t.size and not (rel == _INVALID_RELATIVE).any():
        t_acc = t + rel * 1e-6
        if np.all(np.diff(t_acc) > 0):
            dev["accel"] = interp_join(t, t_acc,
                                       _xyz(d, [f"accelerometer_m_s2[{k}]" for k in range(3)]))
    return dev


def read(path: Path, file: str, prefix: str) -> LogTable:
    """Read ``path`` (a ULog) as a :class:`LogTable`; see the module docstring."""
    ulog = _open(path, file)
    devices, meta, slow = _gyro_devices(ulog, prefix)
    warnings = []
    if not devices:
        combined = _combined(ulog, prefix)
        if combined is None:
            broken = "; the file is corrupted" if ulog.file_corruption else ""
            raise DataError(f"no gyro data in the log (no sensor_gyro or sensor_combined "
                            f"samples{broken})", file=file)
        why = ("is not logged" if not slow else
               f"is logged at {max(r for _, r in slow):.3g} samples/s (< {MIN_RATE:g})")
        warnings.append(f"warning: file {file}: sensor_gyro {why}; reading sensor_combined "
                        f"instead (one device, no temperature)")
        devices = [combined]
    elif slow:
        left = ", ".join(str(k) for k, _ in slow)
        warnings.append(f"warning: file {file}: sensor_gyro instance(s) {left} logged at "
                        f"< {MIN_RATE:g} samples/s are left out")
    if ulog.file_corruption:
        warnings.append(f"warning: file {file}: pyulog found corrupted data and skipped it")
    out = table(devices, file, warnings)
    out.metadata = meta
    return out
