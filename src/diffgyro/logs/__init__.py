"""Autopilot and robot logs as standard-schema tables: PX4 ULog, ROS bags, ArduPilot DataFlash.

Each reader turns one log into a long-format :class:`pandas.DataFrame` in the
standard schema (``device, t, gx, gy, gz`` and, when the log has them,
``temp`` and ``ax, ay, az``; SI units) that :func:`diffgyro.io.load` then
checks like any table (column mapping, units, NaN and time checks). The
format follows the extension and is checked against the file's first bytes.
The libraries (pyulog, rosbags, pymavlink) are imported only when a log is
read; without them the error says ``pip install "diffgyro[logs]"``.
A ULog or DataFlash log whose last message is cut off is read up to its last
whole message, with one warning line (:func:`.table.truncated`).
The field mapping of each format is in docs/formats.md.
"""

from __future__ import annotations

from pathlib import Path

from ..errors import DataError
from ._table import LogTable

__all__ = ["read_log", "log_format", "LogTable", "LOG_SUFFIXES", "is_rosbag_dir"]

# extension -> reader
LOG_SUFFIXES = {".ulg": "ulog", ".bag": "rosbag", ".mcap": "rosbag", ".bin": "dataflash",
                ".log": "dataflash"}
_NAMES = {"ulog": "PX4 ULog", "rosbag": "ROS bag", "dataflash": "ArduPilot DataFlash"}
_MAGIC = {"ulog": (b"ULog\x01\x12\x35",), "rosbag": (b"#ROSBAG V2.0", b"\x89MCAP0\r\n"),
          "dataflash": (b"\xa3\x95", b"FMT,", b"FMT ")}


def is_rosbag_dir(path: Path) -> bool:
    """True for a rosbag2 folder (it holds ``metadata.yaml``).

    **Arguments:**

    - ``path``: the folder.
    """
    return path.is_dir() and (path / "metadata.yaml").is_file()


def log_format(path: Path) -> str | None:
    """The log reader for ``path`` by its name (``None``: not a log).

    **Arguments:**

    - ``path``: the file or folder.
    """
    if is_rosbag_dir(path):
        return "rosbag"
    return LOG_SUFFIXES.get(path.suffix.lower())


def _check_magic(path: Path, fmt: str, file: str) -> None:
    if path.is_dir():
        return
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError as err:
        raise DataError(f"cannot read file ({err})", file=file) from None
    if not head:
        raise DataError(f"empty file, not a {_NAMES[fmt]} log", file=file)
    text = head.lstrip() if fmt == "dataflash" else head
    if fmt == "dataflash" and not text.startswith(_MAGIC[fmt][0]):
        # a text log may open with lines the board printed at boot (firmware, free RAM)
        # before its first FMT line
        text = b"".join(line.lstrip() for line in text.splitlines(keepends=True)
                        if line.lstrip().startswith(_MAGIC[fmt][1:]))
    if not any(text.startswith(m) for m in _MAGIC[fmt]):
        raise DataError(f"not a {_NAMES[fmt]} log (the file does not start with its "
                        f"marker {_MAGIC[fmt][0]!r})", file=file)


def read_log(path: str | Path, fmt: str | None = None, *, file: str | None = None,
             prefix: str | None = None, topic: str | None = None,
             temp_topic: str | None = None, channel: str = "gyro") -> LogTable:
    """Read one log as a :class:`LogTable`.

    **Arguments:**

    - ``path``: the log (a rosbag2 folder is a path too).
    - ``fmt``: ``ulog``, ``rosbag`` or ``dataflash`` (default: by extension).
    - ``file``: the name errors give (default: ``path``).
    - ``prefix``: device ids start with this (default: the file stem).
    - ``topic``: ROS bags: the Imu topic(s) to read, comma-separated.
    - ``temp_topic``: ROS bags: the Temperature topic joined to them.
    - ``channel``: ``accel``: a PX4 ULog gives one device per ``sensor_accel`` instance
      (its own times, temperature and device id); a DataFlash log's IMU instances
      keep the accelerometer's id (``INS_ACCn_ID``) instead of the gyro's; ROS logs
      read the same either way.
    """
    path = Path(path)
    file = str(path) if file is None else file
    fmt = fmt or log_format(path)
    if fmt not in _NAMES:
        raise DataError("not a log file (.ulg, .bag, .mcap, rosbag2 folder, .bin, .log)",
                        file=file)
    _check_magic(path, fmt, file)
    prefix = prefix if prefix is not None else (path.name if path.is_dir() else path.stem)
    if fmt == "ulog":
        from . import _ulog as ulog

        return ulog.read(path, file, prefix, channel)
    if fmt == "rosbag":
        from . import _rosbag as rosbag

        return rosbag.read(path, file, prefix, topic, temp_topic)
    from . import _dataflash as dataflash

    return dataflash.read(path, file, prefix, channel)
