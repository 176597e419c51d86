"""ROS 1 and ROS 2 bags (``.bag``, rosbag2 folders, ``.mcap``) via rosbags.

Every ``sensor_msgs/msg/Imu`` topic (or those named by ``topic``) is the
device ``<stem><topic>`` (``flight/imu/data``): ``angular_velocity`` (rad/s)
→ ``gx, gy, gz``, ``linear_acceleration`` (m/s²) → ``ax, ay, az``. Time is
the message's ``header.stamp`` in s (sec + nanosec·1e-9, the sensor's time);
a topic whose stamps are all zero uses the bag's receive time instead.

A ``sensor_msgs/msg/Temperature`` topic (``temperature``, °C) gives
``temp``: linearly interpolated at the Imu stamps, the first / last reading
held beyond its ends. Which one: the topic named by ``temp_topic`` (for
every Imu topic), else the only one in the bag, else the one in the same
namespace as each Imu topic (``/imu0/data`` ↔ ``/imu0/temperature``); several
Temperature topics that do not pair up so are an error listing them.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import DataError
from ._table import LogTable, interp_join, require, table

IMU = "sensor_msgs/msg/Imu"
# rosbags needs a bag's index (ROS 1) / summary (MCAP), written at its end: a bag cut off
# (recording killed, copy interrupted) fails with one of these
_INDEX_LOST = re.compile(r"index|end magic|magic is invalid|summary", re.IGNORECASE)
_REBUILD = {".bag": "'rosbag reindex'", ".mcap": "'mcap recover'"}


def _truncated_hint(path: Path, err: Exception) -> str | None:
    """What to do about a bag whose index is lost (``None``: the error is something else)."""
    if not _INDEX_LOST.search(str(err)):
        return None
    tool = _REBUILD.get(path.suffix.lower(), "'mcap recover' (MCAP) or 'ros2 bag reindex'")
    return f"the bag looks truncated, its index at the end missing or damaged: {tool} rebuilds it"
TEMPERATURE = "sensor_msgs/msg/Temperature"


def _topics(connections, msgtype: str) -> list[str]:
    return sorted({c.topic for c in connections if c.msgtype == msgtype})


def _listing(connections) -> str:
    found = sorted({(c.topic, c.msgtype) for c in connections})
    return ", ".join(f"{t} [{m}]" for t, m in found) or "none"


def _namespace(topic: str) -> str:
    return topic.rsplit("/", 1)[0]


def _pick(connections, file: str, topic: str | None,
          temp_topic: str | None) -> tuple[list[str], dict[str, str]]:
    imus, temps = _topics(connections, IMU), _topics(connections, TEMPERATURE)
    if not imus:
        raise DataError(f"no {IMU} topic in the bag (topics: {_listing(connections)})",
                        file=file)
    if topic:
        wanted = [s.strip() for s in topic.split(",") if s.strip()]
        for name in wanted:
            if name not in imus:
                raise DataError(f"topic {name} is not an Imu topic of the bag "
                                f"(Imu topics: {', '.join(imus)})", file=file)
        imus = wanted
    if temp_topic:
        if temp_topic not in temps:
            raise DataError(f"topic {temp_topic} is not a Temperature topic of the bag "
                            f"(Temperature topics: {', '.join(temps) or 'none'})", file=file)
        return imus, {name: temp_topic for name in imus}
    if len(temps) <= 1:
        return imus, {name: temps[0] for name in imus} if temps else {}
    pairs = {name: [t for t in temps if _namespace(t) == _namespace(name)] for name in imus}
    if any(len(p) != 1 for p in pairs.values()):
        raise DataError(f"several Temperature topics ({', '.join(temps)}) and no one-to-one "
                        f"pairing with the Imu topics by namespace", file=file,
                        hint="pick one with --temp-topic")
    return imus, {name: p[0] for name, p in pairs.items()}


def _stamp(msg, bag_ns: int) -> tuple[float, float]:
    s = msg.header.stamp
    return float(s.sec) + float(s.nanosec) * 1e-9, bag_ns * 1e-9


def _collect(reader, imus: list[str], temps: set[str]) -> dict[str, dict[str, list]]:
    want = {*imus, *temps}
    cons = [c for c in reader.connections if c.topic in want]
    rows: dict[str, dict[str, list]] = {t: {"stamp": [], "bag": [], "v": []} for t in want}
    for con, bag_ns, raw in reader.messages(connections=cons):
        msg = reader.deserialize(raw, con.msgtype)
        stamp, bag = _stamp(msg, bag_ns)
        r = rows[con.topic]
        r["stamp"].append(stamp)
        r["bag"].append(bag)
        if con.topic in temps:
            r["v"].append(float(msg.temperature))
        else:
            w, a = msg.angular_velocity, msg.linear_acceleration
            r["v"].append((w.x, w.y, w.z, a.x, a.y, a.z))
    return rows


def _times(r: dict[str, list]) -> np.ndarray:
    stamp = np.asarray(r["stamp"], dtype=np.float64)
    return np.asarray(r["bag"], dtype=np.float64) if not stamp.any() else stamp


def read(path: Path, file: str, prefix: str, topic: str | None = None,
         temp_topic: str | None = None) -> LogTable:
    """Read ``path`` (a ROS 1 / ROS 2 bag) as a :class:`LogTable`; see the module docstring."""
    highlevel = require("rosbags.highlevel", "rosbags", file)
    typesys = require("rosbags.typesys", "rosbags", file)
    store = typesys.get_typestore(typesys.Stores.ROS2_HUMBLE)
    try:
        with highlevel.AnyReader([path], default_typestore=store) as reader:
            imus, temp_of = _pick(reader.connections, file, topic, temp_topic)
            rows = _collect(reader, imus, set(temp_of.values()))
    except DataError:
        raise
    except Exception as err:  # rosbags' reader/deserializer errors, sqlite, truncated chunks
        raise DataError(f"cannot read as ROS bag ({type(err).__name__}: {err})", file=file,
                        hint=_truncated_hint(path, err)) from None
    devices = []
    for name in imus:
        r = rows[name]
        if not r["v"]:
            raise DataError(f"topic {name} has no messages", file=file)
        t, v = _times(r), np.asarray(r["v"], dtype=np.float64)
        dev = {"device": prefix + (name if name.startswith("/") else "/" + name), "t": t,
               "gyro": v[:, :3], "accel": v[:, 3:]}
        temp = temp_of.get(name)
        if temp and rows[temp]["v"]:
            dev["temp"] = interp_join(t, _times(rows[temp]), np.asarray(rows[temp]["v"]))
        devices.append(dev)
    return table(devices, file)
