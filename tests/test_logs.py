"""Log readers (diffgyro.logs): PX4 ULog, ROS 1/2 bags, ArduPilot DataFlash.

Each format is written through its own library (pyulog's ``write_ulog``,
rosbags' writers) or, where the library cannot write (pymavlink), byte by
byte from the format's definition; read back it must give the same Batch as
the CSV path and the same fit to 1e-12. The real PX4 logs in tests/data/px4
are read against pyulog's own numbers.
"""

from __future__ import annotations

import struct
from pathlib import Path

import jax
import numpy as np
import pandas as pd
import pytest

from diffgyro.cli import main
from diffgyro.io import LoadReport, load, load_batch

PX4 = Path(__file__).parent / "data" / "px4"
N, RATE, T0 = 600, 250.0, 10_000_000  # samples, Hz, first timestamp (µs)
B0 = np.array([[0.01, -0.02, 0.005], [-0.004, 0.012, 0.02], [0.003, 0.0, -0.015]])  # rad/s
B1 = np.array([[2e-4, -1e-4, 3e-4], [1e-4, 2e-4, -2e-4], [-3e-4, 1e-4, 1e-4]])  # rad/s/°C
SIGMA = 2e-4


def _truth(k: int, seed: int = 0) -> dict[str, np.ndarray]:
    """Device k: a linear thermal bias, white noise, a 20→40 °C ramp, gravity on z."""
    rng = np.random.default_rng(seed + k)
    us = T0 + np.round(np.arange(N) * 1e6 / RATE).astype(np.int64) + 50 * k
    us = np.delete(us, [100, 101, 350])  # dropped samples stay gaps
    temp = 20.0 + 20.0 * (us - us[0]) / (us[-1] - us[0])
    gyro = B0[k] + np.outer(temp - 30.0, B1[k]) + SIGMA * rng.standard_normal((us.size, 3))
    accel = np.array([0.1, -0.2, 9.81]) + 0.01 * rng.standard_normal((us.size, 3))
    return {"us": us, "temp": temp, "gyro": gyro, "accel": accel}


def _csv(path: Path, rows: list[dict]) -> Path:
    frames = []
    for r in rows:
        cols = {"device": r["device"], "t": r["t"], "gx": r["gyro"][:, 0],
                "gy": r["gyro"][:, 1], "gz": r["gyro"][:, 2]}
        if "temp" in r:
            cols["temp"] = r["temp"]
        cols.update(ax=r["accel"][:, 0], ay=r["accel"][:, 1], az=r["accel"][:, 2])
        frames.append(pd.DataFrame(cols))
    pd.concat(frames).to_csv(path, index=False, float_format="%.17g")
    return path


def _f32(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float32).astype(np.float64)


# --------------------------------------------------------------------------- writers


def write_ulog(path: Path, devices: list[dict]) -> list[dict]:
    """sensor_gyro / sensor_accel instances through pyulog's writer.

    PX4's own message definitions come from the real log in tests/data/px4,
    whose data are replaced (pyulog writes a ULog object; it has no builder).
    """
    import pyulog

    ulog = pyulog.ULog(str(PX4 / "sample_log_small.ulg"), ["sensor_gyro", "sensor_accel"])
    expect = []
    for d in ulog.data_list:
        k = d.multi_id
        if k >= len(devices):
            continue
        dev = devices[k]
        n = dev["us"].size
        new = {name: np.zeros(n, dtype=v.dtype) for name, v in d.data.items()}
        new["timestamp_sample"] = dev["us"].astype(np.uint64)
        new["timestamp"] = new["timestamp_sample"] + 300
        new["device_id"][:] = 1000 + k
        new["temperature"] = dev["temp"].astype(np.float32)
        values = dev["gyro"] if d.name == "sensor_gyro" else dev["accel"]
        for j, axis in enumerate("xyz"):
            new[axis] = values[:, j].astype(np.float32)
        d.data = new
    ulog.data_list[:] = [d for d in ulog.data_list if d.multi_id < len(devices)]
    ulog.write_ulog(str(path))
    for k, dev in enumerate(devices):
        expect.append({"device": f"{path.stem}/gyro{k}", "t": dev["us"] * 1e-6,
                       "gyro": _f32(dev["gyro"]), "temp": _f32(dev["temp"]),
                       "accel": _f32(dev["accel"])})
    return expect


def _ros_messages(typestore, dev: dict, k: int):
    Imu = typestore.types["sensor_msgs/msg/Imu"]
    Temperature = typestore.types["sensor_msgs/msg/Temperature"]
    Header = typestore.types["std_msgs/msg/Header"]
    Time = typestore.types["builtin_interfaces/msg/Time"]
    Vector3 = typestore.types["geometry_msgs/msg/Vector3"]
    Quaternion = typestore.types["geometry_msgs/msg/Quaternion"]
    zero = np.zeros(9)
    for i, us in enumerate(dev["us"].tolist()):
        header = Header(stamp=Time(sec=us // 1_000_000, nanosec=(us % 1_000_000) * 1000),
                        frame_id=f"imu{k}")
        w, a = dev["gyro"][i], dev["accel"][i]
        imu = Imu(header=header, orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                  orientation_covariance=zero,
                  angular_velocity=Vector3(x=w[0], y=w[1], z=w[2]),
                  angular_velocity_covariance=zero,
                  linear_acceleration=Vector3(x=a[0], y=a[1], z=a[2]),
                  linear_acceleration_covariance=zero)
        yield f"/imu{k}/data", Imu, us * 1000 + 7, imu
        if i % 5 == 0:  # temperature at a fifth of the rate, own topic per IMU
            yield f"/imu{k}/temperature", Temperature, us * 1000 + 9, Temperature(
                header=header, temperature=float(dev["temp"][i]), variance=0.0)


def write_bag(path: Path, devices: list[dict], kind: str) -> list[dict]:
    """Imu + Temperature topics through rosbags' writers (ROS 1, ROS 2 sqlite or MCAP)."""
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    if kind == "ros1":
        from rosbags.rosbag1 import Writer

        writer, serialize = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if kind == "mcap" else StoragePlugin.SQLITE3
        writer, serialize = Writer(path, version=8, storage_plugin=plugin), store.serialize_cdr
    with writer:
        conns = {}
        for k, dev in enumerate(devices):
            for topic, cls, ns, msg in _ros_messages(store, dev, k):
                if topic not in conns:
                    conns[topic] = writer.add_connection(topic, cls.__msgtype__, typestore=store)
                writer.write(conns[topic], ns, serialize(msg, cls.__msgtype__))
    stem = path.name if kind != "ros1" else path.stem
    expect = []
    for k, dev in enumerate(devices):
        t = (dev["us"] // 1_000_000) + (dev["us"] % 1_000_000) * 1000 * 1e-9
        expect.append({"device": f"{stem}/imu{k}/data", "t": t, "gyro": dev["gyro"],
                       "temp": np.interp(t, t[::5], dev["temp"][::5]), "accel": dev["accel"]})
    return expect


_FMT_FMT = ("BBnNZ", "Type,Length,Name,Format,Columns")
_IMU_FMT = ("QBffffffIIf", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T")
_OLD_IMU_FMT = ("QffffffIIf", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T")


def write_dataflash(path: Path, devices: list[dict], text: bool,
                    params: dict[str, float] | None = None) -> list[dict]:
    """IMU messages from the DataFlash definition (pymavlink reads but does not write).

    Binary: ``A3 95 type`` then the packed fields, with FMT messages first;
    ``IMU`` carries its instance in ``I``. Text: the same messages as comma-
    separated lines, in the older style ``IMU``/``IMU2``/``IMU3`` without ``I``.
    ``params`` (binary only): ``PARM`` messages (``TimeUS, Name, Value``) before the samples.
    """
    out = bytearray()
    lines = []
    fmts = [(128, "FMT", *_FMT_FMT)]
    fmts += ([(129 + k, "IMU" if k == 0 else f"IMU{k + 1}", *_OLD_IMU_FMT)
              for k in range(len(devices))] if text else [(129, "IMU", *_IMU_FMT)])
    if params and not text:
        fmts.append((140, "PARM", "QNf", "TimeUS,Name,Value"))
    sizes = {"Q": 8, "B": 1, "f": 4, "I": 4, "n": 4, "N": 16, "Z": 64}
    length = {t: 3 + sum(sizes[c] for c in f) for t, _, f, _ in fmts}
    for t, name, f, cols in fmts:
        out += b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", t, length[t], name.encode(),
                                             f.encode(), cols.encode())
        lines.append(f"FMT, {t}, {length[t]}, {name}, {f}, {cols}")
    for name, value in (params or {}).items() if not text else ():
        out += b"\xa3\x95\x8c" + struct.pack("<Q16sf", 1000, name.encode(), value)
    events = sorted((int(us), k, i) for k, d in enumerate(devices)
                    for i, us in enumerate(d["us"].tolist()))
    for us, k, i in events:
        d = devices[k]
        vals = [float(np.float32(v)) for v in (*d["gyro"][i], *d["accel"][i])]
        temp = float(np.float32(d["temp"][i]))
        if text:
            name = fmts[1 + k][1]
            lines.append(", ".join([name, str(us), *map(repr, vals), "0", "0", repr(temp)]))
        else:
            out += b"\xa3\x95\x81" + struct.pack("<QB6fIIf", us, k, *vals, 0, 0, temp)
    if text:
        path.write_text("\n".join(lines) + "\n")
    else:
        path.write_bytes(bytes(out))
    return [{"device": f"{path.stem}/imu{k}", "t": d["us"] * 1e-6, "gyro": _f32(d["gyro"]),
             "temp": _f32(d["temp"]), "accel": _f32(d["accel"])} for k, d in enumerate(devices)]


WRITERS = {
    "ulog": ("flight.ulg", write_ulog),
    "ros1": ("flight.bag", lambda p, d: write_bag(p, d, "ros1")),
    "ros2": ("flight_ros2", lambda p, d: write_bag(p, d, "ros2")),
    "mcap": ("flight_mcap", lambda p, d: write_bag(p, d, "mcap")),
    "dataflash": ("flight.bin", lambda p, d: write_dataflash(p, d, text=False)),
    "dataflash-text": ("flight.log", lambda p, d: write_dataflash(p, d, text=True)),
}


# --------------------------------------------------------------------------- same as CSV


def _leaves(result) -> list[np.ndarray]:
    return [np.asarray(x) for x in jax.tree_util.tree_leaves(result.params)]


@pytest.mark.parametrize("fmt", list(WRITERS))
def test_log_reads_as_the_csv_path(fmt, tmp_path):
    from diffgyro.fit import fit

    name, writer = WRITERS[fmt]
    truth = [_truth(k) for k in range(3)]
    expect = writer(tmp_path / name, truth)
    if fmt == "mcap":  # rosbags writes a folder; the bare .mcap inside is a log too
        mcap = next((tmp_path / name).glob("*.mcap")).rename(tmp_path / "flight.mcap")
        for e in expect:
            e["device"] = e["device"].replace("flight_mcap/", "flight/")
        log = mcap
    else:
        log = tmp_path / name
    csv = _csv(tmp_path / "same.csv", expect)
    from_log, from_csv = load_batch(log), load_batch(csv)
    assert from_log.devices == tuple(e["device"] for e in expect)
    for sig in ("t", "gyro", "temp", "accel", "mask"):
        np.testing.assert_array_equal(getattr(from_log, sig), getattr(from_csv, sig), err_msg=sig)
    fit_log, fit_csv = fit("bias_poly(1)", from_log), fit("bias_poly(1)", from_csv)
    for a, b in zip(_leaves(fit_log), _leaves(fit_csv), strict=True):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)
    recs = load(log)  # the simulated thermal bias comes back (slope σ ≈ 1.4e-6 rad/s/°C)
    for k, rec in enumerate(recs):
        assert rec.temp is not None and rec.accel is not None
        assert rec.t.size == N - 3  # the three dropped samples are gaps, not filled
        assert np.max(np.diff(rec.t)) == pytest.approx(3 / RATE, abs=1e-9)
        fitted = np.polyfit(rec.temp - 30.0, rec.gyro, 1)
        np.testing.assert_allclose(fitted[0], B1[k], atol=1e-5)
        np.testing.assert_allclose(fitted[1], B0[k], atol=5e-5)


def test_ulog_keeps_device_id_and_sampled_time(tmp_path):
    from diffgyro.logs import read_log

    write_ulog(tmp_path / "f.ulg", [_truth(k) for k in range(2)])
    log = read_log(tmp_path / "f.ulg")
    assert log.metadata == {"f/gyro0": {"device_id": 1000}, "f/gyro1": {"device_id": 1001}}
    assert log.warnings == []
    first = log.frame[log.frame.device == "f/gyro1"].t.iloc[0]
    assert first == (T0 + 50) * 1e-6  # timestamp_sample, not timestamp (+300 µs)


def test_device_option_replaces_the_stem(tmp_path):
    write_dataflash(tmp_path / "f.bin", [_truth(0)], text=False)
    assert [r.device for r in load(tmp_path / "f.bin", device="drone7")] == ["drone7/imu0"]


# --------------------------------------------------------------------------- real PX4 logs


def test_sample_ulog_bias_is_the_logs_mean_rate(capsys):
    """sample.ulg has no sensor_gyro: the documented sensor_combined fallback."""
    import json

    import pyulog

    path = PX4 / "sample.ulg"
    code = main(["fit", str(path), "--model", "bias_poly(0)", "--json"])
    captured = capsys.readouterr()
    assert code == 0
    doc = json.loads(captured.out)
    warnings = [line for line in captured.err.splitlines() if "sensor_combined" in line]
    assert len(warnings) == 1 and str(path) in warnings[0]
    (dev,) = doc["devices"]
    assert dev["device"] == "sample/sensor_combined"
    combined = next(d for d in pyulog.ULog(str(path), ["sensor_combined"]).data_list)
    for k, axis in enumerate("xyz"):
        mean = np.mean(combined.data[f"gyro_rad[{k}]"].astype(np.float64))
        assert dev["params"][axis]["bias_poly(0).c0"] == pytest.approx(mean, rel=1e-9, abs=1e-12)


def test_small_ulog_gyro_at_1hz_falls_back_to_sensor_combined():
    import pyulog

    path = PX4 / "sample_log_small.ulg"
    ulog = pyulog.ULog(str(path), ["sensor_gyro", "sensor_combined"])
    gyros = [d for d in ulog.data_list if d.name == "sensor_gyro"]
    assert len(gyros) == 3 and all(len(d.data["timestamp"]) < 10 for d in gyros)
    report = LoadReport()
    (rec,) = load(path, report=report)
    assert rec.device == "sample_log_small/sensor_combined" and rec.temp is None
    combined = next(d for d in ulog.data_list if d.name == "sensor_combined")
    np.testing.assert_array_equal(rec.t, combined.data["timestamp"] * 1e-6)
    np.testing.assert_array_equal(rec.gyro[:, 2], combined.data["gyro_rad[2]"])
    assert len(report.warnings) == 1
    assert "logged at 1 samples/s (< 10)" in report.warnings[0]


# --------------------------------------------------------------------------- bad input


def _one_line_error(args, capsys, *names):
    code = main(args)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("diffgyro: error: "), err
    for name in names:
        assert name in err[0], err[0]
    return err[0]


def test_corrupted_ulog_is_one_line(tmp_path, capsys):
    good = (PX4 / "sample_log_small.ulg").read_bytes()
    header_broken = tmp_path / "broken.ulg"
    header_broken.write_bytes(good[:16] + bytes(range(256)) * 40)
    _one_line_error(["fit", str(header_broken), "-m", "bias_poly(0)"], capsys, str(header_broken))
    garbled = tmp_path / "garbled.ulg"
    garbled.write_bytes(good[:20000] + b"\xff" * 5000 + good[25000:])
    line = _one_line_error(["fit", str(garbled), "-m", "bias_poly(0)"], capsys, str(garbled))
    assert "no gyro data" in line and "corrupted" in line
    renamed = tmp_path / "notulog.ulg"
    renamed.write_text("t,gx,gy,gz\n0,1,2,3\n")
    _one_line_error(["fit", str(renamed), "-m", "bias_poly(0)"], capsys, str(renamed), "ULog")
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(good[:300])
    _one_line_error(["fit", str(cut), "-m", "bias_poly(0)"], capsys, str(cut), "no gyro data")


def test_bag_without_imu_topic_lists_the_topics(tmp_path, capsys):
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    Float64 = store.types["std_msgs/msg/Float64"]
    path = tmp_path / "noimu.bag"
    with Writer(path) as w:
        conn = w.add_connection("/battery", Float64.__msgtype__, typestore=store)
        w.write(conn, 1, store.serialize_ros1(Float64(data=1.0), Float64.__msgtype__))
    _one_line_error(["fit", str(path), "-m", "bias_poly(0)"], capsys, str(path),
                    "sensor_msgs/msg/Imu", "/battery [std_msgs/msg/Float64]")


def test_unknown_topic_lists_the_imu_topics(tmp_path, capsys):
    path = tmp_path / "two.bag"
    write_bag(path, [_truth(0), _truth(1)], "ros1")
    _one_line_error(["fit", str(path), "-m", "bias_poly(0)", "--topic", "/imu9/data"], capsys,
                    str(path), "/imu9/data", "/imu0/data, /imu1/data")
    _one_line_error(["fit", str(path), "-m", "bias_poly(0)", "--temp-topic", "/t"], capsys,
                    str(path), "/imu0/temperature, /imu1/temperature")
    recs = load(path, topic="/imu1/data", temp_topic="/imu0/temperature")
    assert [r.device for r in recs] == ["two/imu1/data"]
    t0 = np.asarray(_truth(0)["us"], dtype=np.float64)  # /imu0's temperature, /imu1's times
    assert recs[0].temp[0] == pytest.approx(20.0 + 20.0 * (recs[0].t[0] * 1e6 - t0[0])
                                            / (t0[-1] - t0[0]), abs=1e-3)


def test_truncated_bag_is_one_line(tmp_path, capsys):
    path = tmp_path / "full.bag"
    write_bag(path, [_truth(0)], "ros1")
    cut = tmp_path / "cut.bag"
    cut.write_bytes(path.read_bytes()[:5000])
    _one_line_error(["fit", str(cut), "-m", "bias_poly(0)"], capsys, str(cut), "truncated",
                    "rosbag reindex")
    write_bag(tmp_path / "m", [_truth(0)], "mcap")
    mcap = tmp_path / "cut.mcap"
    mcap.write_bytes(next((tmp_path / "m").glob("*.mcap")).read_bytes()[:20000])
    _one_line_error(["fit", str(mcap), "-m", "bias_poly(0)"], capsys, str(mcap), "truncated",
                    "mcap recover")


def test_dataflash_without_imu_is_one_line(tmp_path, capsys):
    path = tmp_path / "noimu.bin"
    fmt = struct.pack("<BB4s16s64s", 128, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns")
    path.write_bytes(b"\xa3\x95\x80" + fmt)
    _one_line_error(["fit", str(path), "-m", "bias_poly(0)"], capsys, str(path), "no IMU, GYR or ISBD messages")
    other = tmp_path / "other.bin"
    other.write_bytes(b"\x00" * 100)
    _one_line_error(["fit", str(other), "-m", "bias_poly(0)"], capsys, str(other), "DataFlash")


def test_rosbag2_folder_is_read_whole_not_streamed(tmp_path, capsys):
    import json

    write_bag(tmp_path / "run", [_truth(0)], "ros2")
    assert main(["fit", str(tmp_path / "run"), "-m", "bias_poly(1)", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [d["device"] for d in doc["devices"]] == ["run/imu0/data"]


# --------------------------------------------------------------------------- truncated logs


def _ulog_messages(data: bytes):
    """(offset, type, payload) of each message, from the ULog definition: a 16-byte file
    header, then per message a uint16 payload size, a uint8 type and the payload."""
    ofs = 16
    while ofs + 3 <= len(data):
        size, kind = struct.unpack_from("<HB", data, ofs)
        yield ofs, chr(kind), data[ofs + 3:ofs + 3 + size]
        ofs += 3 + size


def _ulog_samples_before(data: bytes, topic: str, end: int) -> int:
    """The data ('D') messages of ``topic`` that start before byte ``end``."""
    ids, n = set(), 0
    for ofs, kind, payload in _ulog_messages(data):
        if ofs >= end:
            break
        if kind == "A" and payload[3:].decode() == topic:  # multi_id u8, msg_id u16, name
            ids.add(struct.unpack_from("<H", payload, 1)[0])
        elif kind == "D" and struct.unpack_from("<H", payload)[0] in ids:
            n += 1
    return n


def _same_prefix(cut, full, whole: bool = False) -> None:
    """``cut``'s recordings start as ``full``'s (all of them when ``whole``)."""
    assert [r.device.split("/")[1] for r in cut] == [r.device.split("/")[1] for r in full]
    for c, f in zip(cut, full, strict=True):
        assert c.n == f.n if whole else c.n < f.n
        np.testing.assert_array_equal(c.t, f.t[:c.n])
        np.testing.assert_array_equal(c.gyro, f.gyro[:c.n])


@pytest.mark.parametrize("which", ["sample_log_small", "generated"])
def test_truncated_ulog_warns_and_keeps_the_complete_samples(which, tmp_path):
    """Cut inside a message: one warning naming the file, the byte where the whole messages
    end and the samples kept; they are those of the file cut at that byte (no warning), a
    prefix of the full log's, as many as its data messages before that byte."""
    if which == "generated":
        write_ulog(tmp_path / "full.ulg", [_truth(0), _truth(1)])
        data, topic = (tmp_path / "full.ulg").read_bytes(), "sensor_gyro"
    else:
        data, topic = (PX4 / "sample_log_small.ulg").read_bytes(), "sensor_combined"
    assert sum(3 + len(p) for _, _, p in _ulog_messages(data)) == len(data) - 16
    boundary, _, payload = next(m for m in _ulog_messages(data)
                                if m[0] > 0.6 * len(data) and m[1] == "D")
    assert len(payload) > 4
    (tmp_path / "whole.ulg").write_bytes(data[:boundary])
    (tmp_path / "cut.ulg").write_bytes(data[:boundary + 5])
    whole_report, cut_report = LoadReport(), LoadReport()
    whole = load(tmp_path / "whole.ulg", report=whole_report)
    cut = load(tmp_path / "cut.ulg", report=cut_report)
    assert not [w for w in whole_report.warnings if "truncated after" in w]
    (line,) = [w for w in cut_report.warnings if "truncated after" in w]
    n = sum(r.n for r in cut)
    span = max(r.t[-1] for r in cut) - min(r.t[0] for r in cut)
    for words in (str(tmp_path / "cut.ulg"), f"last 5 bytes, from byte {boundary},",
                  f"using the {n} complete samples"):
        assert words in line, line
    assert float(line.split("truncated after ")[1].split(" s ")[0]) == pytest.approx(span, rel=0.06)
    assert n == _ulog_samples_before(data, topic, boundary)
    _same_prefix(cut, whole, whole=True)
    full = PX4 / "sample_log_small.ulg" if which != "generated" else tmp_path / "full.ulg"
    _same_prefix(cut, load(full, report=LoadReport()))


def _dataflash_cut(data: bytes, text: bool, keep: float) -> tuple[int, int]:
    """A byte inside the message at about ``keep`` of the file, and where that message starts
    (text: lines; binary: FMT messages of 89 bytes, then IMU messages of 3 + 45 bytes)."""
    inside = int(keep * len(data))
    if text:
        return inside, data.rfind(b"\n", 0, inside) + 1
    start = 2 * 89 + (inside - 2 * 89) // 48 * 48
    return start + 20, start


@pytest.mark.parametrize("text", [False, True], ids=["bin", "log"])
def test_truncated_dataflash_warns_and_keeps_the_complete_samples(text, tmp_path, capsys):
    truth = [_truth(0), _truth(1)]
    full = tmp_path / ("full.log" if text else "full.bin")
    write_dataflash(full, truth, text=text)
    data = full.read_bytes()
    inside, start = _dataflash_cut(data, text, 0.6)
    cut = tmp_path / ("cut.log" if text else "cut.bin")
    cut.write_bytes(data[:inside])
    report = LoadReport()
    recs = load(cut, report=report)
    (line,) = report.warnings
    n = sum(r.n for r in recs)
    for words in (str(cut), f"from byte {start},", f"last {inside - start} bytes",
                  f"using the {n} complete samples of 2 devices"):
        assert words in line, line
    # the IMU messages before the cut, in the order they were written (time, instance)
    events = sorted((int(us), k) for k, d in enumerate(truth) for us in d["us"].tolist())
    head = data[:start]
    written = head.count(b"\nIMU") if text else (len(head) - 2 * 89) // 48
    assert n == written and written > 0.5 * len(events)
    for k, rec in enumerate(recs):
        assert rec.n == sum(1 for _, j in events[:written] if j == k)
        np.testing.assert_array_equal(rec.gyro, _f32(truth[k]["gyro"][:rec.n]))
    assert main(["fit", str(cut), "-m", "bias_poly(0)"]) == 0  # one warning line, then fits
    err = capsys.readouterr().err.strip().splitlines()
    assert [e for e in err if "truncated after" in e] == ["diffgyro: " + line]
    # a whole file, and (binary) one padded with zeros as block logs are: no warning
    padded = tmp_path / "padded.bin"
    padded.write_bytes(data + (b"" if text else b"\0" * 200))
    report = LoadReport()
    load(full, report=report)
    load(padded, report=report) if not text else None
    assert report.warnings == []


def test_truncated_log_with_no_whole_sample_is_one_line(tmp_path, capsys):
    write_dataflash(tmp_path / "full.bin", [_truth(0)], text=False)
    cut = tmp_path / "cut.bin"
    cut.write_bytes((tmp_path / "full.bin").read_bytes()[:2 * 89 + 20])
    _one_line_error(["fit", str(cut), "-m", "bias_poly(0)"], capsys, str(cut),
                    "no IMU, GYR or ISBD messages", "truncated", f"from byte {2 * 89}")
    ulog = tmp_path / "cut.ulg"
    ulog.write_bytes((PX4 / "sample_log_small.ulg").read_bytes()[:2000])
    _one_line_error(["fit", str(ulog), "-m", "bias_poly(0)"], capsys, str(ulog),
                    "no gyro data", "truncated")


# --------------------------------------------------------------------------- DataFlash variants

ARDUPILOT = Path(__file__).parent / "data" / "ardupilot"


def _pymavlink_rows(path: Path) -> dict[str, list]:
    """Every IMU/GYR/ACC message as pymavlink reads it: name -> [message, ...]."""
    from pymavlink import DFReader

    reader = DFReader.DFReader_text if path.suffix.lower() == ".log" else DFReader.DFReader_binary
    log = reader(str(path), zero_time_base=False)
    out: dict[str, list] = {}
    while (m := log.recv_match(type=["IMU", "IMU2", "IMU3", "GYR", "ACC"])) is not None:
        out.setdefault(m.get_type(), []).append(m)
    return out


def _xyz(msgs, names) -> np.ndarray:
    return np.array([[float(getattr(m, n)) for n in names] for m in msgs])


def _by_instance(ref: dict[str, list]) -> dict[int, list]:
    """pymavlink's IMU messages per instance: the ``I`` field, else IMU, IMU2, IMU3."""
    out: dict[int, list] = {}
    for k, kind in enumerate(("IMU", "IMU2", "IMU3")):
        for m in ref.get(kind, []):
            out.setdefault(int(m.I) if "I" in m.get_fieldnames() else k, []).append(m)
    return out


@pytest.mark.parametrize("name, time_field, scale", [("nan.log", "TimeMS", 1e-3),
                                                     ("test.BIN", "TimeUS", 1e-6),
                                                     ("backend_log_80k.bin", "TimeUS", 1e-6)])
def test_real_dataflash_logs_equal_pymavlink(name, time_field, scale):
    """nan.log: ArduCopter 3.1 text log, ``IMU``/``IMU2`` timed by ``TimeMS``; test.BIN: a
    2019 binary log, ``IMU``/``IMU2`` with ``TimeUS`` and ``T`` (its last message cut off);
    backend_log_80k.bin: ArduCopter 4.6, ``IMU`` with instance ``I`` and ``T``."""
    from diffgyro.logs import read_log

    path = ARDUPILOT / name
    ref = _by_instance(_pymavlink_rows(path))
    log = read_log(path)
    stem = path.stem
    assert sorted(ref) == [0, 1]
    assert {f"{stem}/imu0", f"{stem}/imu1"} <= set(log.frame.device)
    for k, msgs in ref.items():
        assert time_field in msgs[0].get_fieldnames()
        dev = log.frame[log.frame.device == f"{stem}/imu{k}"]
        assert len(dev) == len(msgs) >= 10
        np.testing.assert_allclose(dev.t, _xyz(msgs, [time_field])[:, 0] * scale, rtol=0,
                                   atol=1e-9)
        np.testing.assert_allclose(dev[["gx", "gy", "gz"]], _xyz(msgs, ["GyrX", "GyrY", "GyrZ"]),
                                   rtol=0, atol=1e-9)
        np.testing.assert_allclose(dev[["ax", "ay", "az"]], _xyz(msgs, ["AccX", "AccY", "AccZ"]),
                                   rtol=0, atol=1e-9)
        if "T" in msgs[0].get_fieldnames():
            np.testing.assert_allclose(dev.temp, _xyz(msgs, ["T"])[:, 0], rtol=0, atol=1e-9)
        else:
            assert "temp" not in log.frame


def test_real_batch_sampler_log_equals_pymavlink():
    """backend_log_80k.bin holds one gyro batch of ArduCopter 4.6's batch sampler (``ISBH``
    then 18 ``ISBD`` messages of 32 samples, 2 kHz, cut short): unpacked as pymavlink's
    mavfft_isb does (samples in seqno order, count / ``mul``), timed ``SampleUS + i/smp_rate``."""
    from pymavlink import DFReader

    from diffgyro.logs import read_log

    path = ARDUPILOT / "backend_log_80k.bin"
    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    head, counts = None, []
    while (m := reader.recv_match(type=["ISBH", "ISBD"])) is not None:
        if m.get_type() == "ISBH":
            head = m
        else:
            assert m.N == head.N and m.seqno == len(counts) // 32
            counts.extend(zip(m.x, m.y, m.z, strict=True))
    assert head.type == 1 and head.instance == 0 and len(counts) == 18 * 32
    t = head.SampleUS * 1e-6 + np.arange(len(counts)) / head.smp_rate
    log = read_log(path)
    dev = log.frame[log.frame.device == "backend_log_80k/gyro_batch0"]
    np.testing.assert_allclose(dev.t, t, rtol=0, atol=1e-9)
    np.testing.assert_allclose(dev[["gx", "gy", "gz"]], np.array(counts) / head.mul, rtol=0,
                               atol=1e-9)
    imu = _by_instance(_pymavlink_rows(path))[0]
    t_imu = _xyz(imu, ["TimeUS"])[:, 0] * 1e-6
    np.testing.assert_allclose(dev.temp, np.interp(t, t_imu, _xyz(imu, ["T"])[:, 0]), atol=1e-9)
    np.testing.assert_allclose(dev.az, np.interp(t, t_imu, _xyz(imu, ["AccZ"])[:, 0]), atol=1e-9)
    # the batch's mean rate is the IMU messages' of the same 0.4 s to the batch's resolution
    assert np.abs(dev.gx.mean() - _xyz(imu, ["GyrX"]).mean()) < 2 / head.mul


def test_old_text_dataflash_fits_from_the_command_line(capsys):
    """The TimeMS log that failed with ``AttributeError: TimeUS``: fit reads it, and the bias
    is pymavlink's mean rate of each IMU."""
    import json

    path = ARDUPILOT / "nan.log"
    assert main(["fit", str(path), "--model", "bias_poly(0)", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    ref = _by_instance(_pymavlink_rows(path))
    for dev, k in zip(doc["devices"], (0, 1), strict=True):
        mean = _xyz(ref[k], ["GyrX", "GyrY", "GyrZ"]).mean(axis=0)
        for k, axis in enumerate("xyz"):
            assert dev["params"][axis]["bias_poly(0).c0"] == pytest.approx(mean[k], rel=1e-9,
                                                                           abs=1e-12)


def write_dataflash_pymavlink(path: Path, formats: dict[str, tuple[str, str]],
                              messages: list[tuple[str, list]]) -> Path:
    """A binary DataFlash log packed by pymavlink's own ``DFMessage.get_msgbuf``.

    ``formats``: name -> (format letters, columns); ``messages``: (name, values) in order.
    """
    from pymavlink.DFReader import DFFormat, DFMessage

    fmt_fmt = DFFormat(128, "FMT", 89, "BBnNZ", "Type,Length,Name,Format,Columns")
    out = bytearray(DFMessage(fmt_fmt, [128, 89, "FMT", "BBnNZ",
                                        "Type,Length,Name,Format,Columns"], False, None).get_msgbuf())
    defs = {}
    for i, (name, (letters, cols)) in enumerate(formats.items()):
        probe = DFFormat(129 + i, name, 0, letters, cols)
        defs[name] = DFFormat(129 + i, name, 3 + struct.calcsize(probe.msg_struct), letters, cols)
        out += DFMessage(fmt_fmt, [129 + i, defs[name].len, name, letters, cols], False,
                         None).get_msgbuf()
    for name, values in messages:
        buf = DFMessage(defs[name], list(values), False, None).get_msgbuf()
        assert buf is not None, (name, values)
        out += buf
    path.write_bytes(bytes(out))
    return path


_NOW_IMU = ("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
_RAW_FMT = {"GYR": ("QBQfff", "TimeUS,I,SampleUS,GyrX,GyrY,GyrZ"),
            "ACC": ("QBQfff", "TimeUS,I,SampleUS,AccX,AccY,AccZ")}


def _f32s(x) -> list[float]:
    return [float(np.float32(v)) for v in x]


@pytest.fixture(scope="module")
def current_dataflash(tmp_path_factory):
    """Current ArduPilot: ``IMU`` with instance ``I`` and ``T``, and sensor-rate ``GYR``/``ACC``
    (``SampleUS`` before ``TimeUS``, as the logger writes a sample after taking it), for two
    IMUs; gyro at 1 kHz, accelerometer at 500 Hz, IMU at 50 Hz with a warming ``T``."""
    rng = np.random.default_rng(7)
    msgs = []
    for us in range(1_000_000, 1_400_000, 1000):
        for k in range(2):
            gyro = B0[k] + 1e-3 * rng.standard_normal(3)
            msgs.append((us + 300, "GYR", [us + 300, k, us + 7 * k, *_f32s(gyro)]))
            if us % 2000 == 0:
                acc = np.array([0.1, -0.2, -9.8]) + 0.01 * rng.standard_normal(3)
                msgs.append((us + 310, "ACC", [us + 310, k, us + 11 * k, *_f32s(acc)]))
            if us % 20000 == 0:
                temp = 30.0 + k + 1e-5 * (us - 1_000_000)
                msgs.append((us + 400, "IMU", [us + 400, k, *_f32s(B0[k]), 0.0, 0.0, -9.8, 0, 0,
                                               float(np.float32(temp)), 1, 1, 1000, 500]))
    msgs.sort(key=lambda m: m[0])
    path = tmp_path_factory.mktemp("df") / "now.bin"
    return write_dataflash_pymavlink(path, {"IMU": _NOW_IMU, **_RAW_FMT},
                                     [(name, v) for _, name, v in msgs])


def test_dataflash_instance_field_and_sensor_rate_messages(current_dataflash):
    from diffgyro.logs import read_log

    ref = _pymavlink_rows(current_dataflash)
    log = read_log(current_dataflash)
    assert log.warnings == []
    assert sorted(set(log.frame.device)) == ["now/gyro0", "now/gyro1", "now/imu0", "now/imu1"]
    for k in range(2):
        imu = [m for m in ref["IMU"] if m.I == k]
        dev = log.frame[log.frame.device == f"now/imu{k}"]
        np.testing.assert_allclose(dev.t, _xyz(imu, ["TimeUS"])[:, 0] * 1e-6, rtol=0, atol=1e-9)
        np.testing.assert_allclose(dev.temp, _xyz(imu, ["T"])[:, 0], rtol=0, atol=1e-9)
        gyr = [m for m in ref["GYR"] if m.I == k]
        acc = [m for m in ref["ACC"] if m.I == k]
        dev = log.frame[log.frame.device == f"now/gyro{k}"]
        t = _xyz(gyr, ["SampleUS"])[:, 0] * 1e-6  # the sample's time, not the write's
        assert len(dev) == 400 and np.all(np.diff(dev.t) > 0)
        np.testing.assert_allclose(dev.t, t, rtol=0, atol=1e-9)
        np.testing.assert_allclose(dev[["gx", "gy", "gz"]], _xyz(gyr, ["GyrX", "GyrY", "GyrZ"]),
                                   rtol=0, atol=1e-9)
        t_acc = _xyz(acc, ["SampleUS"])[:, 0] * 1e-6
        for j, axis in enumerate(("AccX", "AccY", "AccZ")):
            want = np.interp(t, t_acc, _xyz(acc, [axis])[:, 0])
            np.testing.assert_allclose(dev[f"a{'xyz'[j]}"], want, rtol=0, atol=1e-9)
        want = np.interp(t, _xyz(imu, ["TimeUS"])[:, 0] * 1e-6, _xyz(imu, ["T"])[:, 0])
        np.testing.assert_allclose(dev.temp, want, rtol=0, atol=1e-9)
        assert dev.temp.iloc[-1] > dev.temp.iloc[0]  # the warming IMU's T, joined


@pytest.mark.parametrize("old, scale", [
    (("IffffffIIf", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG,ErrA,Temp"), 1e-3),  # Copter 3.2
    (("QffffffIIfBB", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG,ErrA,Temp,GyHlt,AcHlt"), 1e-6)])
def test_dataflash_temp_field(old, scale, tmp_path):
    """Firmware of 2014-2016 calls the temperature ``Temp``, timed in ``TimeMS`` or
    ``TimeUS``: ``bias_poly(1)`` finds the thermal slope written into the log."""
    rng = np.random.default_rng(3)
    msgs = []
    for i in range(600):
        stamp = (5000 + 20 * i) * round(1e-3 / scale)
        for k, name in enumerate(("IMU", "IMU2")):
            temp = 25.0 + 15.0 * i / 600
            gyro = B0[k] + B1[k] * (temp - 30.0) + SIGMA * rng.standard_normal(3)
            health = [1, 1] if old[0].endswith("BB") else []
            msgs.append((name, [stamp, *_f32s(gyro), 0.0, 0.0, -9.8, 0, 0,
                                float(np.float32(temp)), *health]))
    path = write_dataflash_pymavlink(tmp_path / "old.bin", {"IMU": old, "IMU2": old}, msgs)
    ref = _pymavlink_rows(path)
    recs = load(path)
    assert [r.device for r in recs] == ["old/imu0", "old/imu1"]
    time_field = old[1].split(",")[0]
    for k, (rec, kind) in enumerate(zip(recs, ("IMU", "IMU2"), strict=True)):
        np.testing.assert_allclose(rec.t, _xyz(ref[kind], [time_field])[:, 0] * scale,
                                   atol=1e-9)
        assert rec.t[1] - rec.t[0] == pytest.approx(0.02)
        np.testing.assert_allclose(rec.temp, _xyz(ref[kind], ["Temp"])[:, 0], rtol=0, atol=1e-9)
        slope = np.polyfit(rec.temp - 30.0, rec.gyro, 1)[0]
        np.testing.assert_allclose(slope, B1[k], atol=2e-5)


def test_dataflash_without_time_field_is_one_line(tmp_path, capsys):
    path = write_dataflash_pymavlink(tmp_path / "notime.bin",
                                     {"IMU": ("ffffff", "GyrX,GyrY,GyrZ,AccX,AccY,AccZ")},
                                     [("IMU", [0.0, 0.0, 0.0, 0.0, 0.0, -9.8])])
    _one_line_error(["fit", str(path), "-m", "bias_poly(0)"], capsys, str(path),
                    "no time field", "TimeUS or TimeMS")


# --------------------------------------------------------------------------- ULog FIFO

_FIFO_FIELDS = ("uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float dt;"
                "float scale;uint8_t samples;int16_t[32] x;int16_t[32] y;int16_t[32] z;"
                "uint8_t[3] _padding0;")


def write_ulog_fifo(path: Path, seed: int = 0, accel_fields: str = _FIFO_FIELDS) -> Path:
    """``sensor_gyro_fifo`` / ``sensor_accel_fifo`` (PX4's SensorGyroFifo.msg layout) for two
    sensors, added to the real log in tests/data/px4 and written by pyulog's writer; the 1 Hz
    ``sensor_gyro`` of that log (with its temperature) stays."""
    import pyulog

    ulog = pyulog.ULog(str(PX4 / "sample_log_small.ulg"), ["sensor_gyro"])
    t0 = int(min(d.data["timestamp"][0] for d in ulog.data_list))
    t1 = int(max(d.data["timestamp"][-1] for d in ulog.data_list))
    rng = np.random.default_rng(seed)
    msg_id = max(d.msg_id for d in ulog.data_list) + 1
    for topic in ("sensor_gyro_fifo", "sensor_accel_fifo"):
        header = None
        fields = _FIFO_FIELDS if topic == "sensor_gyro_fifo" else accel_fields
        ulog._message_formats[topic] = pyulog.ULog.MessageFormat(f"{topic}:{fields}".encode(),
                                                                 header)
        for k in range(2):
            add = pyulog.ULog._MessageAddLogged(struct.pack("<BH", k, msg_id) + topic.encode(),
                                                header, ulog._message_formats)
            dt = 125.0 if topic == "sensor_gyro_fifo" else 250.0  # 8 kHz gyro, 4 kHz accel
            m = int((t1 - t0) / 4000)  # a message every 4 ms
            rows = np.zeros(m, dtype=add.dtype)
            full = int(4000 / dt)  # a full FIFO read every 4 ms; instance 0 drops some
            n = rng.integers(1, full + 1, m) if k == 0 else np.full(m, full)
            last = t0 + 4000 * np.arange(1, m + 1) + 13 * k
            rows["timestamp"] = last + 150
            rows["timestamp_sample"] = last
            rows["device_id"] = 2000 + k
            if "dt" in rows.dtype.names:
                rows["dt"] = dt
            rows["scale"] = np.float32(1 / 16.4 * np.pi / 180) if "gyro" in topic else 0.0024
            rows["samples"] = n
            centre = (200, -150, 90) if "gyro" in topic else (40, -80, -4080)
            for a, c in zip("xyz", centre, strict=True):
                counts = c + rng.integers(-30, 31, (m, 32))
                for i in range(32):
                    rows[f"{a}[{i}]"] = counts[:, i]
            add.buffer = bytearray(rows.tobytes())
            ulog._data_list.append(pyulog.ULog.Data(add))
            msg_id += 1
    ulog.write_ulog(str(path))
    return path


def _pyulog_fifo(d) -> tuple[np.ndarray, np.ndarray]:
    """Unpacked one message and one sample at a time, as SensorGyroFifo.msg defines it."""
    t, v = [], []
    for j in range(len(d.data["timestamp"])):
        n, dt = int(d.data["samples"][j]), float(d.data["dt"][j])
        for i in range(n):
            t.append((float(d.data["timestamp_sample"][j]) - (n - 1 - i) * dt) * 1e-6)
            v.append([float(d.data[f"{a}[{i}]"][j]) * float(d.data["scale"][j]) for a in "xyz"])
    return np.array(t), np.array(v)


def test_ulog_gyro_fifo_is_unpacked_as_px4_defines_it(tmp_path):
    import pyulog

    path = write_ulog_fifo(tmp_path / "fifo.ulg")
    ref = pyulog.ULog(str(path), ["sensor_gyro_fifo", "sensor_accel_fifo", "sensor_gyro"])
    from diffgyro.logs import read_log

    log = read_log(path)
    assert sorted(set(log.frame.device)) == ["fifo/gyro_fifo0", "fifo/gyro_fifo1"]
    assert log.metadata["fifo/gyro_fifo1"] == {"device_id": 2001}
    # the log's third sensor has no FIFO: only its 1 Hz sensor_gyro is left out
    assert [w for w in log.warnings if "left out" in w or "sensor_combined" in w] == [
        f"warning: file {path}: sensor_gyro instance(s) 2 logged at < 10 samples/s are left out"]
    for k in range(2):
        topic = {d.name: d for d in ref.data_list if d.multi_id == k}
        t, gyro = _pyulog_fifo(topic["sensor_gyro_fifo"])
        t_acc, acc = _pyulog_fifo(topic["sensor_accel_fifo"])
        assert np.all(np.diff(t_acc) > 0)
        dev = log.frame[log.frame.device == f"fifo/gyro_fifo{k}"]
        assert len(dev) == len(t) > 1000
        np.testing.assert_allclose(dev.t, t, rtol=0, atol=1e-9)
        assert np.all(np.diff(dev.t) > 0)
        np.testing.assert_allclose(dev[["gx", "gy", "gz"]], gyro, rtol=0, atol=1e-9)
        for j, a in enumerate("xyz"):
            np.testing.assert_allclose(dev[f"a{a}"], np.interp(t, t_acc, acc[:, j]), atol=1e-9)
        g = topic["sensor_gyro"]
        want = np.interp(t, g.data["timestamp_sample"] * 1e-6, g.data["temperature"])
        np.testing.assert_allclose(dev.temp, want, rtol=0, atol=1e-9)


def test_ulog_sensor_gyro_instances_equal_pyulog(tmp_path):
    """Three ``sensor_gyro`` instances at 250 Hz (pyulog's writer), each its own device;
    ``sensor_accel`` of the same instance joined by linear interpolation at the gyro's
    ``timestamp_sample`` (each accelerometer sample here is taken 137 µs after the gyro's)."""
    import pyulog

    from diffgyro.logs import read_log

    path = tmp_path / "three.ulg"
    write_ulog(path, [_truth(k) for k in range(3)])
    ulog = pyulog.ULog(str(path))  # move each sensor_accel instance to its own sample times
    for d in ulog.data_list:
        if d.name == "sensor_accel":
            d.data["timestamp_sample"] = d.data["timestamp_sample"] + np.uint64(137)
    ulog.write_ulog(str(path))
    ref = pyulog.ULog(str(path), ["sensor_gyro", "sensor_accel"])
    log = read_log(path)
    assert sorted(set(log.frame.device)) == [f"three/gyro{k}" for k in range(3)]
    for k in range(3):
        g = next(d for d in ref.data_list if d.name == "sensor_gyro" and d.multi_id == k)
        a = next(d for d in ref.data_list if d.name == "sensor_accel" and d.multi_id == k)
        dev = log.frame[log.frame.device == f"three/gyro{k}"]
        t = g.data["timestamp_sample"] * 1e-6
        np.testing.assert_allclose(dev.t, t, rtol=0, atol=1e-9)
        for axis in "xyz":
            np.testing.assert_allclose(dev[f"g{axis}"], g.data[axis], rtol=0, atol=1e-9)
            want = np.interp(t, a.data["timestamp_sample"] * 1e-6, a.data[axis])
            np.testing.assert_allclose(dev[f"a{axis}"], want, rtol=0, atol=1e-9)
            # interpolated, not the nearest sample: between two accelerometer samples
            assert np.abs(dev[f"a{axis}"].to_numpy()[1:-1]
                          - a.data[axis][1:-1].astype(np.float64)).max() > 0
        np.testing.assert_allclose(dev.temp, g.data["temperature"], rtol=0, atol=1e-9)


def test_dataflash_numbered_raw_messages(tmp_path):
    """Raw IMU logs before the instance field: ``GYR1``/``GYR2`` and ``ACC1``/``ACC2``."""
    formats = {f"{kind}{k}": ("QQfff", f"TimeUS,SampleUS,{axes}")
               for kind, axes in (("GYR", "GyrX,GyrY,GyrZ"), ("ACC", "AccX,AccY,AccZ"))
               for k in (1, 2)}
    msgs = []
    for i in range(200):
        us = 2_000_000 + 1000 * i
        for k in (1, 2):
            msgs.append((f"GYR{k}", [us + 50, us + k, 0.01 * k, -0.02, 0.003 * i]))
            msgs.append((f"ACC{k}", [us + 60, us + 2 * k, 0.1, 0.2, -9.8]))
    path = write_dataflash_pymavlink(tmp_path / "raw.bin", formats, msgs)
    ref = _pymavlink_rows(path)  # GYR1 etc. are not in its list: read them here
    from pymavlink import DFReader

    reader = DFReader.DFReader_binary(str(path), zero_time_base=False)
    gyr = {1: [], 2: []}
    while (m := reader.recv_match(type=["GYR1", "GYR2"])) is not None:
        gyr[int(m.get_type()[-1])].append(m)
    assert ref == {}
    recs = load(path)
    assert [r.device for r in recs] == ["raw/gyro0", "raw/gyro1"]
    for rec, k in zip(recs, (1, 2), strict=True):
        np.testing.assert_allclose(rec.t, _xyz(gyr[k], ["SampleUS"])[:, 0] * 1e-6, atol=1e-9)
        np.testing.assert_allclose(rec.gyro, _xyz(gyr[k], ["GyrX", "GyrY", "GyrZ"]), atol=1e-9)
        np.testing.assert_allclose(rec.accel[:, 2], -9.8, atol=1e-6)


def test_dataflash_unreadable_message_type_is_left_out_with_a_warning(tmp_path):
    """An ``ACC`` type without ``AccZ`` does not sink the log's gyro: one warning names it."""
    msgs = [("GYR", [1000 * i + 5, 0, 1000 * i, 0.01, 0.02, 0.03]) for i in range(50)]
    msgs += [("ACC", [1000 * i + 6, 0, 1000 * i, 0.1, 0.2]) for i in range(50)]
    path = write_dataflash_pymavlink(tmp_path / "odd.bin", {
        "GYR": _RAW_FMT["GYR"], "ACC": ("QBQff", "TimeUS,I,SampleUS,AccX,AccY")}, msgs)
    report = LoadReport()
    (rec,) = load(path, report=report)
    assert rec.device == "odd/gyro0" and rec.n == 50 and rec.accel is None
    assert report.warnings == [f"warning: file {path}: ACC messages lack the field(s) AccZ; "
                               f"their fields are TimeUS, I, SampleUS, AccX, AccY; they are "
                               f"left out"]


def test_dataflash_gyr_without_acc_takes_the_imu_accelerometer(tmp_path):
    msgs = []
    for i in range(100):
        us = 1_000_000 + 1000 * i
        msgs.append(("GYR", [us + 5, 0, us, 0.01, 0.02, 0.03]))
        if i % 10 == 0:
            msgs.append(("IMU", [us + 9, 0, 0.01, 0.02, 0.03, 0.1, 0.2 + 1e-3 * i, -9.8, 0, 0,
                                 35.0, 1, 1, 1000, 1000]))
    path = write_dataflash_pymavlink(tmp_path / "noacc.bin",
                                     {"IMU": _NOW_IMU, "GYR": _RAW_FMT["GYR"]}, msgs)
    report = LoadReport()
    imu, gyr = load(path, report=report)
    assert (imu.device, gyr.device) == ("noacc/imu0", "noacc/gyro0") and report.warnings == []
    np.testing.assert_allclose(gyr.accel[:, 1], np.interp(gyr.t, imu.t, imu.accel[:, 1]),
                               atol=1e-12)
    np.testing.assert_allclose(gyr.temp, 35.0)


def test_ulog_fifo_topic_without_dt_is_left_out_with_a_warning(tmp_path):
    path = write_ulog_fifo(tmp_path / "nodt.ulg",
                           accel_fields=_FIFO_FIELDS.replace("float dt;", "float _dt_unused;"))
    report = LoadReport()
    recs = load(path, report=report)
    assert [r.device for r in recs] == ["nodt/gyro_fifo0", "nodt/gyro_fifo1"]
    assert all(r.accel is None for r in recs)
    left = [w for w in report.warnings if "sensor_accel_fifo" in w]
    assert left == [f"warning: file {path}: sensor_accel_fifo instance {k} has no dt; it is "
                    f"left out" for k in (0, 1)]


def test_dataflash_kind_is_told_by_content_not_name(tmp_path):
    """A binary log saved as ``.log`` and a text log saved as ``.bin`` read as they are."""
    for name, renamed in (("test.BIN", "binary.log"), ("nan.log", "text.bin")):
        (tmp_path / renamed).write_bytes((ARDUPILOT / name).read_bytes())
        got, want = load(tmp_path / renamed, report=LoadReport()), load(ARDUPILOT / name,
                                                                         report=LoadReport())
        assert [r.n for r in got] == [r.n for r in want]
        for a, b in zip(got, want, strict=True):
            np.testing.assert_array_equal(a.gyro, b.gyro)
