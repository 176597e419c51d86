"""``diffgyro recipe NAME DATA``: the command line over every recipe."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from diffgyro.cli import main

DATA = Path(__file__).resolve().parents[1] / "data"
IMUCAL = DATA / "imucal"
COLS = "gx=gyr_x,gy=gyr_y,gz=gyr_z,ax=acc_x,ay=acc_y,az=acc_z"


def run(capsys, *argv):
    code = main(list(map(str, argv)))
    out = capsys.readouterr()
    return code, out.out, out.err


def test_six_position_json_contract_matches_imucal(capsys, tmp_path):
    imucal = pytest.importorskip("imucal")
    # the section file is found beside the data by default (DATA stem + "_list.json")
    for f in ("example_ferraris_session.csv", "example_ferraris_session_list.json"):
        shutil.copy(IMUCAL / f, tmp_path / f)
    code, out, err = run(capsys, "recipe", "six-position", tmp_path / "example_ferraris_session.csv",
                         "--columns", COLS, "--gyro-unit", "deg/s", "--sampling-rate", 102.4,
                         "--json")
    assert code == 0, err
    got = json.loads(out)
    assert list(got) == ["gyro_bias", "gyro_matrix", "g_sens", "accel_bias", "accel_matrix"]
    assert np.shape(got["gyro_bias"]) == (3,) and np.shape(got["gyro_matrix"]) == (3, 3)
    df = pd.read_csv(IMUCAL / "example_ferraris_session.csv", header=0, index_col=0)
    sl = pd.read_json(IMUCAL / "example_ferraris_session_list.json").T
    cal = imucal.FerrarisCalibration().compute(
        imucal.ferraris_regions_from_section_list(df, sl), 102.4, "m/s^2", "deg/s")
    # in the input units: deg/s and m/s²
    np.testing.assert_allclose(got["gyro_bias"], cal.b_g, atol=0.01)
    np.testing.assert_allclose(got["gyro_matrix"], np.linalg.inv(cal.R_g) @ np.linalg.inv(cal.K_g),
                               atol=1e-2)
    np.testing.assert_allclose(got["g_sens"], cal.K_ga, atol=1e-2)
    np.testing.assert_allclose(got["accel_bias"], cal.b_a, atol=0.02)
    np.testing.assert_allclose(got["accel_matrix"], np.linalg.inv(cal.R_a) @ np.linalg.inv(cal.K_a),
                               atol=1e-2)


def test_six_position_output_follows_the_input_unit(capsys):
    base = ["recipe", "six-position", IMUCAL / "example_ferraris_session.csv", "--columns", COLS,
            "--sampling-rate", 102.4, "--sections", IMUCAL / "example_ferraris_session_list.json",
            "--json"]
    code, out_deg, err = run(capsys, *base, "--gyro-unit", "deg/s")
    assert code == 0, err
    # the same numbers read as rad/s, with the turn given as −360 "rad" (−360·180/π degrees),
    # give the same numbers: the output is always in the input unit
    code, out_rad, err = run(capsys, *base, "--rotation-angle", -360.0 * 180.0 / np.pi,
                             "--gyro-unit", "rad/s")  # the option that keeps implausible rad/s
    assert code == 0, err
    deg, rad = json.loads(out_deg), json.loads(out_rad)
    np.testing.assert_allclose(deg["gyro_bias"], rad["gyro_bias"], rtol=1e-9)
    np.testing.assert_allclose(deg["gyro_matrix"], rad["gyro_matrix"], rtol=1e-9)
    np.testing.assert_allclose(deg["g_sens"], rad["g_sens"], rtol=1e-9)


def test_options_and_errors(capsys, tmp_path):
    csv = IMUCAL / "example_ferraris_session.csv"
    code, _, err = run(capsys, "recipe", "six-position", csv, "--bin-width", 0.2)
    assert code == 2 and "--bin-width does not apply" in err and "Traceback" not in err
    code, _, err = run(capsys, "recipe", "magic", csv)
    assert code == 2 and "unknown recipe" in err and "six-position" in err
    lonely = tmp_path / "lonely.csv"
    shutil.copy(csv, lonely)
    code, _, err = run(capsys, "recipe", "six-position", lonely, "--columns", COLS,
                       "--sampling-rate", 102.4)
    assert code == 2 and "--sections" in err
    code, _, err = run(capsys, "recipe", "binned-thermal", csv, "--columns", COLS,
                       "--sampling-rate", 102.4, "--gyro-unit", "deg/s")
    assert code == 2 and "temp" in err
    # the same file read as rad/s (no --gyro-unit) is refused, naming the option that passes
    code, _, err = run(capsys, "recipe", "binned-thermal", csv, "--columns", COLS,
                       "--sampling-rate", 102.4)
    assert code == 2 and "not plausible in rad/s" in err and "--gyro-unit deg/s" in err


def test_binned_thermal_and_static_kalman_from_files(capsys, tmp_path):
    rng = np.random.default_rng(0)
    t = np.arange(0, 3600.0, 0.5)
    temp = 20 + 15 * (1 - np.exp(-t / 900))
    g = np.stack([0.01 + 1e-3 * temp, -0.02 + 5e-4 * temp, 0.003 - 8e-4 * temp], 1)
    g = g + 2e-4 * rng.normal(size=g.shape)
    a = np.tile([0, 0, 9.81], (t.size, 1)) + 0.01 * rng.normal(size=g.shape)
    df = pd.DataFrame({"t": t, "gx": g[:, 0], "gy": g[:, 1], "gz": g[:, 2], "temp": temp,
                       "ax": a[:, 0], "ay": a[:, 1], "az": a[:, 2]})
    path = tmp_path / "warm.csv"
    df.to_csv(path, index=False)
    code, out, err = run(capsys, "recipe", "binned-thermal", path, "--edge", "centre", "--json")
    assert code == 0, err
    res = json.loads(out)
    np.testing.assert_allclose(res["slope"], [1e-3, 5e-4, -8e-4], rtol=0.05)
    assert res["accepted"] == [True, True, True]
    code, out, err = run(capsys, "recipe", "static-kalman", path, "--window", 50, "--json")
    assert code == 0, err
    res = json.loads(out)
    assert res["n_static_windows"] > 0 and len(res["offset_track"][0]) == 3
    code, out, err = run(capsys, "recipe", "binned-thermal", path)   # human-readable
    assert code == 0 and "slope" in out and "binned-thermal" in out


def test_multi_position_on_the_imutk_files(capsys, tmp_path):
    acc = np.loadtxt(DATA / "imu_tk" / "xsens_acc.mat")
    gyr = np.loadtxt(DATA / "imu_tk" / "xsens_gyro.mat")
    df = pd.DataFrame({"t": acc[:, 0], "ax": acc[:, 1], "ay": acc[:, 2], "az": acc[:, 3],
                       "gx": gyr[:, 1], "gy": gyr[:, 2], "gz": gyr[:, 3]})
    path = tmp_path / "xsens.csv"
    df.to_csv(path, index=False)
    code, out, err = run(capsys, "recipe", "multi-position", path, "--gravity", 9.81744, "--json")
    assert code == 0, err
    res = json.loads(out)
    ref = json.loads((DATA / "imu_tk" / "imutk_reference.json").read_text())  # IMU-TK's output
    assert len(res["intervals"]) == ref["accelerometer"]["static_intervals"]
    assert max(abs(x) for x in res["pose_norm_error"]) < 5e-4 * 9.81744
    np.testing.assert_allclose(res["gyro_scale_counts"], 1.0 / np.asarray(ref["gyroscope"]["K"]),
                               rtol=5e-4)


def test_cube_bias_fog_and_attitude_from_simulated_files(capsys, tmp_path):
    from diffgyro.io import save
    from diffgyro.simulate import simulate

    batch, truth = simulate("six_face", 1, seed=1, turns=False, noise="none")
    save(batch.recording(0), tmp_path / "cube.csv")
    sets = {f"{s['face'][1]}_{'up' if s['face'][0] == '+' else 'down'}_{s['index'] + 1}":
            {"start": s["start"], "end": s["end"]} for s in truth.segments if s["label"] == "face"}
    (tmp_path / "cube_list.json").write_text(json.dumps(sets))
    code, out, err = run(capsys, "recipe", "cube-bias", tmp_path / "cube.csv", "--json")
    assert code == 0, err
    np.testing.assert_allclose(json.loads(out)["gyro_bias"], np.asarray(truth.params.beta)[0, :, 0],
                               atol=1e-9)
    code, out, err = run(capsys, "recipe", "cube-bias", tmp_path / "cube.csv")
    assert code == 0 and "pairs_used: {x: [z], y: [z], z: [y]}" in out

    batch, _ = simulate("s2", 1, seed=1)
    save(batch.recording(0), tmp_path / "s2.csv")
    code, out, err = run(capsys, "recipe", "fog-one-run", tmp_path / "s2.csv", "--m", 3, "--json")
    assert code == 0, err
    res = json.loads(out)
    assert res["columns"] == ["D", "T*D", "T^2*D", "T", "T-T_out", "dT"]
    assert abs(res["coefficients"][0] - 1.0) < 1e-3

    batch, _ = simulate("attitude", 1, seed=1, duration=60.0, accel_share=0.0)
    save(batch.recording(0), tmp_path / "att.csv")
    code, out, err = run(capsys, "recipe", "attitude-reference", tmp_path / "att.csv",
                         "--interval", 10, "--json")
    assert code == 0, err
    res = json.loads(out)
    assert set(res) >= {"scale", "bias", "joint_scale", "joint_bias", "n_gated"}
    code, _, err = run(capsys, "recipe", "attitude-reference", tmp_path / "s2.csv")
    assert code == 2 and "mx, my, mz" in err
