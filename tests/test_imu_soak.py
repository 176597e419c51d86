"""One thermal soak, the whole IMU: the gyro and the accelerometer calibrated from the same
run, exported together, and applied with each autopilot's own formula (written here from
PX4's and ArduPilot's source, not by calling diffgyro) to an unseen soak of the same boards.

Three simulated boards: a cubic thermal offset on every gyro and accelerometer, and on
board 2's accelerometer a dT/dt term as well (which no autopilot parameter holds).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import medfilt
from test_logs import write_dataflash

from diffgyro import calibration
from diffgyro.cli import main
from diffgyro.diagnose import diagnose
from diffgyro.errors import DataError
from diffgyro.export import render
from diffgyro.fit import fit
from diffgyro.io import LoadReport, load_batch
from diffgyro.model import Params
from diffgyro.simulate import simulate

PX4 = Path(__file__).parent / "data" / "px4"
MODEL = "bias_poly(3)"
ACCEL = "bias_poly(3)+gradient"
#: Accelerometer truth (m/s² per unit regressor, T_s basis): c0..c3 and dT/dt (per °C/s).
ACC_BETA = np.array([
    [[0.02, 0.09, 0.03, -0.02, 0.0], [-0.01, -0.05, 0.02, 0.015, 0.0], [0.03, 0.12, -0.04, 0.01, 0.0]],
    [[-0.03, 0.06, -0.02, 0.01, 0.0], [0.02, 0.08, 0.01, -0.02, 0.0], [-0.02, -0.10, 0.03, 0.02, 0.0]],
    [[0.01, -0.07, 0.02, 0.01, 0.6], [0.02, 0.05, -0.03, 0.0, -0.5], [-0.01, 0.09, 0.02, -0.01, 0.7]],
])
ACC_PARAMS = Params(beta=ACC_BETA, theta=np.zeros((3, 0)))
RUN = {"sample_rate": 10.0, "duration": 3600.0}
UNSEEN = {"start_temp": 20.0, "profile": ((45.0, 1.5, 15.0), (0.0, 1.0, 15.0), (30.0, 0.5, 10.0))}
#: The sensors' ids as a PX4 log gives them; the accelerometers' instance order differs
#: from the gyros' (instance k is board 2 − k's), as it may on a real board.
GYRO_IDS = [0x240012, 0x380022, 0x280032]
ACCEL_IDS = [0x24A012, 0x38A022, 0x28A032]
ACCEL_BOARD = [2, 1, 0]


@pytest.fixture(scope="module")
def soak():
    """The calibration soak, its fits, and an unseen soak of the same boards."""
    batch, truth = simulate("thermal", 3, effects=MODEL, seed=41, accel_effects=ACCEL,
                            accel_params=ACC_PARAMS, **RUN)
    unseen, ut = simulate("thermal", 3, effects=MODEL, seed=42, params=truth.params,
                          temp_norm=truth.norm, accel_effects=ACCEL, accel_params=ACC_PARAMS,
                          keep_components=True, **RUN, **UNSEEN)
    gyro = calibration.from_fit(fit(MODEL, batch), batch)
    accel = calibration.from_fit(fit(MODEL, batch.select([0, 1]), channel="accel"))
    return batch, truth, unseen, ut, gyro, accel


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def _noise(unseen, ut, i: int):
    """The unseen soak's readings of board i and the noise the simulator added to each."""
    n = int(unseen.n_valid[i])
    gyro, acc = np.asarray(unseen.gyro[i, :n]), np.asarray(unseen.accel[i, :n])
    temp = np.asarray(unseen.temp[i, :n])
    g_noise = gyro - ut.env["rate"][i] - ut.env["error"][i]
    clean = ((np.eye(3) + ut.accel["error_matrix"][i]) @ ut.env["specific_force"][i].T).T
    a_noise = acc - clean - ut.accel["bias"][i] - ut.env["accel_thermal"][i]
    return gyro, acc, temp, ut.env["rate"][i], g_noise, a_noise


def _px4_params(text: str) -> dict:
    out = {}
    for line in text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        _, _, name, value, typ = line.split("\t")
        out[name] = int(value) if typ == "6" else float(np.float32(value))
    return out


def _px4_offset(p: dict, prefix: str, temp) -> np.ndarray:
    """TemperatureCompensation.cpp calc_thermal_offsets_3D, in float32: dT = clamp(T, TMIN,
    TMAX) − TREF; offset = X0 + X1·dT + X2·dT² + X3·dT³ per axis (subtracted from the raw
    reading by Gyroscope/Accelerometer::Correct)."""
    f = np.float32
    t = np.clip(temp.astype(f), f(p[prefix + "TMIN"]), f(p[prefix + "TMAX"]))
    d = t - f(p[prefix + "TREF"])
    return np.stack([sum(f(p[f"{prefix}X{k}_{i}"]) * d**k for k in range(4)) for i in range(3)], -1)


def _slot(p: dict, letter: str, device_id: int) -> str:
    """PX4's slot for a sensor: the TC_{letter}n whose ID equals its device_id."""
    hits = [n for n in range(4) if p.get(f"TC_{letter}{n}_ID") == device_id]
    assert len(hits) == 1, (letter, device_id, hits)
    return f"TC_{letter}{hits[0]}_"


def test_px4_parameters_leave_each_channel_at_its_noise(soak):
    _, _, unseen, ut, gyro, accel = soak
    text, _ = render(gyro, "px4", device_ids=GYRO_IDS, accel=accel, accel_ids=ACCEL_IDS[:2])
    p = _px4_params(text)
    assert p["TC_G_ENABLE"] == 1 and p["TC_A_ENABLE"] == 1
    for i in range(3):
        raw_g, raw_a, temp, rate, g_noise, a_noise = _noise(unseen, ut, i)
        corrected = raw_g - _px4_offset(p, _slot(p, "G", GYRO_IDS[i]), temp)
        assert _rms(corrected - rate) <= 1.05 * _rms(g_noise), i
        if i < 2:  # the cubic boards; board 2's dT/dt term is no TC_A parameter
            c = raw_a - _px4_offset(p, _slot(p, "A", ACCEL_IDS[i]), temp)
            # the constant is the accelerometer calibration's (CAL_ACCn_*OFF)
            assert _rms(c - c.mean(0)) <= 1.05 * _rms(a_noise - a_noise.mean(0)), i
            before = _rms(raw_a - raw_a.mean(0))
            assert before > 5 * _rms(a_noise), i  # the thermal offset was there to remove


def _ardupilot_params(text: str) -> dict:
    out = {}
    for line in text.splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, value = line.split(",")
            out[name] = float(np.float32(value))
    return out


def _ardupilot_correct(p: dict, n: int, raw, temp, letters: str, cal_temp: float, offs):
    """AP_InertialSensor_tempcal.cpp TCal::correct_sensor, then the offset: P(d) = (c1 + (c2 +
    c3·d)·d)·d·1e-6, T and the calibration temperature constrained to [TMIN, TMAX],
    v −= P(T − 35); v += P(Tcal − 35); v −= offset."""
    lo, hi = p[f"INS_TCAL{n}_TMIN"], p[f"INS_TCAL{n}_TMAX"]
    t, tc = np.clip(temp, lo, hi), np.clip(cal_temp, lo, hi)
    out = np.array(raw, float)
    for i, ax in enumerate("XYZ"):
        c1, c2, c3 = (p[f"INS_TCAL{n}_{letters}{k}_{ax}"] for k in (1, 2, 3))

        def poly(d, c1=c1, c2=c2, c3=c3):
            return (c1 + (c2 + c3 * d) * d) * d * 1e-6

        out[:, i] = out[:, i] - poly(t - 35.0) + poly(tc - 35.0) - offs[i]
    return out


def test_ardupilot_parameters_leave_each_channel_at_its_noise(soak):
    _, _, unseen, ut, gyro, accel = soak
    two = calibration.from_json(gyro.to_json() | {"devices": gyro.to_json()["devices"][:2]})
    p = _ardupilot_params(render(two, "ardupilot", accel=accel)[0])
    for i in range(2):
        n = i + 1
        raw_g, raw_a, temp, rate, g_noise, a_noise = _noise(unseen, ut, i)
        stem = "INS_GYROFFS" if n == 1 else f"INS_GYR{n}OFFS"
        g = _ardupilot_correct(p, n, raw_g, temp, "GYR", p[f"INS_GYR{n}_CALTEMP"],
                               [p[f"{stem}_{ax}"] for ax in "XYZ"])
        assert _rms(g - rate) <= 1.05 * _rms(g_noise), i
        # an accelerometer calibration made at 25 °C (INS_ACCn_CALTEMP) measured offsets
        # that are constant over the soak: the residual's mean
        a = _ardupilot_correct(p, n, raw_a, temp, "ACC", 25.0, [0.0, 0.0, 0.0])
        assert _rms(a - a.mean(0)) <= 1.05 * _rms(a_noise - a_noise.mean(0)), i


def test_dtdt_board_is_named_and_refused(soak, tmp_path):
    batch, _, _, _, _, _ = soak
    diag = diagnose(MODEL, batch, ["gradient", "temp_diff"], channel="accel", greedy=False,
                    synthesis=False, noise=False)
    verdicts = {d.device: d for d in diag.devices}
    dev2 = verdicts[batch.devices[2]]
    assert dev2.verdict == "missing_effect" and dev2.best.effect == "gradient"
    assert all(verdicts[batch.devices[i]].verdict == "adequate" for i in (0, 1))
    assert diag.to_json()["channel"] == "accel"
    # the report draws the accelerometer in m/s²: the named term refitted on what was fitted
    # (the accelerometer less its reference) leaves board 2 at its noise floor
    from diffgyro.channel import fitted_batch
    from diffgyro.report import named_term_residuals, write_report

    spec, e_new = named_term_residuals(diag, fitted_batch(diag.fit, batch))[2]
    assert spec == ACCEL
    assert 0.8 < _rms(e_new) / np.sqrt(np.mean(np.square(dev2.noise_axes))) < 1.2
    write_report(diag, batch, tmp_path)
    page = (tmp_path / f"{batch.devices[2]}.html").read_text()
    assert "m/s²" in page and "rad/s" not in page and "with gradient" in page
    # the cubic alone leaves board 2's dT/dt residual: written with a warning that says so
    cubic = calibration.from_fit(fit(MODEL, batch.select([2]), channel="accel"))
    text, report = render(cubic, "px4", device_ids=[ACCEL_IDS[0]])
    warning = f"WARNING: device {batch.devices[2]}: held-out RMS"
    assert any(line.startswith(warning) for line in report) and f"# {warning}" in text
    full = calibration.from_fit(fit(ACCEL, batch.select([2]), channel="accel"))
    with pytest.raises(DataError, match="term gradient cannot be written as px4"):
        render(full, "px4")


def _process_sensor_caldata(temp, x):
    """PX4 Tools/process_sensor_caldata.py, accelerometer axis: a 31-sample median filter,
    the reading less its median, TREF = (TMIN + TMAX)/2, the samples averaged in 2000 equal
    bins of T − TREF, a cubic least-squares fit of the bin means; coefficients X0..X3."""
    lo, hi = temp.min(), temp.max()
    ref = 0.5 * (lo + hi)
    rel = temp - ref
    y = medfilt(x, 31)
    y = y - np.median(y)
    edges = (rel - rel.min()) / ((rel.max() - rel.min()) / 2000)
    idx = np.minimum(edges.astype(int), 1999)
    count = np.bincount(idx, minlength=2000)
    keep = count > 0
    bx = np.bincount(idx, rel, 2000)[keep] / count[keep]
    by = np.bincount(idx, y, 2000)[keep] / count[keep]
    return np.polyfit(bx, by, 3)[::-1], ref, lo, hi


def test_accel_coefficients_agree_with_process_sensor_caldata(soak):
    batch, truth, unseen, ut, _, accel = soak
    p = _px4_params(render(accel, "px4", device_ids=ACCEL_IDS[:2])[0])
    for i in range(2):
        n = int(batch.n_valid[i])
        temp, acc = np.asarray(batch.temp[i, :n]), np.asarray(batch.accel[i, :n])
        t = np.linspace(temp.min(), temp.max(), 200)
        for ax in range(3):
            c, ref, lo, hi = _process_sensor_caldata(temp, acc[:, ax])
            prefix = _slot(p, "A", ACCEL_IDS[i])
            assert p[prefix + "TREF"] == pytest.approx(ref, abs=1e-4)
            ours = sum(p[f"{prefix}X{k}_{ax}"] * (t - ref) ** k for k in range(4))
            theirs = sum(c[k] * (t - ref) ** k for k in range(4))
            # the same curve, up to the constant (PX4's is relative to the median reading,
            # diffgyro's to TREF) and to the fit's own uncertainty
            diff = (ours - ours.mean()) - (theirs - theirs.mean())
            sigma = float(accel.devices[i].quality["noise_floor"])
            assert np.abs(diff).max() < 0.1 * sigma, (i, ax, np.abs(diff).max() / sigma)
        # applied to the unseen soak, neither method leaves more than the other (docs/imu.md)
        raw_a, utemp, a_noise = (_noise(unseen, ut, i)[k] for k in (1, 2, 5))
        ours = raw_a - _px4_offset(p, _slot(p, "A", ACCEL_IDS[i]), utemp)
        theirs = np.stack([raw_a[:, ax] - np.polyval(
            _process_sensor_caldata(temp, acc[:, ax])[0][::-1],
            np.clip(utemp, temp.min(), temp.max()) - 0.5 * (temp.min() + temp.max()))
            for ax in range(3)], -1)
        noise = _rms(a_noise - a_noise.mean(0))
        assert _rms(ours - ours.mean(0)) <= 1.001 * _rms(theirs - theirs.mean(0))
        assert _rms(theirs - theirs.mean(0)) <= 1.01 * noise


def _write_ulog(path: Path, batch) -> None:
    """sensor_gyro / sensor_accel instances through pyulog's writer (PX4's own message
    definitions from the real log in tests/data/px4, their data replaced): gyro instance k
    is board k, accelerometer instance k board ACCEL_BOARD[k], each with its own id."""
    import pyulog

    ulog = pyulog.ULog(str(PX4 / "sample_log_small.ulg"), ["sensor_gyro", "sensor_accel"])
    for d in ulog.data_list:
        k = d.multi_id
        board = k if d.name == "sensor_gyro" else ACCEL_BOARD[k]
        n = int(batch.n_valid[board])
        us = np.round(np.asarray(batch.t[board, :n]) * 1e6).astype(np.uint64) + 1_000_000
        new = {name: np.zeros(n, dtype=v.dtype) for name, v in d.data.items()}
        new["timestamp_sample"], new["timestamp"] = us, us + 300
        new["device_id"][:] = GYRO_IDS[board] if d.name == "sensor_gyro" else ACCEL_IDS[k]
        new["temperature"] = np.asarray(batch.temp[board, :n], np.float32)
        values = batch.gyro if d.name == "sensor_gyro" else batch.accel
        for j, axis in enumerate("xyz"):
            new[axis] = np.asarray(values[board, :n, j], np.float32)
        d.data = new
    ulog.write_ulog(str(path))


def test_ulog_accelerometers_matched_to_their_device_ids(soak, tmp_path, capsys):
    batch, truth, _, _, _, _ = soak
    log = tmp_path / "soak.ulg"
    _write_ulog(log, batch)
    report = LoadReport()
    acc = load_batch([log], report=report, channel="accel")
    assert acc.devices == ("soak/accel0", "soak/accel1", "soak/accel2")
    assert report.device_ids == dict(zip(acc.devices, ACCEL_IDS))
    for k, board in enumerate(ACCEL_BOARD):  # each instance is its own board's accelerometer
        np.testing.assert_allclose(acc.temp[k, :int(acc.n_valid[k])],
                                   np.float32(batch.temp[board, :int(batch.n_valid[board])]))
    cal_g, cal_a = tmp_path / "gyro.json", tmp_path / "accel.json"
    assert main(["fit", str(log), "-m", MODEL, "--out", str(cal_g)]) == 0
    assert main(["fit", str(log), "-m", f"accel: {MODEL}", "--out", str(cal_a)]) == 0
    a = calibration.load(cal_a)
    assert a.channel == "accel" and [d.device_id for d in a.devices] == ACCEL_IDS
    capsys.readouterr()
    # the command line names the hidden dT/dt on board 2's accelerometer (instance 0)
    assert main(["diagnose", str(log), "-m", MODEL, "--channel", "accel", "--json",
                 "--candidates", "gradient,temp_diff", "--no-synthesis",
                 "--report", str(tmp_path / "report")]) == 0
    doc = json.loads(capsys.readouterr().out)
    index = (tmp_path / "report" / "index.html").read_text()
    assert "m/s²" in index and "rad/s" not in index
    verdicts = {d["device"]: d for d in doc["devices"]}
    assert doc["channel"] == "accel" and verdicts["soak/accel0"]["verdict"] == "missing_effect"
    assert verdicts["soak/accel0"]["candidates"][0]["effect"] == "gradient"
    assert verdicts["soak/accel0"]["candidates"][0]["significant"]
    assert {verdicts[f"soak/accel{k}"]["verdict"] for k in (1, 2)} == {"adequate"}
    out = tmp_path / "tc.params"
    # board 2's accelerometer (instance 0) keeps its dT/dt residual: written with a warning
    assert main(["export", str(cal_g), "--accel", str(cal_a), "--format", "px4",
                 "--out", str(out)]) == 0
    p = _px4_params(out.read_text())
    for k, board in enumerate(ACCEL_BOARD):
        prefix = _slot(p, "A", ACCEL_IDS[k])
        temp = np.linspace(p[prefix + "TMIN"] + 1, p[prefix + "TMAX"] - 1, 50)
        got = _px4_offset(p, prefix, temp)
        true = _true_accel_cubic(truth, board, temp) - _true_accel_cubic(
            truth, board, np.array([p[prefix + "TREF"]]))
        # the dT/dt board's cubic absorbs part of its gradient: judged on the cubic boards
        if board != 2:
            assert np.abs(got - true).max() < 0.01, (k, board)
    for k in range(3):
        assert _slot(p, "G", GYRO_IDS[k])
    err = capsys.readouterr().err
    assert "WARNING: device soak/accel0: held-out RMS" in err


def _true_accel_cubic(truth, board: int, temp) -> np.ndarray:
    ts = (temp - float(truth.norm.centre)) / float(truth.norm.scale)
    beta = truth.accel["thermal_beta"][board]
    return np.stack([sum(beta[i, j] * ts**j for j in range(4)) for i in range(3)], -1)


def test_dataflash_imus_calibrated_by_instance(soak, tmp_path):
    batch, truth, _, _, _, _ = soak
    devices = []
    for i in range(2):  # at 5 Hz (every other sample): DataFlash has no rate floor
        n = int(batch.n_valid[i])
        us = np.round(np.asarray(batch.t[i, :n:2]) * 1e6).astype(np.int64) + 1_000_000
        devices.append({"us": us, "gyro": np.asarray(batch.gyro[i, :n:2]),
                        "accel": np.asarray(batch.accel[i, :n:2]),
                        "temp": np.asarray(batch.temp[i, :n:2])})
    log = tmp_path / "soak.bin"
    ids = {"INS_GYR_ID": GYRO_IDS[0], "INS_GYR2_ID": GYRO_IDS[1], "INS_ACC_ID": ACCEL_IDS[0],
           "INS_ACC2_ID": ACCEL_IDS[1]}
    write_dataflash(log, devices, text=False, params=ids)
    cal_g, cal_a, out = tmp_path / "g.json", tmp_path / "a.json", tmp_path / "tcal.param"
    assert main(["fit", str(log), "-m", MODEL, "--out", str(cal_g)]) == 0
    assert main(["fit", str(log), "-m", MODEL, "--channel", "accel", "--out", str(cal_a)]) == 0
    assert main(["export", str(cal_g), "--accel", str(cal_a), "--format", "ardupilot",
                 "--out", str(out)]) == 0
    # each sensor's id from the log's INS_GYRn_ID / INS_ACCn_ID, and said beside its slot
    assert [d.device_id for d in calibration.load(cal_g).devices] == GYRO_IDS[:2]
    assert [d.device_id for d in calibration.load(cal_a).devices] == ACCEL_IDS[:2]
    assert f"INS_TCAL2 ACC (device_id {ACCEL_IDS[1]})" in out.read_text()
    p = _ardupilot_params(out.read_text())
    for i in range(2):
        n = i + 1
        lo, hi = p[f"INS_TCAL{n}_TMIN"], p[f"INS_TCAL{n}_TMAX"]
        temp = np.linspace(lo + 1, hi - 1, 50)
        got = _ardupilot_correct(p, n, np.zeros((50, 3)), temp, "ACC", 35.0, [0.0] * 3)
        true = _true_accel_cubic(truth, i, temp) - _true_accel_cubic(truth, i, np.array([35.0]))
        assert np.abs(-got - true).max() < 0.01, i


def test_real_ulog_accelerometers_each_refused_with_reason_and_id(capsys):
    """pyulog's real three-IMU log: every sensor_accel instance is logged at 1 Hz, so each
    is refused, named with its device_id."""
    log = PX4 / "sample_log_small.ulg"
    assert main(["fit", str(log), "-m", MODEL, "--channel", "accel"]) == 2
    err = capsys.readouterr().err
    for k, dev_id in enumerate((2424842, 3670050, 2621474)):
        assert f"sensor_accel instance {k} (device_id {dev_id}) is logged at 1 samples/s" in err


def test_accel_channel_refuses_what_it_cannot_hold(soak, capsys):
    batch = soak[0]
    with pytest.raises(Exception, match="cannot be fitted on the accelerometer channel"):
        fit("bias_poly(1)+g_sens", batch, channel="accel")
    import dataclasses

    with pytest.raises(DataError, match="needs ax, ay, az, which the data lack"):
        fit(MODEL, dataclasses.replace(batch.select([0]), accel=None), channel="accel")
    with pytest.raises(Exception, match="random_walk cannot be fitted on the accelerometer"):
        fit("bias_poly(1)+random_walk", batch, channel="accel")
    with pytest.raises(Exception, match="static_only"):
        fit(MODEL, batch, channel="accel", static_only=True)
    with pytest.raises(Exception, match="names channel accel"):
        from diffgyro.channel import resolve

        resolve("accel: bias_poly(3)", "gyro")


def test_tilt_between_runs_is_refused_with_the_turn(soak):
    """Board 0 turned by 30° about x halfway through the soak (the gyro sees the turn,
    gravity moves between axes): the accelerometer fit is in_motion, named by the IMU's
    motion check, and export refuses it with that reason."""
    import dataclasses

    one = soak[0].select([0])
    n = int(one.n_valid[0])
    gyro, acc = np.array(one.gyro), np.array(one.accel)
    k0, k1 = n // 2, n // 2 + 20  # 2 s at 10 Hz
    gyro[0, k0:k1, 0] += np.radians(30.0) / 2.0
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    acc[0, k1:n] = acc[0, k1:n] @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]]).T
    tilted = dataclasses.replace(one, gyro=gyro, accel=acc)
    result = fit(MODEL, tilted, channel="accel")
    rec = result.records()[0]
    assert rec["status"] == "in_motion" and "turns up to 30°" in rec["status_detail"]
    assert "one orientation" in rec["status_detail"] and "--static-only" not in rec["status_detail"]
    cal = calibration.from_fit(result)
    with pytest.raises(DataError, match="turns up to 30°"):
        render(cal, "px4")


def test_export_accel_only_where_the_format_has_a_table(tmp_path, capsys):
    for name in ("g.json", "a.json"):
        (tmp_path / name).write_text("{}")
    assert main(["export", str(tmp_path / "g.json"), "--accel", str(tmp_path / "a.json"),
                 "--format", "kalibr"]) == 2
    assert "--accel is for px4 and ardupilot" in capsys.readouterr().err


def test_spec_names_its_channel():
    from diffgyro.channel import resolve, split_spec
    from diffgyro.errors import SpecError

    assert split_spec("accel: bias_poly(3)") == ("accel", "bias_poly(3)")
    assert split_spec("bias_poly(3)+term(temp*az)") == (None, "bias_poly(3)+term(temp*az)")
    assert resolve("bias_poly(3)") == ("gyro", "bias_poly(3)")
    assert resolve("bias_poly(3)", "accel") == ("accel", "bias_poly(3)")
    assert resolve("gyro:bias_poly(1)", "gyro") == ("gyro", "bias_poly(1)")
    with pytest.raises(SpecError, match="unknown channel 'mag'"):
        resolve("bias_poly(1)", "mag")


def test_calibration_file_keeps_channel_reference_and_id(soak):
    from diffgyro.errors import SpecError

    accel = soak[5]
    doc = accel.to_json()
    assert doc["channel"] == "accel" and len(doc["devices"][0]["reference"]) == 3
    back = calibration.from_json(doc)
    assert back.channel == "accel" and back.devices[1].reference == accel.devices[1].reference
    assert "channel" not in soak[4].to_json()  # a gyro file reads as before
    with_id = dict(doc, devices=[dict(doc["devices"][0], device_id=ACCEL_IDS[0])])
    assert calibration.from_json(with_id).devices[0].device_id == ACCEL_IDS[0]
    for bad, what in ((dict(doc, channel="mag"), "channel must be one of"),
                      (dict(doc, devices=[dict(doc["devices"][0], device_id=-1)]), "device_id"),
                      (dict(doc, devices=[{k: v for k, v in doc["devices"][0].items()
                                           if k != "reference"}]), "needs each device's reference")):
        with pytest.raises(SpecError, match=what):
            calibration.from_json(bad)
    with pytest.raises(SpecError, match="compensation applies gyro calibrations"):
        calibration.compensate(accel, soak[0].select([0, 1]))


def test_ardupilot_shared_range_is_the_overlap_and_said(soak):
    """One INS_TCALn_TMIN/TMAX serves both sensors of IMU n: the overlap of their ranges."""
    gyro, accel = soak[4], soak[5]
    doc = accel.to_json()
    lo, hi = doc["devices"][0]["temp_range"]
    doc["devices"][0]["temp_range"] = [lo + 2.0, hi]
    narrowed = calibration.from_json(doc)
    two = calibration.from_json(gyro.to_json() | {"devices": gyro.to_json()["devices"][:2]})
    text, report = render(two, "ardupilot", accel=narrowed)
    p = _ardupilot_params(text)
    assert p["INS_TCAL1_TMIN"] == pytest.approx(lo + 2.0, abs=1e-4)
    assert any(line.startswith("INS_TCAL1 TMIN/TMAX") and "the gyro's" in line for line in report)
    assert not any(line.startswith("INS_TCAL2 TMIN/TMAX") for line in report)


def test_compensate_corrects_the_accelerometer_as_px4_does(soak, tmp_path, capsys):
    """``compensate`` with the accelerometer's calibration file (numpy only,
    apply.compensate_accel) removes the offset's change from the calibration's centre
    temperature: on the unseen soak it is PX4's TC_A correction (TREF the same centre),
    it leaves each cubic board at its noise, and the gyro columns are written as read."""
    from diffgyro import apply, io

    _, _, unseen, ut, gyro, accel = soak
    text, _ = render(gyro, "px4", device_ids=GYRO_IDS, accel=accel, accel_ids=ACCEL_IDS[:2])
    p = _px4_params(text)
    two = unseen.select([0, 1])
    io.save(two, tmp_path / "unseen.csv")
    calibration.save(accel, tmp_path / "accel.json")
    code = main(["compensate", str(tmp_path / "unseen.csv"), "--cal", str(tmp_path / "accel.json"),
                 "--out", str(tmp_path / "out.csv")])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "accelerometer samples corrected by bias_poly(3)" in out.out
    written = load_batch([tmp_path / "out.csv"])
    for i in range(2):
        raw_g, raw_a, temp, _, _, a_noise = _noise(unseen, ut, i)
        n = len(temp)
        got = np.asarray(written.accel[i, :n])
        doc = accel.to_json()
        np.testing.assert_allclose(got, apply.compensate_accel(
            doc, accel.devices[i].device, np.asarray(unseen.t[i, :n]), raw_a, temp), atol=1e-9)
        px4 = raw_a - _px4_offset(p, _slot(p, "A", ACCEL_IDS[i]), temp)
        assert np.abs(got - px4).max() < 1e-4, i  # float32 parameters
        assert _rms(got - got.mean(0)) <= 1.05 * _rms(a_noise - a_noise.mean(0)), i
        np.testing.assert_allclose(np.asarray(written.gyro[i, :n]), raw_g, atol=1e-9)


def test_compensate_refuses_a_device_the_accelerometer_file_lacks(soak, tmp_path, capsys):
    _, _, unseen, _, _, accel = soak
    from diffgyro import io

    io.save(unseen.select([2]), tmp_path / "board2.csv")
    calibration.save(accel, tmp_path / "accel.json")
    code = main(["compensate", str(tmp_path / "board2.csv"), "--cal", str(tmp_path / "accel.json"),
                 "--out", str(tmp_path / "out.csv")])
    err = capsys.readouterr().err
    assert code == 2 and unseen.devices[2] in err and "not in the calibration" in err


def test_limits_judge_the_accelerometer_in_its_units(soak, tmp_path, capsys):
    """``fit --channel accel --limits``: the records' numbers are the accelerometer's (m/s²),
    bounds may be written in mg or mg/K, a rate unit is refused naming its key; the
    temperature coefficient the limits compute is the true cubic's (per board), so a bound
    between the two boards passes one and fails the other."""
    from diffgyro import io

    batch, truth = soak[0], soak[1]
    io.save(batch.select([0, 1]), tmp_path / "soak.csv")
    slopes = []
    for board in (0, 1):
        temp = np.linspace(*np.percentile(batch.temp[board, :int(batch.n_valid[board])],
                                          [0, 100]), 2001)
        curve = _true_accel_cubic(truth, board, temp)
        slopes.append(np.abs(np.gradient(curve, temp, axis=0)).max() / 9.80665e-3)  # mg/K
    bound = float(np.mean(slopes))
    (tmp_path / "lim.toml").write_text(
        "[limits]\nstatus = \"ok\"\nheldout_rms = { max = 1, unit = \"mg\" }\n"
        f"\"bias_tempco.worst\" = {{ max = {bound!r}, unit = \"mg/K\" }}\n")
    code = main(["fit", str(tmp_path / "soak.csv"), "-m", MODEL, "--channel", "accel",
                 "--limits", str(tmp_path / "lim.toml"), "--json"])
    out = capsys.readouterr()
    assert code == 0, out.err
    doc = json.loads(out.out)
    assert sorted(r["limits"]["result"] for r in doc["devices"]) == ["fail", "pass"]
    for rec, slope in zip(doc["devices"], slopes, strict=True):
        got = rec["bias_tempco"]["worst"] / 9.80665e-3
        assert abs(got - slope) < 0.02 * slope, (got, slope)
        assert rec["limits"]["result"] == ("pass" if slope <= bound else "fail")
        assert rec["heldout_rms"] < 9.80665e-3  # the 1 mg bound, in m/s²
    (tmp_path / "rate.toml").write_text("[limits]\nheldout_rms = { max = 1, unit = \"deg/s\" }\n")
    code = main(["fit", str(tmp_path / "soak.csv"), "-m", MODEL, "--channel", "accel",
                 "--limits", str(tmp_path / "rate.toml")])
    err = capsys.readouterr().err
    assert code == 2 and "heldout_rms.unit" in err and "not the accelerometer's" in err
