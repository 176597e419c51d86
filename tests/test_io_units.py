"""Units that cannot pass silently: units read from headers, implausible numbers refused
or flagged, on every simulator plan and on the real recordings in tests/data."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from diffgyro.errors import DataError
from diffgyro.internal import header_units, merge_units, split_header
from diffgyro.io import LoadReport, load, save
from diffgyro.simulate import simulate

DATA = Path(__file__).resolve().parent / "data"

# every plan of diffgyro.simulate, shortened (2 devices each)
PLANS = {
    "thermal": {"duration": 1800.0},
    "rate_table": {"temps": (20.0,), "rates": (30.0, 300.0), "axes": "xz", "settle": 2.0},
    "s2": {"t_min": -10.0, "t_max": 10.0, "settle": 5.0},
    "six_face": {"dwell": 10.0, "headings": 2},
    "static": {"duration": 60.0},
    "warmup": {"duration": 600.0},
    "attitude": {"duration": 60.0},
}
GYRO, ACCEL, TEMP = ["gx", "gy", "gz", "rx", "ry", "rz"], ["ax", "ay", "az"], ["temp", "temp_ext"]
# how a file in another unit is written: (columns, factor, offset), signal, the option
WRITTEN = {
    "deg/s": (GYRO, 180.0 / math.pi, 0.0, "gyro", {"gyro": "deg/s"}),
    "mdps": (GYRO, 180e3 / math.pi, 0.0, "gyro", {"gyro": "mdps"}),
    "g": (ACCEL, 1.0 / 9.80665, 0.0, "accel", {"accel": "g"}),
    "mg": (ACCEL, 1e3 / 9.80665, 0.0, "accel", {"accel": "mg"}),
    "K": (TEMP, 1.0, 273.15, "temp", {"temp": "K"}),
    "ms": (["t"], 1e3, 0.0, "t", {"t": "ms"}),
    "us": (["t"], 1e6, 0.0, "t", {"t": "us"}),
}


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Each plan simulated once (SI units), as a data frame; s2 also with a MEMS gyro."""
    out, d = {}, tmp_path_factory.mktemp("plans")
    runs = {p: (p, {}) for p in PLANS} | {"s2 mems": ("s2", {"preset": "mems"})}
    for key, (plan, extra) in runs.items():
        batch, _ = simulate(plan, 2, seed=3, **PLANS[plan], **extra)
        path = save(batch, d / f"{key.replace(' ', '_')}.parquet")
        out[key] = pd.read_parquet(path)
    return out


def _write(frame: pd.DataFrame, unit: str | None, path: Path) -> Path:
    frame = frame.copy()
    if unit is not None:
        cols, factor, offset, _, _ = WRITTEN[unit]
        frame[cols] = frame[cols] * factor + offset
    frame.to_parquet(path)
    return path


def _load(path: Path, units=None) -> tuple[list[str], str | None]:
    """(unit lines, the refusal or None)."""
    report = LoadReport()
    try:
        load(path, units=units, report=report)
    except DataError as err:
        return [u.message() for u in report.units], str(err)
    return [u.message() for u in report.units], None


@pytest.mark.parametrize("plan", list(PLANS) + ["s2 mems"])
def test_every_plan_in_si_units_passes_without_a_warning(frames, plan, tmp_path):
    lines, refused = _load(_write(frames[plan], None, tmp_path / "si.parquet"))
    assert refused is None and lines == []


@pytest.mark.parametrize("plan", list(PLANS) + ["s2 mems"])
def test_every_plan_in_other_units_is_flagged_and_passes_with_the_option(frames, plan, tmp_path):
    for unit, (cols, _, _, signal, option) in WRITTEN.items():
        if plan == "s2" and unit == "deg/s":
            continue  # a FOG in °/s looks like a tactical MEMS in rad/s ("s2 mems" has its gyro)
        path = _write(frames[plan], unit, tmp_path / f"{unit.replace('/', '_')}.parquet")
        lines, refused = _load(path)
        opt = {"gyro": "--gyro-unit", "accel": "--acc-unit", "temp": "--temp-unit",
               "t": "--time-unit"}[signal]
        if refused is not None:  # one line naming file, column and the option that passes
            assert str(path) in refused and cols[0] in refused, (unit, refused)
            assert f"give {opt} {unit}," in refused, (unit, refused)
            assert "\n" not in refused
        else:
            assert len(lines) == 1 and lines[0].startswith("warning: ") and opt in lines[0], \
                (unit, lines)
        assert _load(path, option) == ([], None), unit  # the right option: no warning


def test_a_fog_in_mdps_and_a_time_base_in_us_are_refused(frames, tmp_path):
    _, refused = _load(_write(frames["s2"], "mdps", tmp_path / "fog.parquet"))
    assert refused is not None and "--gyro-unit mdps" in refused
    _, refused = _load(_write(frames["thermal"], "us", tmp_path / "us.parquet"))
    assert refused is not None and "--time-unit us" in refused


def test_an_explicit_si_option_keeps_implausible_numbers(frames, tmp_path):
    path = _write(frames["static"], "deg/s", tmp_path / "deg.parquet")
    recs = load(path, units={"gyro": "rad/s"})  # the user says rad/s: numbers kept as written
    np.testing.assert_array_equal(recs[0].gyro[:, 0],
                                  frames["static"]["gx"].to_numpy()[:6000] * (180.0 / math.pi))


def test_raw_counts_are_kept_with_a_warning(frames, tmp_path):
    frame = frames["static"].copy()
    frame[GYRO] = np.round(frame[GYRO] * 180 / math.pi * 131.0) + 32768.0  # 16-bit ±250 °/s
    frame[ACCEL] = np.round(frame[ACCEL] / 9.80665 * 16384.0)
    lines, refused = _load(_write(frame, None, tmp_path / "counts.parquet"))
    assert refused is None and len(lines) == 2
    assert all("whole numbers (raw counts?)" in line for line in lines)


def test_python_api_warns_without_a_report(frames, tmp_path):
    path = _write(frames["static"], "ms", tmp_path / "ms.parquet")
    with pytest.warns(UserWarning, match="--time-unit ms"):
        load(path)


# ---------------------------------------------------------------- headers


@pytest.mark.parametrize(("header", "split"), [
    ("Gyroscope X (deg/s)", ("Gyroscope X", "deg/s")), ("gyr_x[dps]", ("gyr_x", "dps")),
    ("acc z {m/s²}", ("acc z", "m/s²")), ("t (µs)", ("t", "µs")), ("gx", None), ("(K)", None),
])
def test_split_header(header, split):
    assert split_header(header) == split


def test_header_names_and_units():
    names = ["Time (ms)", "Gyroscope X (deg/s)", "Gyroscope Y (°/s)", "Gyroscope Z (dps)",
             "acc_x[m/s^2]", "acc_y[m/s²]", "acc_z[m/s2]", "T (K)", "Magnetometer X (uT)"]
    got = header_units(names, {})
    assert got.columns == {"t": "Time (ms)", "gx": "Gyroscope X (deg/s)",
                           "gy": "Gyroscope Y (°/s)", "gz": "Gyroscope Z (dps)",
                           "ax": "acc_x[m/s^2]", "ay": "acc_y[m/s²]", "az": "acc_z[m/s2]",
                           "temp": "T (K)"}
    assert got.units == {"t": "ms", "gyro": "deg/s", "accel": "m/s^2", "temp": "K"}
    assert "gyro in deg/s ('Gyroscope X (deg/s)' as gx" in got.describe()
    # the user's mapping wins, and the header of a column it maps still gives the unit
    got = header_units(["gx", "gyr_x (mdps)", "gy", "gz"], {"gx": "gyr_x (mdps)"})
    assert got.columns == {} and got.units == {"gyro": "mdeg/s"}
    with pytest.raises(DataError, match=r"file f.csv, column gy \(rad/s\): the headers give gyro "
                                        r"two units: deg/s \('gx \(deg/s\)'\) and rad/s"):
        header_units(["gx (deg/s)", "gy (rad/s)", "gz (deg/s)"], {}, "f.csv")


def test_a_header_that_contradicts_the_option_is_refused():
    header = header_units(["t", "Gyroscope X (deg/s)", "Gyroscope Y (deg/s)",
                           "Gyroscope Z (deg/s)"], {})
    assert merge_units(header, {"gyro": "dps"}, "f.csv")["gyro"] == "dps"  # the same unit
    with pytest.raises(DataError, match=r"file f.csv, column Gyroscope X \(deg/s\): the header "
                                        r"says deg/s but --gyro-unit rad/s was given"):
        merge_units(header, {"gyro": "rad/s"}, "f.csv")


def _issue_example(path: Path) -> Path:
    """A handheld recording as the issue has it: readable headers, °/s, g, an extra column."""
    frame = pd.read_csv(DATA / "imucal" / "example_ferraris_session.csv", nrows=4000)
    out = pd.DataFrame({"time (s)": frame["n_samples"] / 102.4})
    for ax in "xyz":
        out[f"Gyroscope {ax.upper()} (deg/s)"] = frame[f"gyr_{ax}"]
    for ax in "xyz":
        out[f"Accelerometer {ax.upper()} (g)"] = frame[f"acc_{ax}"] / 9.80665
    out["Magnetometer X (uT)"] = 20.0
    out.to_csv(path, index=False)
    return path


def test_the_issue_example_reads_its_units_from_the_headers(tmp_path):
    path = _issue_example(tmp_path / "handheld.csv")
    frame = pd.read_csv(DATA / "imucal" / "example_ferraris_session.csv", nrows=4000)
    report = LoadReport()
    rec = load(path, report=report)[0]
    np.testing.assert_allclose(rec.gyro[:, 0], frame["gyr_x"] * math.pi / 180.0, rtol=1e-15)
    np.testing.assert_allclose(rec.accel[:, 2], frame["acc_z"], rtol=1e-12)
    assert rec.aux.keys() == {"Magnetometer X (uT)"}
    assert len(report.units) == 1 and report.units[0].kind == "mapped"
    assert "gyro in deg/s ('Gyroscope X (deg/s)' as gx" in report.units[0].message()
    assert np.abs(rec.gyro).max() < 35.0  # rad/s, a 2000 °/s full scale (not "rad/s" in °/s)


def test_fit_cli_on_the_issue_example(tmp_path, capsys):
    from diffgyro.cli import main

    path = _issue_example(tmp_path / "handheld.csv")
    assert main(["fit", str(path), "--model", "bias_poly(0)", "--json"]) == 0
    out, err = capsys.readouterr()
    assert "units from the headers: t in s" in err and "gyro in deg/s" in err
    record = json.loads(out)
    assert record["units"][0]["kind"] == "mapped"
    assert main(["allan", str(path), "--json"]) == 0
    out, err = capsys.readouterr()
    assert json.loads(out)["units"] == record["units"] and "gyro in deg/s" in err
    assert main(["fit", str(path), "--model", "bias_poly(0)", "--gyro-unit", "rad/s"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "column Gyroscope X (deg/s)" in err and "--gyro-unit" in err


# ---------------------------------------------------------------- real recordings


def test_real_recordings_behave(tmp_path):
    imucal = DATA / "imucal" / "example_ferraris_session.csv"
    cols = {"gx": "gyr_x", "gy": "gyr_y", "gz": "gyr_z", "ax": "acc_x", "ay": "acc_y",
            "az": "acc_z"}
    # a real recording in °/s read as rad/s: refused, naming the option that passes it
    with pytest.raises(DataError, match=r"example_ferraris_session.csv, column gyr_x \(gx\).*"
                                        r"not plausible in rad/s.*--gyro-unit deg/s"):
        load(imucal, cols, sampling_rate=102.4)
    report = LoadReport()
    load(imucal, cols, {"gyro": "deg/s"}, sampling_rate=102.4, report=report)
    assert report.units == []  # its accelerometer is in m/s² and passes
    # IMU-TK's raw counts load (the multi-position recipe calibrates them), with a warning
    acc = np.loadtxt(DATA / "imu_tk" / "xsens_acc.mat")
    gyr = np.loadtxt(DATA / "imu_tk" / "xsens_gyro.mat")
    n = min(len(acc), len(gyr))
    pd.DataFrame({"t": acc[:n, 0], "ax": acc[:n, 1], "ay": acc[:n, 2], "az": acc[:n, 3],
                  "gx": gyr[:n, 1], "gy": gyr[:n, 2], "gz": gyr[:n, 3]}).to_csv(
        tmp_path / "xsens.csv", index=False)
    report = LoadReport()
    load(tmp_path / "xsens.csv", report=report)
    assert [u.signal for u in report.units] == ["gyro", "accel"]
    assert all("raw counts" in u.message() for u in report.units)
    # logs are read in SI by their readers: nothing to say; a flight log written out as a
    # table (moving, vibrating) is still plausible in SI
    for name in ("sample.ulg", "sample_log_small.ulg"):
        report = LoadReport()
        recs = load(DATA / "px4" / name, report=report)
        assert report.units == []
        load(save(recs, tmp_path / "px4.parquet"), report=report)
        assert report.units == []


def test_a_streamed_device_in_mdps_fails_alone(tmp_path):
    """The streamed pipeline reads row groups, not whole files: a device only plausible in
    another unit fails on its own (invalid_data, the option in its reason), the rest fit."""
    from pipeline_data import MODEL, load_outputs, simulated, write_parquet

    from diffgyro.pipeline import fit_dataset

    batch, _ = simulated(3, 5, "u-")
    frames = [r.to_frame() for r in batch.recordings()]
    frames[1][["gx", "gy", "gz"]] *= 180e3 / math.pi
    write_parquet(pd.concat(frames, ignore_index=True), tmp_path / "data" / "a.parquet")
    out = tmp_path / "cal.json"
    fit_dataset([tmp_path / "data"], MODEL, out=out, chunk_devices=3, progress=False)
    status = {r["device"]: r for r in load_outputs(out)[1]}
    assert status["u-001"]["status"] == "invalid_data"
    assert "not plausible in rad/s" in status["u-001"]["reason"]
    assert "--gyro-unit mdps" in status["u-001"]["reason"]
    assert status["u-000"]["status"] == status["u-002"]["status"] == "ok"


def test_every_refused_signal_in_one_line(frames, tmp_path):
    frame = frames["static"].copy()
    frame[GYRO] *= 180e3 / math.pi
    frame[ACCEL] /= 9.80665
    _, refused = _load(_write(frame, None, tmp_path / "both.parquet"))
    assert refused is not None and "\n" not in refused
    assert "column gx, gy, gz: gyro read as rad/s" in refused
    assert "column ax, ay, az: accelerometer read as m/s²" in refused
    assert "give --gyro-unit mdps and --acc-unit g, or --gyro-unit rad/s and --acc-unit m/s²" \
        in refused
