"""PX4 ULog (``.ulg``) via pyulog: ``sensor_gyro`` instances as devices.

Each ``sensor_gyro`` instance (``multi_id`` k) is the device ``<stem>/gyro<k>``:
``x, y, z`` (rad/s) → ``gx, gy, gz``, ``temperature`` (°C) → ``temp``, time
``timestamp_sample`` (µs since boot; ``timestamp`` when absent) → ``t`` in s.
The ``sensor_accel`` instance with the same ``multi_id`` gives ``ax, ay, az``
(m/s²), linearly interpolated at the gyro's times. Samples are kept as
logged: a dropped sample stays a gap in ``t``, nothing is resampled.

When no ``sensor_gyro`` instance is logged at 10 samples/s or more (PX4 logs
it at 1 Hz by default; ``SDLOG_PROFILE`` raises it) and no ``sensor_gyro_fifo``
is logged, the gyro comes from
``sensor_combined`` instead: one device ``<stem>/sensor_combined``,
``gyro_rad`` at ``timestamp`` and no temperature, with one warning line.
The sensor's ``device_id`` is kept in :attr:`LogTable.metadata`
(``{"device_id": ...}``); PX4 matches temperature-compensation slots by it.

``sensor_gyro_fifo`` instance k (every sample the sensor's FIFO gave, logged
by PX4's raw-FIFO profile) is the device ``<stem>/gyro_fifo<k>``: each message
holds ``samples`` = N readings ``x[n], y[n], z[n]`` (int16 counts) that are
``scale`` rad/s each, ``dt`` µs apart, the last of them taken at
``timestamp_sample`` (PX4's filters publish the last FIFO sample at that time),
so reading n is at ``timestamp_sample - (N - 1 - n)·dt``. ``sensor_accel_fifo``
k is unpacked the same way (m/s²) and interpolated at the gyro's times; the
temperature is ``sensor_gyro`` k's, interpolated (it is logged at 1 Hz or
more, and changes far slower).

Read for the accelerometer channel (``channel="accel"``), each ``sensor_accel``
instance k logged at rate is the device ``<stem>/accel<k>`` on its own: ``x, y, z``
(m/s²) → ``ax, ay, az`` at its own times, its own ``temperature`` and its own
``device_id`` (PX4 matches ``TC_A`` slots by it; an accelerometer's instance number
need not be its gyro's). The gyro columns, which judge whether the board was at rest,
are ``sensor_gyro`` instance k's (else the first instance logged at rate),
interpolated at the accelerometer's times.
"""

from __future__ import annotations

import contextlib
import io
from pathlib import Path

import numpy as np

from ..errors import DataError
from ._table import LogTable, cut_at, interp_join, require, table, truncated

MIN_RATE = 10.0  # samples per second below which sensor_gyro is "not logged at rate"
_TOPICS = ["sensor_gyro", "sensor_accel", "sensor_combined", "sensor_gyro_fifo",
           "sensor_accel_fifo"]
_INVALID_RELATIVE = 2147483647  # PX4's RELATIVE_TIMESTAMP_INVALID


class _CutWatch:
    """The file as pyulog reads it, noting where a message is cut off by the end of the file.

    pyulog reads each message as its 3-byte header (payload size, type), then the payload
    of that size, and stops without a word when either read comes up short; ``cut`` is
    then the offset of that message's header (``None``: the file ends between messages).
    """

    def __init__(self, fh):
        self._fh, self._pos = fh, 0
        self._header, self._payload = 0, None  # last header's offset, its payload size
        self.cut: int | None = None

    def read(self, n: int = -1) -> bytes:
        data = self._fh.read(n)
        start, self._pos = self._pos, self._pos + len(data)
        if self._payload is not None and n == self._payload:
            if len(data) < n and self.cut is None:
                self.cut = self._header
            self._payload = None
        elif n == 3:
            self._header = start
            self._payload = int.from_bytes(data[:2], "little") if len(data) == 3 else None
            if 0 < len(data) < 3 and self.cut is None:
                self.cut = start
        else:
            self._payload = None
        return data

    def seek(self, offset: int, whence: int = 0) -> int:
        self._pos = self._fh.seek(offset, whence)
        self._payload = None
        return self._pos

    def tell(self) -> int:
        return self._pos

    def close(self) -> None:
        self._fh.close()


def _open(path: Path, file: str):
    """The parsed log and, when its last message is cut off, the offset of that message."""
    pyulog = require("pyulog", "pyulog", file)
    try:
        with open(path, "rb") as fh, contextlib.redirect_stdout(io.StringIO()):
            watch = _CutWatch(fh)  # pyulog prints its warnings: kept off stdout
            ulog = pyulog.ULog(watch, _TOPICS)
    except Exception as err:  # pyulog raises ULogException, OSError, struct/index errors
        raise DataError(f"cannot read as PX4 ULog ({type(err).__name__}: {err})",
                        file=file) from None
    return ulog, watch.cut


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


def _accel_devices(ulog, prefix: str, file: str) -> tuple[list[dict], dict, list[str]]:
    """One device per ``sensor_accel`` instance at rate, its ``device_id``, and warnings."""
    accels = sorted((d for d in ulog.data_list if d.name == "sensor_accel"),
                    key=lambda d: d.multi_id)
    gyros = {d.multi_id: d for d in ulog.data_list
             if d.name == "sensor_gyro" and _rate(_seconds(d)) >= MIN_RATE}
    devices, meta, warnings = [], {}, []
    for d in accels:
        t = _seconds(d)
        ids = np.asarray(d.data.get("device_id", []))
        what = f"sensor_accel instance {d.multi_id}" + (f" (device_id {int(ids[-1])})"
                                                        if ids.size else "")
        if _rate(t) < MIN_RATE:
            warnings.append(f"warning: file {file}: {what} is logged at {_rate(t):.3g} "
                            f"samples/s (< {MIN_RATE:g}); it is left out")
            continue
        g = gyros.get(d.multi_id, next(iter(gyros.values()), None))
        if g is None:
            warnings.append(f"warning: file {file}: {what} is left out: no sensor_gyro at rate "
                            "shows whether the board was at rest")
            continue
        name = f"{prefix}/accel{d.multi_id}"
        dev = {"device": name, "t": t, "accel": _xyz(d, "xyz"),
               "gyro": interp_join(t, _seconds(g), _xyz(g, "xyz"))}
        if "temperature" in d.data:
            dev["temp"] = np.asarray(d.data["temperature"], dtype=np.float64)
        if "device_id" in d.data and len(d.data["device_id"]):
            meta[name] = {"device_id": int(d.data["device_id"][-1])}
        devices.append(dev)
    return devices, meta, warnings


def _unpack_fifo(d) -> tuple[np.ndarray, np.ndarray]:
    """The samples packed in a ``sensor_*_fifo`` topic: times (s) and values (SI), in order.

    Message j holds N_j = ``samples`` readings in the first N_j slots of ``x, y, z``;
    reading n is ``scale`` × count, at ``timestamp_sample - (N_j - 1 - n)·dt`` µs.
    """
    width = sum(1 for key in d.data if key.startswith("x["))
    n = np.clip(np.asarray(d.data["samples"], dtype=np.int64), 0, width)
    msg, slot = np.nonzero(np.arange(width)[None, :] < n[:, None])  # one entry per reading
    scale = np.asarray(d.data["scale"], dtype=np.float32).astype(np.float64)[msg]
    dt = np.asarray(d.data["dt"], dtype=np.float32).astype(np.float64)[msg]
    last = np.asarray(d.data["timestamp_sample"], dtype=np.float64)[msg]
    us = last - (n[msg] - 1 - slot) * dt
    values = np.empty((msg.size, 3))
    for j, axis in enumerate("xyz"):  # the counts stay int16 until picked
        counts = np.stack([np.asarray(d.data[f"{axis}[{i}]"]) for i in range(width)], axis=1)
        values[:, j] = counts[msg, slot] * scale
    return us * 1e-6, values


_FIFO_FIELDS = ("timestamp_sample", "dt", "scale", "samples", "x[0]", "y[0]", "z[0]")


def _fifo_devices(ulog, prefix: str, file: str) -> tuple[list[dict], dict, list[str]]:
    """The ``sensor_gyro_fifo`` devices, their ``device_id``, and a warning for each FIFO
    topic that lacks a field its definition has (left out)."""
    warnings = []

    def readable(d) -> bool:
        missing = [f for f in _FIFO_FIELDS if f not in d.data]
        if missing:
            warnings.append(f"warning: file {file}: {d.name} instance {d.multi_id} has no "
                            f"{', '.join(missing)}; it is left out")
        return not missing

    fifos = sorted((d for d in ulog.data_list if d.name == "sensor_gyro_fifo" and readable(d)),
                   key=lambda d: d.multi_id)
    accels = {d.multi_id: d for d in ulog.data_list
              if d.name == "sensor_accel_fifo" and readable(d)}
    gyros = {d.multi_id: d for d in ulog.data_list if d.name == "sensor_gyro"}
    devices, meta = [], {}
    for d in fifos:
        t, gyro = _unpack_fifo(d)
        if t.size == 0:
            continue
        name = f"{prefix}/gyro_fifo{d.multi_id}"
        dev = {"device": name, "t": t, "gyro": gyro}
        acc = accels.get(d.multi_id)
        if acc is not None:
            t_acc, v_acc = _unpack_fifo(acc)
            if t_acc.size:  # np.interp needs increasing times; the FIFO's are as logged
                order = np.argsort(t_acc, kind="stable")
                dev["accel"] = interp_join(t, t_acc[order], v_acc[order])
        g = gyros.get(d.multi_id)
        if g is not None and "temperature" in g.data and len(g.data["temperature"]):
            dev["temp"] = interp_join(t, _seconds(g), np.asarray(g.data["temperature"],
                                                                 dtype=np.float64))
        if "device_id" in d.data and len(d.data["device_id"]):
            meta[name] = {"device_id": int(d.data["device_id"][-1])}
        devices.append(dev)
    return devices, meta, warnings


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


def read(path: Path, file: str, prefix: str, channel: str = "gyro") -> LogTable:
    """Read ``path`` (a ULog) as a :class:`LogTable`; see the module docstring."""
    ulog, cut = _open(path, file)
    size = path.stat().st_size
    if channel == "accel":
        devices, meta, warnings = _accel_devices(ulog, prefix, file)
        if not devices:
            why = "; ".join(w.split(": ", 2)[-1] for w in warnings) or "no sensor_accel logged"
            raise DataError(f"no accelerometer to calibrate in the log ({why})", file=file,
                            hint="log sensor_accel and sensor_gyro at rate (SDLOG_PROFILE: "
                                 "thermal calibration)")
        if cut is not None:
            warnings.append(truncated(file, cut, size, devices))
        out = table(devices, file, warnings)
        out.metadata = meta
        return out
    devices, meta, slow = _gyro_devices(ulog, prefix)
    fifo, fifo_meta, warnings = _fifo_devices(ulog, prefix, file)
    devices, meta = devices + fifo, {**meta, **fifo_meta}
    if fifo:  # the FIFO gives every sample of the sensors logged below rate
        unpacked = {int(dev["device"].rsplit("gyro_fifo", 1)[1]) for dev in fifo}
        slow = [(k, r) for k, r in slow if k not in unpacked]
    if not devices:
        combined = _combined(ulog, prefix)
        if combined is None:
            broken = "; the file is corrupted" if ulog.file_corruption else ""
            if cut is not None:
                broken += f"; the file is truncated: {cut_at(cut, size)}"
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
    if cut is not None:
        warnings.append(truncated(file, cut, size, devices))
    out = table(devices, file, warnings)
    out.metadata = meta
    return out
