"""Loading and saving recordings: exact round trips, mapping, units, clear errors."""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diffgyro.data import Batch, Recording
from diffgyro.errors import DataError
from diffgyro.io import (
    LoadReport,
    check_min_samples,
    load,
    load_batch,
    parse_columns,
    resolve_units,
    save,
)


def make_recording(device: str, n: int, seed: int, signals=("temp", "accel")) -> Recording:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.001, 0.02, n)) + rng.uniform(0, 1e3)
    # values across many decades and a few awkward ones, to test exact round trips
    gyro = rng.standard_normal((n, 3)) * 10.0 ** rng.integers(-12, 3, (n, 3))
    gyro[0] = [-0.0, 5e-324, 99999999.99999999]  # within io.LIMITS (±1e8 rad/s)
    gyro[1] = [0.1, 1 / 3, 2.0**-1074 * 3]
    kw = {}
    if "temp" in signals:
        kw["temp"] = 25 + rng.standard_normal(n) * 7
    if "temp_ext" in signals:
        kw["temp_ext"] = 20 + rng.standard_normal(n)
    if "accel" in signals:
        kw["accel"] = rng.standard_normal((n, 3)) + [0, 0, 9.81]
    if "mag" in signals:  # any unit, no physical limit: the extreme floats go here
        kw["mag"] = rng.standard_normal((n, 3)) * 40
        kw["mag"][0] = [1.7976931348623157e308, -1.7976931348623157e308, 2.0**-1074]
    if "rate" in signals:
        kw["rate"] = rng.standard_normal((n, 3))
    if "quat" in signals:
        q = rng.standard_normal((n, 4))
        kw["quat"] = q / np.linalg.norm(q, axis=1, keepdims=True)
    return Recording(t=t, gyro=gyro, device=device, **kw)


def bits(a) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float64).view(np.int64)


def assert_same(a: Recording, b: Recording) -> None:
    assert a.device == b.device
    assert a.signals == b.signals
    for sig in a.signals:
        np.testing.assert_array_equal(bits(getattr(a, sig)), bits(getattr(b, sig)), err_msg=sig)


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def error_of(*args, **kw) -> DataError:
    with pytest.raises(DataError) as info:
        load(*args, **kw)
    return info.value


ALL = ("temp", "temp_ext", "accel", "mag", "rate", "quat")


# ---------------------------------------------------------------- round trips


@pytest.mark.parametrize("ext", ["csv", "parquet", "npz", "csv.gz", "tsv"])
def test_round_trip_is_bitwise(tmp_path, ext):
    recs = [make_recording("001", 50, 1, ALL), make_recording("B,2 \"x\"", 73, 2, ALL),
            make_recording("unit-3", 64, 3, ALL)]
    path = save(recs, tmp_path / f"devices.{ext}")
    back = load(path, check_units=False)  # values across decades: not a gyro's
    assert [r.device for r in back] == ["001", 'B,2 "x"', "unit-3"]
    for a, b in zip(recs, back, strict=True):
        assert_same(a, b)
        assert b.source == str(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"devices.{ext}"]  # no temp left


def test_round_trip_of_a_batch_and_single_recording(tmp_path):
    recs = [make_recording("a", 40, 4), make_recording("b", 90, 5)]
    batch = Batch.from_recordings(recs)
    save(batch, tmp_path / "b.parquet")
    for a, b in zip(recs, load(tmp_path / "b.parquet", check_units=False), strict=True):
        assert_same(a, b)
    save(recs[0], tmp_path / "one.csv")
    assert_same(recs[0], load(tmp_path / "one.csv", check_units=False)[0])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=6,
                max_size=30))
def test_csv_round_trip_any_finite_float(values):
    n = len(values) // 3
    mag = np.asarray(values[: 3 * n]).reshape(n, 3)  # magnetometer: any unit, no limit
    gyro = np.clip(mag, -1e8, 1e8)                    # gyro: within io.LIMITS
    rec = Recording(t=np.arange(n) * 0.5 + 1e-9, gyro=gyro, mag=mag, device="d")
    with tempfile.TemporaryDirectory() as d:
        back = load(save(rec, Path(d) / "x.csv"))[0]
    assert_same(rec, back)


def test_save_refuses_mixed_signal_sets(tmp_path):
    recs = [make_recording("a", 10, 1, ("temp",)), make_recording("b", 10, 2, ())]
    with pytest.raises(DataError, match="different signals"):
        save(recs, tmp_path / "x.csv")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- layout


def test_long_format_interleaved_devices_keep_file_order(tmp_path):
    rows = ["device,t,gx,gy,gz"]
    expect = {"B": [], "A": [], "C": []}
    order = ["B", "A", "B", "C", "A", "A", "B", "C"]
    for i, dev in enumerate(order):
        k = len(expect[dev])
        expect[dev].append((float(k), float(i), 10.0 * i, -float(i)))
        rows.append(f"{dev},{k},{i},{10 * i},{-i}")
    recs = load(write(tmp_path / "mixed.csv", "\n".join(rows) + "\n"))
    assert [r.device for r in recs] == ["B", "A", "C"]  # order of first appearance
    for r in recs:
        e = np.array(expect[r.device])
        np.testing.assert_array_equal(r.t, e[:, 0])
        np.testing.assert_array_equal(r.gyro, e[:, 1:])


def test_device_id_defaults_to_file_stem_and_can_be_given(tmp_path):
    text = "t,gx,gy,gz\n0,1,2,3\n1,4,5,6\n"
    assert load(write(tmp_path / "gyro_07.csv", text))[0].device == "gyro_07"
    assert load(tmp_path / "gyro_07.csv", device="SN-9")[0].device == "SN-9"
    save(load(tmp_path / "gyro_07.csv"), tmp_path / "z.csv.gz")
    assert load(tmp_path / "z.csv.gz")[0].device == "gyro_07"


def test_many_files_at_once(tmp_path):
    a = save([make_recording("a", 20, 1), make_recording("b", 30, 2)], tmp_path / "ab.npz")
    c = save(make_recording("c", 25, 3), tmp_path / "c.parquet")
    assert [r.device for r in load([a, c])] == ["a", "b", "c"]


def test_semicolon_separator_and_whitespace(tmp_path):
    path = write(tmp_path / "eu.csv", " t ; gx ;gy;gz\n0; 1.5 ;2;3\n1;4;5;6\n")
    rec = load(path)[0]
    np.testing.assert_array_equal(rec.gyro, [[1.5, 2, 3], [4, 5, 6]])
    path.write_bytes(b"\xef\xbb\xbft,gx,gy,gz\r\n0,1,2,3\r\n1,4,5,6\r\n")  # BOM, CRLF
    np.testing.assert_array_equal(load(path)[0].gyro, [[1, 2, 3], [4, 5, 6]])


def test_blank_lines_are_not_rows(tmp_path):
    path = write(tmp_path / "b.csv", "t,gx,gy,gz\n0,1,2,3\n\n1,4,5,6\n2,x,5,6\n\n")
    err = error_of(path)
    assert err.row == 3 and err.column == "gx"


# ---------------------------------------------------------------- mapping, units


def test_parse_columns():
    assert parse_columns("gx=gyr_x, gy = gyr_y,gz=gyr_z,") == {
        "gx": "gyr_x", "gy": "gyr_y", "gz": "gyr_z"}
    assert parse_columns(None) == {} and parse_columns("  ") == {}
    # another left-hand name renames an extra column (for aux(NAME) terms)
    assert parse_columns("vdd=Supply V,gx=g") == {"vdd": "Supply V", "gx": "g"}
    for bad, words in [("gx", "no '='"), ("1q=a", "unknown standard column"),
                       ("g q=a", "unknown standard column"),
                       ("gx=", "names no column"), ("gx=a,gx=b", "twice")]:
        with pytest.raises(DataError, match=words):
            parse_columns(bad)


def test_column_mapping_and_unit_conversion(tmp_path):
    text = ("time_ms,gyr_x,gyr_y,gyr_z,acc_x,acc_y,acc_z,T_K,ref_x,ref_y,ref_z\n"
            "0,90,0.5,-180,0,0,1,298.15,90,0,0\n"
            "10,45,0,360,0.5,0,1,300.15,0,0,0\n")
    path = write(tmp_path / "imu.csv", text)
    columns = parse_columns("t=time_ms,gx=gyr_x,gy=gyr_y,gz=gyr_z,ax=acc_x,ay=acc_y,"
                            "az=acc_z,temp=T_K,rx=ref_x,ry=ref_y,rz=ref_z")
    rec = load(path, columns, units={"t": "ms", "gyro": "deg/s", "accel": "g", "temp": "K"})[0]
    np.testing.assert_allclose(rec.t, [0.0, 0.01], rtol=0, atol=1e-15)
    np.testing.assert_allclose(rec.gyro, np.deg2rad([[90, 0.5, -180], [45, 0, 360]]), rtol=1e-15)
    np.testing.assert_allclose(rec.rate, np.deg2rad([[90, 0, 0], [0, 0, 0]]), rtol=1e-15)
    np.testing.assert_allclose(rec.accel, [[0, 0, 9.80665], [4.903325, 0, 9.80665]], rtol=1e-15)
    np.testing.assert_allclose(rec.temp, [25.0, 27.0], atol=1e-12)
    rec = load(path, columns, units={"gyro": "mdps", "accel": "mg", "temp": "°F",
                                     "rate": "rpm"})[0]
    np.testing.assert_allclose(rec.gyro[0], np.deg2rad([0.090, 0.0005, -0.180]), rtol=1e-15)
    np.testing.assert_allclose(rec.rate[0], [90 * 2 * math.pi / 60, 0, 0], rtol=1e-15)
    np.testing.assert_allclose(rec.accel[1], [0.5 * 9.80665e-3, 0, 9.80665e-3], rtol=1e-15)
    np.testing.assert_allclose(rec.temp, [(298.15 - 32) * 5 / 9, (300.15 - 32) * 5 / 9])


def test_unit_table():
    assert resolve_units({"gyro": "deg/h"})["gyro"][0] == pytest.approx(math.pi / 180 / 3600)
    assert resolve_units({"gyro": "rad/s", "temp": "degC", "mag": "uT"}) == {}
    assert resolve_units({"gyro": "dps"})["rate"] == resolve_units({"gyro": "deg/s"})["gyro"]
    assert resolve_units({"t": "µs"})["t"] == (1e-6, 0.0)
    with pytest.raises(DataError, match=r"unknown gyro unit 'deg/fortnight'.*--gyro-unit.*deg/s"):
        resolve_units({"gyro": "deg/fortnight"})
    with pytest.raises(DataError, match=r"unknown signal 'pressure'.*valid: t, gyro"):
        resolve_units({"pressure": "Pa"})


def test_sampling_rate_gives_time_and_keeps_gaps_of_dropped_rows(tmp_path):
    path = write(tmp_path / "imucal.csv", "gx,gy,gz\n1,2,3\n4,nan,6\n7,8,9\n1,1,1\n")
    err = error_of(path)
    assert err.column == "t" and "sampling rate" in str(err)
    report = LoadReport()
    rec = load(path, sampling_rate=200.0, drop_invalid=True, report=report)[0]
    np.testing.assert_array_equal(rec.t, [0.0, 2 / 200, 3 / 200])
    assert report.n_dropped == 1
    with pytest.raises(DataError, match="positive"):
        load(path, sampling_rate=-1.0)


# ---------------------------------------------------------------- bad input


def long_text(cells: dict[tuple[int, str], str] | None = None) -> str:
    """Two interleaved devices A, B with 4 rows each; ``cells`` overrides (row, col)."""
    cols = ["device", "t", "gx", "gy", "gz", "temp"]
    lines = [",".join(cols)]
    for i in range(8):
        dev = "AB"[i % 2]
        row = {"device": dev, "t": str(i // 2), "gx": "0.1", "gy": "0.2", "gz": "0.3",
               "temp": "20"}
        for (r, c), v in (cells or {}).items():
            if r == i + 1:
                row[c] = v
        lines.append(",".join(row[c] for c in cols))
    return "\n".join(lines) + "\n"


def assert_names(err: DataError, file=None, device=None, column=None, row=None):
    text = str(err)
    assert "\n" not in text
    for key, want in (("file", file), ("device", device), ("column", column), ("row", row)):
        if want is not None:
            assert getattr(err, key) == want, (key, text)
            assert f"{key} {want}" in text, text


@pytest.mark.parametrize("cell,value,problem", [
    ((6, "gy"), "abc", "non-numeric text 'abc'"),
    ((6, "gy"), "1,5", None),  # decimal comma: an extra field
    ((5, "temp"), "", "missing or NaN"),
    ((5, "temp"), "NaN", "missing or NaN"),
    ((7, "gz"), "inf", "infinite"),
    ((7, "gz"), "-1e999", "infinite"),
    ((4, "gx"), "true", "non-numeric text 'true'"),
    ((4, "gx"), "1_000", "non-numeric text '1_000'"),
])
def test_bad_cells_name_file_device_column_row(tmp_path, cell, value, problem):
    path = write(tmp_path / "bad.csv", long_text({cell: value}))
    err = error_of(path)
    if problem is None:
        assert "fields" in str(err) and err.file == str(path)
        return
    row, col = cell
    assert problem in str(err)
    assert_names(err, file=str(path), device="AB"[(row - 1) % 2], column=col, row=row)


def test_time_errors_name_the_row(tmp_path):
    # device B (rows 2,4,6,8) gets t = 0,1,1,3: row 6 repeats row 4
    err = error_of(write(tmp_path / "dup.csv", long_text({(6, "t"): "1"})))
    assert_names(err, device="B", column="t", row=6)
    assert "repeats row 4" in str(err)
    err = error_of(write(tmp_path / "back.csv", long_text({(7, "t"): "0.5"})))
    assert_names(err, device="A", column="t", row=7)
    assert "backwards" in str(err)
    # a single-device file with two devices' data concatenated gets a hint
    err = error_of(write(tmp_path / "two.csv", "t,gx,gy,gz\n0,0,0,0\n1,0,0,0\n0,0,0,0\n"))
    assert_names(err, device="two", column="t", row=3)
    assert "'device' column" in str(err)


def test_missing_and_partial_columns(tmp_path):
    err = error_of(write(tmp_path / "m.csv", "t,gx,gz\n0,1,2\n"))
    assert_names(err, file=str(tmp_path / "m.csv"), device="m", column="gy")
    assert "missing required column" in str(err) and "t, gx, gz" in str(err)
    err = error_of(write(tmp_path / "p.csv", "t,gx,gy,gz,ax,ay\n0,1,2,3,4,5\n"))
    assert_names(err, column="az")
    assert "incomplete accel group" in str(err)
    swapped = load(write(tmp_path / "s.csv", "t,gx,gy,gz\n0,1,2,3\n1,4,5,6\n"),
                   columns={"gx": "gy", "gy": "gx"})[0]
    np.testing.assert_array_equal(swapped.gyro, [[2, 1, 3], [5, 4, 6]])
    err = error_of(tmp_path / "s.csv", columns={"gx": "gy"})  # gy is taken by gx now
    assert_names(err, column="gy")
    with pytest.raises(DataError, match="to both temp and temp_ext"):
        load(tmp_path / "s.csv", columns={"temp": "gx", "temp_ext": "gx"})
    err = error_of(tmp_path / "m.csv", columns={"gy": "gyr_y"})
    assert "'gyr_y' (given for gy) is not in the file" in str(err)
    err = error_of(write(tmp_path / "semi.csv", "t;gx;gy;gz\n0;1;2;3\n"),
                   columns={"gx": "gx;gy"})
    assert "not in the file" in str(err)
    err = error_of(write(tmp_path / "nohead.csv", "0,1,2,3\n1,1,2,3\n"))
    assert "no header" in str(err)
    err = error_of(write(tmp_path / "dupcol.csv", "t,gx,gy,gz,gx\n0,1,2,3,4\n"))
    assert_names(err, column="gx")
    assert "twice" in str(err)


def test_too_few_samples(tmp_path):
    path = write(tmp_path / "few.csv", "t,gx,gy,gz\n0,1,2,3\n")
    err = error_of(path)
    assert_names(err, file=str(path), device="few")
    assert "fewer samples than loading needs (2)" in str(err)
    rec = load(write(tmp_path / "ten.csv", "t,gx,gy,gz\n" + "".join(
        f"{i},0,0,0\n" for i in range(10))))[0]
    with pytest.raises(DataError, match=r"10 samples: fewer samples than bias_poly\(3\) "
                                        r"needs \(12\)") as info:
        check_min_samples(rec, 12, "bias_poly(3)")
    assert_names(info.value, file=str(tmp_path / "ten.csv"), device="ten")
    check_min_samples(rec, 10)
    err = error_of(tmp_path / "ten.csv", min_samples=11)
    assert "fewer samples" in str(err)


def test_device_repeated_across_files_names_both(tmp_path):
    a = save(make_recording("X", 10, 1), tmp_path / "a.csv")
    b = save([make_recording("Y", 10, 2), make_recording("X", 10, 3)], tmp_path / "b.parquet")
    err = error_of([a, b])
    assert str(a) in str(err) and str(b) in str(err)
    assert_names(err, device="X")
    # two files named alike, without device column: same default id
    (tmp_path / "d1").mkdir()
    (tmp_path / "d2").mkdir()
    text = "t,gx,gy,gz\n0,0,0,0\n1,0,0,0\n"
    err = error_of([write(tmp_path / "d1" / "unit.csv", text),
                    write(tmp_path / "d2" / "unit.csv", text)])
    assert "two files" in str(err) and "d1" in str(err) and "d2" in str(err)


@pytest.mark.parametrize("name,content,words", [
    ("empty.csv", b"", "empty file"),
    ("blank.csv", b"\n\n  \n", "empty file"),
    ("header.csv", b"t,gx,gy,gz\n", "no data rows"),
    ("header2.csv", b"device,t,gx,gy,gz", "no data rows"),
    ("garbage.csv", bytes(range(256)) * 4, "binary"),
    ("latin.csv", "t,gx,gy,gz,temp\n0,1,2,3,4\n1,1,2,3,4 \xb0C\n".encode("latin-1"), "UTF-8"),
    ("ragged.csv", b"t,gx,gy,gz\n0,1,2,3\n1,2,3,4,5\n", "fields"),
    ("ragged1.csv", b"t,gx,gy,gz\n0,1,2,3,9\n1,2,3,4,5\n", "more fields"),
    ("bad.parquet", b"PAR1 this is not parquet", "Parquet"),
    ("bad.npz", b"PK\x03\x04 truncated zip", "NPZ"),
    ("bad.csv.gz", b"not gzip at all", "cannot"),
    ("data.xlsx", b"whatever", "unknown file type"),
])
def test_unreadable_files_give_data_error(tmp_path, name, content, words):
    path = tmp_path / name
    path.write_bytes(content)
    err = error_of(path)
    assert words in str(err) and err.file == str(path)


def test_missing_file_and_npz_problems(tmp_path):
    assert "not found" in str(error_of(tmp_path / "nope.csv"))
    np.savez(tmp_path / "obj.npz", t=np.arange(3.0), gx=np.zeros(3), gy=np.zeros(3),
             gz=np.array([1, "a", None], dtype=object))
    assert "NPZ" in str(error_of(tmp_path / "obj.npz"))
    np.savez(tmp_path / "shape.npz", t=np.arange(3.0), gx=np.zeros((3, 2)), gy=np.zeros(3),
             gz=np.zeros(3))
    assert_names(error_of(tmp_path / "shape.npz"), column="gx")
    np.savez(tmp_path / "len.npz", t=np.arange(3.0), gx=np.zeros(3), gy=np.zeros(4),
             gz=np.zeros(3))
    assert "rows" in str(error_of(tmp_path / "len.npz"))
    np.savez(tmp_path / "ok.npz", t=np.arange(3.0), gx=np.zeros(3), gy=np.ones(3),
             gz=np.zeros(3), device=np.array([7, 7, 8]))
    recs = load(tmp_path / "ok.npz", min_samples=1)
    assert [r.device for r in recs] == ["7", "8"]


def test_missing_device_id(tmp_path):
    err = error_of(write(tmp_path / "d.csv", "device,t,gx,gy,gz\nA,0,0,0,0\n ,1,0,0,0\n"))
    assert_names(err, column="device", row=2)


@pytest.mark.parametrize("ids, names, rows", [
    ([" a", "a", "b", "a "], ["a", "b"], [0, 1, 3]),      # text read alike: one device
    ([2.0, 2.0, 1.0, 2.0], ["2", "1"], [0, 1, 3]),         # whole numbers read as integers
    ([1.5, 7.0, 1.5, 1.5], ["1.5", "7"], [0, 2, 3]),
    ([b"x", b"y", b"x", b"x"], ["x", "y"], [0, 2, 3]),
])
def test_device_ids_are_read_per_distinct_value(tmp_path, ids, names, rows):
    n = len(ids)
    np.savez(tmp_path / "ids.npz", device=np.array(ids), t=np.arange(n, dtype=float),
             gx=np.arange(n, dtype=float), gy=np.zeros(n), gz=np.zeros(n))
    recs = load(tmp_path / "ids.npz", min_samples=1)
    assert [r.device for r in recs] == names
    np.testing.assert_array_equal(recs[0].gyro[:, 0], rows)  # the first device's file rows


@pytest.mark.parametrize("bad", [np.nan, np.inf, None, "  "])
def test_missing_device_id_in_parquet_names_its_row(tmp_path, bad):
    import pandas as pd

    numeric = not isinstance(bad, str) and bad is not None
    ids = [1.0, 1.0, bad, 1.0] if numeric else ["A", "A", bad, "A"]
    frame = pd.DataFrame({"device": ids, "t": [0.0, 1.0, 2.0, 3.0], "gx": 0.0, "gy": 0.0, "gz": 0.0})
    frame.to_parquet(tmp_path / "m.parquet")
    assert_names(error_of(tmp_path / "m.parquet"), column="device", row=3)


def test_parquet_nulls_and_text_cells(tmp_path):
    import pandas as pd

    frame = pd.DataFrame({"device": ["A", "A", "A", "B", "B"], "t": [0.0, 1.0, 2.0, 0.0, 1.0],
                          "gx": [0.1, None, 0.3, 0.4, 0.5], "gy": [1.0] * 5, "gz": [2.0] * 5})
    frame.to_parquet(tmp_path / "n.parquet")
    assert_names(error_of(tmp_path / "n.parquet"), device="A", column="gx", row=2)
    report = LoadReport()
    recs = load(tmp_path / "n.parquet", drop_invalid=True, report=report)
    np.testing.assert_array_equal(recs[0].gyro[:, 0], [0.1, 0.3])
    assert report.n_dropped == 1
    frame["gy"] = ["1", "2", "3", "four", "5"]
    frame.to_parquet(tmp_path / "s.parquet")
    err = error_of(tmp_path / "s.parquet", drop_invalid=True)
    assert_names(err, device="B", column="gy", row=4)
    assert "'four'" in str(err)


def test_bad_cell_far_down_a_large_file(tmp_path):
    # pandas infers types in chunks; the row reported must still be the file row
    n = 70_000
    lines = ["t,gx,gy,gz"] + [f"{i},0.5,{i % 7},1" for i in range(n)]
    lines[60_001] = "60000,0.5,x7,1"
    lines[50_001] = "50000,0.5,,1"
    err = error_of(write(tmp_path / "long.csv", "\n".join(lines)), drop_invalid=True)
    assert_names(err, column="gy", row=60_001)
    lines[60_001] = "60000,0.5,nan,1"
    report = LoadReport()
    rec = load(write(tmp_path / "long.csv", "\n".join(lines)), drop_invalid=True,
               report=report, check_units=False)[0]
    assert rec.n == n - 2 and [d.first_row for d in report.dropped] == [50_001]
    np.testing.assert_array_equal(rec.gyro[:, 1], [i % 7 for i in range(n)
                                                   if i not in (50_000, 60_000)])


# ---------------------------------------------------------------- drop_invalid


def test_drop_invalid_reports_counts_per_device(tmp_path):
    path = write(tmp_path / "holes.csv", long_text({(3, "gx"): "", (5, "temp"): "nan",
                                                    (4, "gz"): "-inf"}))
    report = LoadReport()
    recs = load(path, drop_invalid=True, report=report)
    assert [r.n for r in recs] == [2, 3]
    np.testing.assert_array_equal(recs[0].t, [0, 3])  # A lost rows 3 and 5 (t = 1, 2)
    np.testing.assert_array_equal(recs[1].t, [0, 2, 3])  # B lost row 4 (t = 1)
    assert [(d.device, d.rows, d.first_row) for d in report.dropped] == [("A", 2, 3),
                                                                         ("B", 1, 4)]
    assert report.lines()[0] == ("dropped 2 rows with empty, NaN, inf or non-physical cells "
                                 f"in file {path} device A (first: row 3)")
    # non-numeric text and bad times are still errors
    assert "non-numeric" in str(error_of(write(tmp_path / "t.csv", long_text({(3, "gx"): "x"})),
                                         drop_invalid=True))
    assert "repeats" in str(error_of(write(tmp_path / "r.csv", long_text({(3, "t"): "0"})),
                                     drop_invalid=True))
    # a device with nothing left is an error, not a silent disappearance
    text = "t,gx,gy,gz\n0,nan,0,0\n1,0,,0\n"
    err = error_of(write(tmp_path / "gone.csv", text), drop_invalid=True)
    assert "0 samples after dropping invalid rows" in str(err)


def test_load_from_cli_prints_drop_report(tmp_path, capsys):
    from diffgyro.internal import load_from_cli

    path = write(tmp_path / "x.csv", "gyr_x,gyr_y,gyr_z\n1,2,3\n4,,6\n7,8,9\n")
    batch = load_from_cli([path], columns="gx=gyr_x,gy=gyr_y,gz=gyr_z", gyro_unit="deg/s",
                          sampling_rate=10.0, drop_invalid=True)
    assert isinstance(batch, Batch) and batch.devices == ("x",)
    np.testing.assert_allclose(batch.gyro[0, 1], np.deg2rad([7, 8, 9]))
    assert ("dropped 1 row with empty, NaN, inf or non-physical cells "
            f"in file {path} device x") in capsys.readouterr().err


# ---------------------------------------------------------------- batches


def test_bucket_length_and_mask(tmp_path):
    recs = [make_recording(f"d{i}", n, i) for i, n in enumerate([1000, 1013, 990])]
    batch = load_batch(save(recs, tmp_path / "r.npz"), check_units=False)
    other = Batch.from_recordings([make_recording("e", 1020, 9)])
    assert batch.length == other.length == 1024  # slightly different lengths share a bucket
    np.testing.assert_array_equal(batch.n_valid, [1000, 1013, 990])
    np.testing.assert_array_equal(batch.mask.sum(axis=1), [1000, 1013, 990])
    for i, r in enumerate(recs):
        assert batch.mask[i, : r.n].all() and not batch.mask[i, r.n:].any()
        assert np.all(np.diff(batch.t[i]) > 0)  # padded times keep increasing
        assert_same(r, batch.recording(i))


# ---------------------------------------------------------------- property test

_COLS = ["device", "t", "gx", "gy", "gz", "temp", "ax", "ay", "az", "junk"]
_CELLS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-10**20, 10**20).map(str),
    st.sampled_from(["", " ", "nan", "NA", "inf", "-", "1e", "0x1", "1,5", '"', "\"1\"",
                     "true", "A", "B", "1_0", "\t", "١٢"]),
    st.text(max_size=6),
)


@st.composite
def csv_text(draw):
    """CSV bytes from mostly well-formed to garbage: every outcome must be handled."""
    kind = draw(st.integers(0, 9))
    if kind == 0:
        return draw(st.binary(max_size=200))
    if kind == 1:
        return draw(st.text(max_size=200)).encode("utf-8", "surrogatepass")
    groups = ("t", "gx gy gz") + tuple(draw(st.lists(st.sampled_from(
        ["device", "temp", "ax ay az", "junk"]), max_size=3, unique=True)))
    cols = draw(st.permutations(" ".join(groups).split()))
    if draw(st.integers(0, 4)) == 0:  # damage the header
        cols = cols + draw(st.lists(st.sampled_from(_COLS), max_size=2))
        if len(cols) > 1 and draw(st.booleans()):
            cols.pop(draw(st.integers(0, len(cols) - 1)))
    bad_rate = draw(st.sampled_from([0, 0, 0.02, 0.2]))
    sep = draw(st.sampled_from([",", ",", ";", "\t"]))
    n = draw(st.integers(0, 12))
    lines = [sep.join(cols)]
    t = 0.0
    for _ in range(n):
        t += draw(st.sampled_from([0.25, 0.25, 0.25, 1e-9, 0.0, -0.3]))
        row = []
        for c in cols:
            if draw(st.floats(0, 1)) < bad_rate:
                row.append(draw(_CELLS))
            elif c == "t":
                row.append(repr(t))
            elif c == "device":
                row.append(draw(st.sampled_from(["A", "B", " A "])))
            else:
                row.append(repr(draw(st.floats(-1e3, 1e3))))
        if draw(st.floats(0, 1)) < bad_rate:
            row = row[:-1] if draw(st.booleans()) else row + ["9"]
        lines.append(sep.join(row))
    end = draw(st.sampled_from(["\n", "\r\n", ""]))
    return (end or "\n").join(lines).encode("utf-8", "surrogatepass") + end.encode()


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(content=csv_text(), drop_invalid=st.booleans())
def test_malformed_csv_gives_data_error_or_valid_recording(fuzz_dir, content, drop_invalid):
    path = fuzz_dir / "fuzz.csv"
    path.write_bytes(content)
    try:
        recs = load(path, drop_invalid=drop_invalid)
    except DataError as err:
        assert str(err) and "\n" not in str(err)
        return
    assert recs
    for r in recs:
        assert r.n >= 2
        assert r.t.dtype == np.float64 and r.t.shape == (r.n,)
        assert np.all(np.diff(r.t) > 0)
        assert r.gyro.shape == (r.n, 3)
        for sig in r.signals:
            arr = getattr(r, sig)
            assert arr.dtype == np.float64 and arr.shape[0] == r.n
            assert np.all(np.isfinite(arr))
