"""ArduPilot DataFlash logs (binary ``.bin`` and text ``.log``) via pymavlink.

Each IMU instance is the device ``<stem>/imu<k>``: the ``I`` field of
``IMU`` messages gives k (older logs write ``IMU``, ``IMU2``, ``IMU3`` for
k = 0, 1, 2). ``GyrX, GyrY, GyrZ`` (rad/s) → ``gx, gy, gz``, ``AccX, AccY,
AccZ`` (m/s²) → ``ax, ay, az``, ``T`` or ``Temp`` (°C) → ``temp``, ``TimeUS``
(µs since boot; ``TimeMS``, ms, in logs before 2015) → ``t`` in s.

Raw sensor-rate logging writes ``GYR`` and ``ACC`` messages (one per sample,
instance ``I``; older logs ``GYR1..3``/``ACC1..3``): each gyro instance is the
device ``<stem>/gyro<k>``, timed by ``SampleUS`` (when the sensor took the
sample, µs since boot), with ``ACC`` instance k interpolated at its times (or,
without ``ACC``, ``IMU`` instance k's accelerometer) and the temperature of
``IMU`` instance k interpolated likewise. The batch
sampler's gyro bursts (``ISBH``/``ISBD``) of instance k are the device
``<stem>/gyro_batch<k>``, beside ``IMU`` instance k's accelerometer and
temperature, interpolated. Samples are kept as logged.

The sensors' ids come from the log's parameters (``PARM``): ``INS_GYR_ID``,
``INS_GYR2_ID``, ... for the gyro of IMU k, ``INS_ACC_ID``, ``INS_ACC2_ID``, ... for its
accelerometer (``channel="accel"``), kept in :attr:`LogTable.metadata` where non-zero.
ArduPilot applies ``INS_TCALn`` by IMU instance; the id says which sensor that was.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
from pathlib import Path

import numpy as np

from ..errors import DataError
from ._table import LogTable, cut_at, interp_join, require, table, truncated

_IMU = ("IMU", "IMU2", "IMU3")
_RAW = {"GYR": ("GyrX", "GyrY", "GyrZ"), "ACC": ("AccX", "AccY", "AccZ")}
_TYPES = [*_IMU, *(f"{kind}{s}" for kind in _RAW for s in ("", "1", "2", "3")), "ISBH", "ISBD",
          "PARM"]
_HEAD = b"\xa3\x95"  # every binary message starts with these
_GYRO, _ACCEL = ("GyrX", "GyrY", "GyrZ"), ("AccX", "AccY", "AccZ")
_TEMP = ("T", "Temp")  # the IMU temperature field: ``T`` now, ``Temp`` in firmware of 2014-2016
# time fields: (name, seconds per count), the first one a message has is used
_TIME = {"imu": (("TimeUS", 1e-6), ("TimeMS", 1e-3)),
         "raw": (("SampleUS", 1e-6), ("TimeUS", 1e-6))}


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


class _Unreadable(ValueError):
    """A message type that lacks a field the reader needs (its messages are left out)."""


class _Layout:
    """Where one message type keeps what is read: its time field, instance and columns."""

    def __init__(self, kind: str, names: list[str]):
        self.kind = "imu" if kind in _IMU else kind.rstrip("123")
        self.time = next(((f, s) for f, s in _TIME["imu" if self.kind == "imu" else "raw"]
                          if f in names), None)
        if self.time is None:
            want = " or ".join(f for f, _ in _TIME["imu" if self.kind == "imu" else "raw"])
            raise _Unreadable(f"{kind} messages have no time field ({want}); their fields "
                              f"are {', '.join(names)}")
        self.values = _GYRO + _ACCEL if self.kind == "imu" else _RAW[self.kind]
        missing = [f for f in self.values if f not in names]
        if missing:
            raise _Unreadable(f"{kind} messages lack the field(s) {', '.join(missing)}; "
                              f"their fields are {', '.join(names)}")
        self.temp = next((f for f in _TEMP if f in names), None) if self.kind == "imu" else None
        self.instance = "I" if "I" in names else None
        suffix = kind[3:]  # IMU, IMU2, IMU3 -> 0, 1, 2; GYR1..3 -> 0..2; GYR (with I) -> I
        self.fixed = int(suffix) - 1 if suffix else 0

    def row(self, m) -> tuple[int, tuple[float, ...]]:
        k = int(m.I) if self.instance else self.fixed
        t = float(getattr(m, self.time[0])) * self.time[1]
        vals = tuple(float(getattr(m, f)) for f in self.values)
        return k, (t, *vals, float(getattr(m, self.temp)) if self.temp else np.nan)


class _Batches:
    """The batch sampler's gyro bursts (``INS_LOG_BAT_*``), per IMU instance.

    ``ISBH`` opens batch ``N``: sensor ``type`` (0 accelerometer, 1 gyro), ``instance``,
    ``smp_cnt`` samples taken ``smp_rate`` Hz apart from ``SampleUS`` (µs since boot), each
    a count of 1/``mul`` rad/s. ``ISBD`` message ``seqno`` of batch ``N`` carries samples
    ``32·seqno .. 32·seqno + 31`` of it in ``x, y, z``.
    """

    GYRO, PER_MESSAGE = 1, 32

    def __init__(self):
        self.open: dict[int, tuple[int, float, float, float, int]] = {}
        self.parts: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}

    def header(self, m) -> None:
        n = int(m.N)
        self.open.pop(n, None)
        rate, mul = float(m.smp_rate), float(m.mul)
        if int(m.type) == self.GYRO and rate > 0 and mul > 0:
            self.open[n] = (int(m.instance), mul, float(m.SampleUS), rate, int(m.smp_cnt))

    def data(self, m) -> None:
        head = self.open.get(int(m.N))
        if head is None:  # an accelerometer batch, or one whose header was not logged
            return
        k, mul, start, rate, count = head
        idx = int(m.seqno) * self.PER_MESSAGE + np.arange(self.PER_MESSAGE)
        keep = idx < count
        counts = np.stack([np.asarray(getattr(m, a), dtype=np.float64) for a in "xyz"], axis=1)
        t = start * 1e-6 + idx[keep] / rate
        self.parts.setdefault(k, []).append((t, counts[keep] / mul))

    def devices(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        out = {}
        for k, parts in self.parts.items():
            t = np.concatenate([p[0] for p in parts])
            out[k] = _increasing(t, np.concatenate([p[1] for p in parts]))
        return out


def _messages(path: Path, file: str, params: dict | None = None
              ) -> tuple[dict[tuple[str, int], tuple[list, bool]], int | None, list[str]]:
    """The rows of each (kind, instance): kind ``imu``, ``GYR`` or ``ACC`` (and ``ISB``:
    the gyro batches, as (t, rad/s) arrays); where the log is cut off; and the message
    types that could not be read, with why. ``params`` receives the log's parameters."""
    params = {} if params is None else params
    dfreader = require("pymavlink.DFReader", "pymavlink", file)
    with open(path, "rb") as fh:  # by content: a binary log may be named .log and back
        text = not fh.read(2).startswith(_HEAD)
    rows: dict[tuple[str, int], list[tuple]] = {}
    has_temp: dict[tuple[str, int], bool] = {}
    layouts: dict[str, _Layout | None] = {}
    problems: list[str] = []
    batches = _Batches()
    try:
        # pymavlink prints on bad data (Python's stdout and stderr, and its C indexer
        # straight to file descriptor 2): our one line says it
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()), \
                _quiet_fd(2):
            log = (dfreader.DFReader_text if text else dfreader.DFReader_binary)(
                str(path), zero_time_base=False)
            while (m := log.recv_match(type=_TYPES)) is not None:
                kind = m.get_type()
                if kind == "PARM":
                    params[str(getattr(m, "Name", ""))] = getattr(m, "Value", None)
                    continue
                if kind in ("ISBH", "ISBD"):
                    (batches.header if kind == "ISBH" else batches.data)(m)
                    continue
                if kind not in layouts:
                    try:
                        layouts[kind] = _Layout(kind, list(m.get_fieldnames()))
                    except _Unreadable as err:
                        layouts[kind] = None
                        problems.append(str(err))
                lay = layouts[kind]
                if lay is None:
                    continue
                k, row = lay.row(m)
                key = (lay.kind, k)
                has_temp[key] = has_temp.get(key, True) and lay.temp is not None
                rows.setdefault(key, []).append(row)
            cut = _text_cut(path) if text else _binary_cut(log)
    except DataError:
        raise
    except Exception as err:  # pymavlink raises struct, index, value and OS errors
        raise DataError(f"cannot read as ArduPilot DataFlash ({type(err).__name__}: {err})",
                        file=file) from None
    found = {key: (v, has_temp[key]) for key, v in rows.items()}
    found.update({("ISB", k): (tv, False) for k, tv in batches.devices().items()})
    return found, cut, problems


def _increasing(t: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Samples in time order, for interpolating them (``np.interp`` needs increasing times;
    a log's are as they were written)."""
    order = np.argsort(t, kind="stable")
    return t[order], v[order]


def _from_imu(t: np.ndarray, imu, cols: slice) -> np.ndarray:
    """IMU message values (``imu``: its rows) interpolated at ``t``."""
    return interp_join(t, *_increasing(imu[:, 0], imu[:, cols]))


def _sensor_ids(params: dict, devices: list[dict], channel: str) -> dict[str, dict]:
    """Each device's sensor id from ``INS_GYRn_ID`` / ``INS_ACCn_ID`` (where non-zero)."""
    stem = "INS_ACC" if channel == "accel" else "INS_GYR"
    out = {}
    for dev in devices:
        k = int(re.search(r"(\d+)$", dev["device"]).group(1))  # imu<k>, gyro<k>, ...
        value = params.get(f"{stem}_ID" if k == 0 else f"{stem}{k + 1}_ID")
        if isinstance(value, (int, float)) and value and value == value:
            out[dev["device"]] = {"device_id": int(value) & 0xFFFFFFFF}
    return out


def read(path: Path, file: str, prefix: str, channel: str = "gyro") -> LogTable:
    """Read ``path`` (a DataFlash log) as a :class:`LogTable`; see the module docstring."""
    params: dict = {}
    found, cut, problems = _messages(path, file, params)
    size = path.stat().st_size
    if not any(kind in ("imu", "GYR", "ISB") for kind, _ in found):
        end = "".join(f"; {p}" for p in problems)
        end += f"; the file is truncated: {cut_at(cut, size)}" if cut is not None else ""
        raise DataError(f"no gyro data in the log (no IMU, GYR or ISBD messages{end})", file=file)
    arrays = {key: (rows if key[0] == "ISB" else np.asarray(rows, dtype=np.float64), temp)
              for key, (rows, temp) in found.items()}
    order = {"imu": 0, "GYR": 1, "ISB": 2}
    devices = []
    for (kind, k), (v, has_temp) in sorted(
            ((key, val) for key, val in arrays.items() if key[0] in order),
            key=lambda kv: (order[kv[0][0]], kv[0][1])):
        imu, imu_temp = arrays.get(("imu", k), (None, False))
        if kind == "imu":
            dev = {"device": f"{prefix}/imu{k}", "t": v[:, 0], "gyro": v[:, 1:4],
                   "accel": v[:, 4:7]}
            if has_temp:
                dev["temp"] = v[:, 7]
            devices.append(dev)
            continue
        if kind == "GYR":
            t = v[:, 0]
            dev = {"device": f"{prefix}/gyro{k}", "t": t, "gyro": v[:, 1:4]}
            acc = arrays.get(("ACC", k))
            if acc is not None:
                dev["accel"] = interp_join(t, *_increasing(acc[0][:, 0], acc[0][:, 1:4]))
        else:  # the batch sampler's accelerometer bursts are taken at other times
            t, gyro = v
            dev = {"device": f"{prefix}/gyro_batch{k}", "t": t, "gyro": gyro}
        if "accel" not in dev and imu is not None:
            dev["accel"] = _from_imu(t, imu, slice(4, 7))
        if imu is not None and imu_temp:
            dev["temp"] = _from_imu(t, imu, slice(7, 8))[:, 0]
        devices.append(dev)
    warnings = [f"warning: file {file}: {p}; they are left out" for p in problems]
    if cut is not None:
        warnings.append(truncated(file, cut, size, devices))
    out = table(devices, file, warnings)
    out.metadata = _sensor_ids(params, devices, channel)
    return out
