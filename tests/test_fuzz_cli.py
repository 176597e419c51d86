"""The command line on corrupted recordings (issue 22): hypothesis-generated damage
to a good small recording (its header plain or with units; truncation, byte flips,
swapped or duplicated rows and columns, constant or empty columns, extreme values, other encodings and line
endings, wrong extensions and magic bytes, damaged Parquet/NPZ/compressed files
and damaged logs: PX4 ULog, ROS 1 bag, ArduPilot DataFlash) through every
command (fit and diagnose with a limits file); export reads damaged calibration files and
fit and diagnose damaged limits files (TOML). Each run ends with exit 0 and strict JSON on stdout (no
NaN/Infinity), or exit 2 and exactly one line on stderr naming the file (under --json
the same error also as a JSON object on stdout): never a traceback. Derandomized, so CI
sees the same examples every run."""

from __future__ import annotations

import contextlib
import gzip
import io
import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diffgyro.cli import main

N = 72  # samples per device: small, so that each run takes milliseconds once compiled, and
#        long enough (36 s) for the motion check to judge rest
HEADER = ["device", "t", "gx", "gy", "gz", "temp", "ax", "ay", "az"]
# the same columns as readable headers with their units (read from the headers)
UNIT_HEADER = ["device", "time (s)", "Gyroscope X (rad/s)", "Gyroscope Y (rad/s)",
               "Gyroscope Z (rad/s)", "Temperature (°C)", "acc_x[m/s²]", "acc_y[m/s²]",
               "acc_z[m/s²]"]


def good_rows() -> list[list[str]]:
    """Two devices with a temperature ramp, a linear bias in it, and gravity on z."""
    rng = np.random.default_rng(7)
    rows = []
    for d, dev in enumerate(("unit-a", "unit-b")):
        t = np.arange(N) * 0.5
        temp = 20.0 + 10.0 * t / t[-1]
        gyro = 1e-3 * (d + 1) + 2e-5 * (temp - 25.0)[:, None] + rng.normal(0, 1e-4, (N, 3))
        acc = rng.normal(0, 1e-3, (N, 3)) + [0.0, 0.0, 9.81]
        for i in range(N):
            rows.append([dev, f"{t[i]:g}", *(f"{v:.9g}" for v in gyro[i]), f"{temp[i]:.6g}",
                         *(f"{v:.6g}" for v in acc[i])])
    return [HEADER, *rows]


def csv_text(rows: list[list[str]], sep: str = ",", newline: str = "\n") -> str:
    return newline.join(sep.join(r) for r in rows) + newline


# --------------------------------------------------------------------------- corruptions

EXTREME = ["1e308", "-1e308", "inf", "-inf", "nan", "NaN", "", "1e-320", "-0", "0", "1e8",
           "100000001", "-273.16", "501", "9" * 400, "0x1F", "1,5", "abc", "\x00", "é", "+", "--1",
           "1e", " 7 ", "TRUE", "nul"]


@st.composite
def text_damage(draw, rows: list[list[str]]) -> list[list[str]]:
    """One edit of the table: rows and columns swapped, duplicated, dropped, made constant
    or empty, or a cell replaced by an extreme or malformed value."""
    rows = [list(r) for r in rows]
    n, k = len(rows), len(rows[0])
    if n < 2 or k < 1:  # a header alone (or nothing) is damaged enough
        return rows
    kind = draw(st.sampled_from(["swap_rows", "dup_row", "drop_row", "swap_cols", "dup_col",
                                 "drop_col", "const_col", "empty_col", "cell", "cells",
                                 "swap_values", "header_only", "short_row", "long_row"]))
    i, j = draw(st.integers(1, n - 1)), draw(st.integers(1, n - 1))
    a, b = draw(st.integers(0, k - 1)), draw(st.integers(0, k - 1))
    if kind == "swap_rows":
        rows[i], rows[j] = rows[j], rows[i]
    elif kind == "dup_row":
        rows.insert(j, list(rows[i]))
    elif kind == "drop_row":
        del rows[i]
    elif kind == "header_only":
        rows = rows[:1]
    elif kind == "short_row":
        rows[i] = rows[i][: max(1, a)]
    elif kind == "long_row":
        rows[i] = rows[i] + ["1"] * (b + 1)
    elif kind == "cell":
        if a < len(rows[i]):
            rows[i][a] = draw(st.sampled_from(EXTREME))
    else:  # column edits, on every row long enough (an earlier edit may have cut one)
        first = 1 if kind in ("swap_values", "const_col", "empty_col", "cells") else 0
        value = {"empty_col": "", "const_col": draw(st.sampled_from(["0", "25", "1e308", "x"]))
                 }.get(kind)
        for r in rows[first:]:
            if max(a, b) >= len(r):
                continue
            if kind in ("swap_cols", "swap_values"):  # swap_values: the header now lies
                r[a], r[b] = r[b], r[a]
            elif kind == "dup_col":
                r.insert(b, r[a])
            elif kind == "drop_col":
                del r[a]
            elif kind == "cells":
                if draw(st.integers(0, 9)) == 0:
                    r[a] = draw(st.sampled_from(EXTREME))
            else:
                r[a] = value
    return rows


ENCODINGS = ["utf-8", "utf-8-sig", "utf-16", "utf-32", "latin-1", "cp1252"]
MAGIC = [b"PAR1", b"PK\x03\x04", b"\x1f\x8b\x08\x00", b"BZh9", b"\xfd7zXZ\x00", b"ULog\x01\x12\x35",
         b"#ROSBAG V2.0\n", b"\xa3\x95", b"\xfe\x64", b"\x89HDF\r\n\x1a\n", b"\x93NUMPY",
         b"\x00" * 8, b"\xef\xbb\xbf", b"\xff\xfe"]
SUFFIXES = [".csv", ".tsv", ".txt", ".parquet", ".npz", ".csv.gz", ".csv.bz2", ".json", ".ulg",
            ".bag", ".bin", ".xlsx", ""]


@st.composite
def byte_damage(draw, data: bytes) -> bytes:
    """One edit of the bytes: truncation, flipped bytes, inserted or dropped bytes, magic
    bytes of another format in front, or a run of bytes zeroed."""
    data = bytearray(data)
    kind = draw(st.sampled_from(["truncate", "flip", "insert", "delete", "magic", "zero"]))
    size = max(len(data), 1)
    at = draw(st.integers(0, size - 1))
    if kind == "truncate":
        del data[at:]
    elif kind == "flip":
        for _ in range(draw(st.integers(1, 8))):
            p = draw(st.integers(0, size - 1))
            if p < len(data):
                data[p] ^= draw(st.integers(1, 255))
    elif kind == "insert":
        data[at:at] = draw(st.binary(min_size=1, max_size=16))
    elif kind == "delete":
        del data[at:at + draw(st.integers(1, 64))]
    elif kind == "magic":
        data[0:0] = draw(st.sampled_from(MAGIC))
    else:
        data[at:at + draw(st.integers(1, 256))] = b"\x00" * len(data[at:at + 256])
    return bytes(data)


class Ground(dict):
    """The fixture's files; a short repr keeps hypothesis' failure reports readable."""

    def __repr__(self) -> str:
        return f"Ground({self['dir']})"


class Blobs(dict):
    """The good files' bytes by suffix (a short repr, as :class:`Ground`)."""

    def __repr__(self) -> str:
        return f"Blobs({', '.join(self)})"


@pytest.fixture(scope="module")
def ground(tmp_path_factory):
    """The good recording as CSV, Parquet and NPZ bytes, and a calibration of it."""
    from diffgyro.io import load, save

    d = tmp_path_factory.mktemp("fuzz-ground")
    good = d / "good.csv"
    good.write_text(csv_text(good_rows()))
    recs = load(good)
    blobs = Blobs({".csv": good.read_bytes()})
    for ext in (".parquet", ".npz"):
        blobs[ext] = save(recs, d / f"good{ext}").read_bytes()
    blobs[".csv.gz"] = gzip.compress(blobs[".csv"], mtime=0)
    for ext, write in LOG_WRITERS.items():  # the same two devices as logs
        write(d / f"good{ext}", log_devices())
        blobs[ext] = (d / f"good{ext}").read_bytes()
    cal = d / "cal.json"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        assert main(["fit", str(good), "--model", "bias_poly(1)", "--out", str(cal)]) == 0
    blobs["cal"] = cal.read_bytes()
    limits = d / "limits.toml"
    limits.write_text(LIMITS)
    return Ground(dir=d, blobs=blobs, cal=cal, count=[0], limits=limits)


#: A production line's limits (the recording's numbers pass them): a text field, bounds in
#: the record's units and in a datasheet's, a wildcard over axes and coefficients.
LIMITS = """[about]
name = "fuzz line"

[limits]
status = "ok"
heldout_rms = { max = 0.01 }          # rad/s
noise_floor = { min = 0, max = 0.01 } # rad/s
"params.*.*" = { abs = true, max = 20, unit = "deg/s" }
"""


def log_devices() -> list[dict]:
    """Two devices like :func:`good_rows` as log samples (µs time stamps, 10 Hz)."""
    rng = np.random.default_rng(8)
    us = 10_000_000 + np.arange(N, dtype=np.int64) * 100_000
    temp = 20.0 + 10.0 * np.arange(N) / (N - 1)
    return [{"us": us, "temp": temp,
             "gyro": 1e-3 * (k + 1) + 2e-5 * (temp - 25.0)[:, None] + rng.normal(0, 1e-4, (N, 3)),
             "accel": rng.normal(0, 1e-3, (N, 3)) + [0.0, 0.0, 9.81]} for k in range(2)]


def _log_writers() -> dict:
    from test_logs import write_bag, write_dataflash, write_ulog  # the formats' own writers

    return {".ulg": write_ulog, ".bag": lambda p, d: write_bag(p, d, "ros1"),
            ".bin": lambda p, d: write_dataflash(p, d, text=False)}


LOG_WRITERS = _log_writers()


@st.composite
def damaged_file(draw, blobs: dict[str, bytes]) -> tuple[bytes, str]:
    """(content, suffix) of a damaged recording."""
    base = draw(st.sampled_from(["text", "text", "text", ".parquet", ".npz", ".csv.gz",
                                 ".ulg", ".bag", ".bin"]))
    if base != "text":
        data = blobs[base]
        suffix = base
        for _ in range(draw(st.integers(1, 2))):
            data = draw(byte_damage(data))
    else:
        rows = good_rows()
        if draw(st.integers(0, 3)) == 0:
            rows[0] = list(UNIT_HEADER)
        for _ in range(draw(st.integers(0, 2))):
            rows = draw(text_damage(rows))
        sep = draw(st.sampled_from([",", ",", ";", "\t", " "]))
        newline = draw(st.sampled_from(["\n", "\n", "\r\n", "\r"]))
        text = csv_text(rows, sep, newline)
        enc = draw(st.sampled_from(ENCODINGS))
        data = text.encode(enc, errors="replace")
        for _ in range(draw(st.integers(0, 2))):
            data = draw(byte_damage(data))
        suffix = ".tsv" if sep == "\t" else ".csv"
    if draw(st.integers(0, 4)) == 0:  # the wrong extension for the content
        suffix = draw(st.sampled_from(SUFFIXES))
    return data, suffix


# --------------------------------------------------------------------------- the runs


def commands(path: str, ground: dict) -> dict[str, list[str]]:
    out = ground["dir"] / "out"
    return {
        "fit": ["fit", path, "--model", "bias_poly(1)", "--json", "--limits",
                str(ground["limits"])],
        "diagnose": ["diagnose", path, "--model", "bias_poly(0)", "--json",
                     "--candidates", "bias_poly,gradient", "--limits", str(ground["limits"])],
        "allan": ["allan", path, "--json"],
        "recipe": ["recipe", "binned-thermal", path, "--json", "--bin-width", "2.5"],
        "compensate": ["compensate", path, "--cal", str(ground["cal"]), "--json",
                       "--out", str(out / "corrected.csv")],
        "export": ["export", path, "--format", "px4", "--out", str(out / "tc.params")],
    }


def strict_json(text: str):
    def refuse(token):
        raise ValueError(f"non-standard JSON token {token} in the output")
    return json.loads(text, parse_constant=refuse)


def run(argv: list[str]) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(argv)
    return code, out.getvalue(), err.getvalue()


def check(command: str, argv: list[str], path: Path) -> None:
    code, out, err = run(argv)
    assert "Traceback" not in err, err
    if code == 0:
        if "--json" in argv:
            doc = strict_json(out)
            assert isinstance(doc, dict) and doc
        return
    assert code == 2, (code, out, err)
    *notes, last = err.strip().splitlines()
    # one error line; before it only the loader's notes (a truncated log read up to its
    # last whole message, dropped rows, ignored columns), each one line
    assert last.startswith("diffgyro: error: ") and all(
        n.startswith("diffgyro: ") and "error" not in n for n in notes), err
    lines = [last]
    if "--json" in argv:  # the same error as one JSON object on stdout
        doc = strict_json(out)
        assert last == f"diffgyro: error: {doc['error']}", (out, err)
        assert {"file", "device", "column", "row"} <= set(doc), doc
    # the file at fault: the damaged one, or (a log read whole whose devices, named after
    # the file, are not in it) the calibration
    assert str(path) in lines[0] or path.name in lines[0] or (
        command == "compensate" and "is not in the calibration" in lines[0]), lines[0]


FUZZ = settings(max_examples=int(__import__("os").environ.get("DIFFGYRO_FUZZ_EXAMPLES", 30)),
                deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                       HealthCheck.function_scoped_fixture])


@pytest.mark.parametrize("command", ["fit", "diagnose", "allan", "recipe", "compensate"])
@FUZZ
@given(data=st.data())
def test_damaged_recording_gives_json_or_one_line(ground, command, data):
    content, suffix = data.draw(damaged_file(ground["blobs"]), label="damaged file")
    ground["count"][0] += 1
    path = ground["dir"] / f"rec{ground['count'][0]}{suffix}"
    path.write_bytes(content)
    argv = commands(str(path), ground)[command]
    if command != "compensate" and data.draw(st.booleans(), label="--static-only"):
        argv = [*argv, "--static-only"]
    check(command, argv, path)


@FUZZ
@given(data=st.data())
def test_damaged_calibration_file_gives_one_line(ground, data):
    """export (and compensate) read a calibration file: damaged, it is one line naming it."""
    content = ground["blobs"]["cal"]
    for _ in range(data.draw(st.integers(1, 2), label="edits")):
        content = data.draw(byte_damage(content), label="damaged calibration")
    ground["count"][0] += 1
    path = ground["dir"] / f"cal{ground['count'][0]}.json"
    path.write_bytes(content)
    argv = commands(str(path), ground)["export"]
    check("export", [*argv, "--force"] if data.draw(st.booleans(), label="--force") else argv, path)
    good = str(ground["dir"] / "good.csv")
    argv = commands(good, ground)["compensate"]
    argv[argv.index("--cal") + 1] = str(path)
    check("compensate", argv, path)


@st.composite
def limits_damage(draw, text: str) -> tuple[bytes, str | None]:
    """One edit of a limits file: a key renamed, a value of the wrong type, a line dropped
    or doubled, or its bytes damaged; with the key the error must name, where one must."""
    lines = text.splitlines()
    rows = [i for i, line in enumerate(lines) if "=" in line and not line.startswith("#")]
    i = draw(st.sampled_from(rows))
    key = lines[i].split("=", 1)[0].strip().strip('"')
    kind = draw(st.sampled_from(["rename", "value", "bound", "drop", "double", "bytes"]))
    if kind == "rename":
        new = draw(st.sampled_from(["heldout_rsm", "noise", "params.q.x", "allan", "status.x"]))
        lines[i] = f'"{new}" =' + lines[i].split("=", 1)[1]
        key = None  # refused as an unknown field, or a path no coefficient has: both named
    elif kind == "value":
        value = draw(st.sampled_from(["0.01", "'ok'", "true", "[1, 2]", "{}", "nan", "inf",
                                      "[]", "{ max = 'x' }", "{ max = inf }", "{ min = 1, max = 0 }",
                                      "{ maximum = 1 }", "{ max = 1, unit = 'parsec' }",
                                      "{ max = 1, abs = 1 }", "1979-05-27"]))
        lines[i] = lines[i].split("=", 1)[0] + "= " + value
    elif kind == "bound":
        lines[i] = lines[i].replace("max", draw(st.sampled_from(["mx", "min", "Max", "max.x"])), 1)
    elif kind == "drop":
        del lines[i]
        key = None
    elif kind == "double":
        lines.insert(i, lines[i])
        key = None  # a TOML error: line and column
    content = ("\n".join(lines) + "\n").encode()
    if kind == "bytes":
        content, key = draw(byte_damage(content)), None
    return content, key


@FUZZ
@given(data=st.data())
def test_damaged_limits_file_gives_json_or_one_line(ground, data):
    """fit and diagnose with a damaged limits file: exit 0 and strict JSON (the edit left a
    valid file), or one line naming the file, and the key where the edit made a key wrong."""
    content, key = data.draw(limits_damage(LIMITS), label="damaged limits")
    ground["count"][0] += 1
    path = ground["dir"] / f"limits{ground['count'][0]}.toml"
    path.write_bytes(content)
    good = str(ground["dir"] / "good.csv")
    for command in ("fit", "diagnose"):
        argv = commands(good, ground)[command]
        argv[argv.index("--limits") + 1] = str(path)
        code, out, err = run(argv)
        assert "Traceback" not in err, err
        if code == 0:
            assert strict_json(out)["limits"]["file"] == str(path)
            continue
        line, = [x for x in err.strip().splitlines() if not x.startswith("diffgyro: warning")]
        assert code == 2 and line.startswith(f"diffgyro: error: file {path}: "), err
        doc = strict_json(out)  # --json: the error as an object on stdout too
        assert doc["file"] == str(path) and line == f"diffgyro: error: {doc['error']}", out
        if key is not None and "not valid TOML" not in line and "UTF-8" not in line:
            assert f"key {key!r}" in line or f"key '{key}." in line, line


@pytest.mark.parametrize("ext", [".csv", ".ulg", ".bag", ".bin"])
@pytest.mark.parametrize("command", ["fit", "diagnose", "allan", "recipe", "compensate"])
def test_the_good_recording_passes_every_command(ground, command, ext):
    """The fuzz test's base case: the undamaged file, as CSV and as each log, gives exit 0
    (and JSON); the logs' devices are named by the file, so compensate finds no calibration
    for them: one line naming the device."""
    path = ground["dir"] / f"good{ext}"
    code, out, err = run(commands(str(path), ground)[command])
    if command == "compensate" and ext != ".csv":
        line, = err.strip().splitlines()
        assert code == 2 and f"file {ground['cal']}: device 'good/" in line, err
        assert "is not in the calibration (it has unit-a, unit-b)" in line
        return
    assert code == 0, err
    doc = strict_json(out)
    if command in ("fit", "diagnose"):  # the good recording passes the line's limits
        assert doc["limits"]["rejected"] == [] and doc["limits"]["yield"] == 1.0
    if command == "compensate":
        assert [{k: e[k] for k in ("device", "n_samples", "clamped")} for e in doc["devices"]] \
            == [{"device": d, "n_samples": N, "clamped": 0} for d in ("unit-a", "unit-b")]
        assert all(e["noise_floor"] > 0 and e["ratio"] > 0 for e in doc["devices"])


def test_the_good_calibration_exports(ground):
    """The calibration fuzz test's base case: export writes both devices' parameters."""
    code, _, err = run(commands(str(ground["cal"]), ground)["export"])
    assert code == 0, err
    params = (ground["dir"] / "out" / "tc.params").read_text()
    assert "TC_G0_X0_0" in params and "TC_G1_X0_0" in params
