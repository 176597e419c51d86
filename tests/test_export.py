"""diffgyro export: autopilot parameters applied with the autopilots' own documented
formulas (written here from PX4's and ArduPilot's docs and source, not from diffgyro)
leave unseen data of the same device at its noise; Kalibr's imu.yaml carries known
noise densities; the C header compiles and agrees with apply.py."""

from __future__ import annotations

import json
import math
import shutil
import subprocess

import numpy as np
import pytest

from diffgyro import apply as ref_apply
from diffgyro import calibration
from diffgyro.cli import main
from diffgyro.export import render
from diffgyro.fit import fit
from diffgyro.simulate import simulate

MODEL = "bias_poly(3)"
#: A second chamber run within the first one's range: other ramps, other seed.
UNSEEN = {"start_temp": 20.0, "profile": ((45.0, 1.5, 15.0), (0.0, 1.0, 15.0), (30.0, 0.5, 10.0))}


@pytest.fixture(scope="module")
def device():
    """A bias_poly(3) MEMS gyro: calibration run, its fit, and an unseen run of the same device."""
    batch, truth = simulate("thermal", 1, effects=MODEL, seed=11)
    cal = calibration.from_fit(fit(MODEL, batch), batch)
    unseen, unseen_truth = simulate("thermal", 1, effects=MODEL, seed=12, params=truth.params,
                                    temp_norm=truth.norm, keep_components=True, **UNSEEN)
    return cal, unseen, unseen_truth


def _unseen_arrays(unseen, unseen_truth):
    n = int(unseen.n_valid[0])
    gyro = np.asarray(unseen.gyro[0, :n], float)
    temp = np.asarray(unseen.temp[0, :n], float)
    rate = unseen_truth.env["rate"][0]
    noise = gyro - rate - unseen_truth.env["error"][0]
    return gyro, temp, rate, noise


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def _px4_parse(text: str) -> dict[str, float]:
    """QGroundControl's parameter file: '#' comments, then vehicle, component, name, value, type."""
    out = {}
    for line in text.splitlines():
        if line.startswith("#") or not line.strip():
            continue
        vehicle, component, name, value, typ = line.split("\t")
        assert (vehicle, component) == ("1", "1") and typ in ("6", "9")
        out[name] = int(value) if typ == "6" else float(np.float32(value))
    return out


def _px4_correct(p: dict, n: int, gyro, temp):
    """PX4 user guide, sensor_thermal_calibration.md, and TemperatureCompensation.cpp:
    delta = clip(T, TMIN, TMAX) - TREF; offset = X0 + X1·delta + X2·delta² + X3·delta³;
    corrected = raw - offset (float arithmetic)."""
    f = np.float32
    t = np.clip(temp.astype(f), f(p[f"TC_G{n}_TMIN"]), f(p[f"TC_G{n}_TMAX"]))
    d = t - f(p[f"TC_G{n}_TREF"])
    offset = np.stack([sum(f(p[f"TC_G{n}_X{k}_{i}"]) * d**k for k in range(4)) for i in range(3)], -1)
    return gyro - offset


def _ardupilot_parse(text: str) -> dict[str, float]:
    out = {}
    for line in text.splitlines():
        line = line.split("#")[0].strip()
        if line:
            name, value = line.replace(",", " ").split()
            out[name] = float(np.float32(value))
    return out


def _ardupilot_correct(p: dict, n: int, gyro, temp):
    """AP_InertialSensor_tempcal.cpp TCal::correct_sensor and _rotate_and_correct_gyro:
    P(d) = (c1 + (c2 + c3·d)·d)·d·1e-6 per axis, T and CALTEMP constrained to [TMIN, TMAX],
    v -= P(T - 35); v += P(CALTEMP - 35); then v -= INS_GYROFFS."""
    lo, hi = p[f"INS_TCAL{n}_TMIN"], p[f"INS_TCAL{n}_TMAX"]
    t = np.clip(temp, lo, hi)
    tcal = np.clip(p[f"INS_GYR{n}_CALTEMP"], lo, hi)
    offs = "INS_GYROFFS" if n == 1 else f"INS_GYR{n}OFFS"
    out = np.array(gyro, float)
    for i, ax in enumerate("XYZ"):
        c1, c2, c3 = (p[f"INS_TCAL{n}_GYR{k}_{ax}"] for k in (1, 2, 3))

        def poly(d, c1=c1, c2=c2, c3=c3):
            return (c1 + (c2 + c3 * d) * d) * d * 1e-6

        out[:, i] = out[:, i] - poly(t - 35.0) + poly(tcal - 35.0) - p[f"{offs}_{ax}"]
    return out


def test_px4_parameters_leave_unseen_data_at_the_noise(device):
    cal, unseen, truth = device
    text, report = render(cal, "px4", device_ids=[2293768])
    p = _px4_parse(text)
    assert p["TC_G_ENABLE"] == 1 and p["TC_G0_ID"] == 2293768
    assert "float32" in report[-1]
    gyro, temp, rate, noise = _unseen_arrays(unseen, truth)
    assert temp.min() > p["TC_G0_TMIN"] and temp.max() < p["TC_G0_TMAX"]  # unseen, within range
    raw_rms = _rms(gyro - rate)
    residual = _rms(_px4_correct(p, 0, gyro, temp) - rate)
    assert residual <= 1.05 * _rms(noise), (residual, _rms(noise))
    assert raw_rms > 5 * _rms(noise)  # the thermal bias was there to remove


def test_ardupilot_parameters_leave_unseen_data_at_the_noise(device, tmp_path):
    cal, unseen, truth = device
    text, _ = render(cal, "ardupilot", instance=2)
    p = _ardupilot_parse(text)
    assert p["INS_TCAL2_ENABLE"] == 1
    gyro, temp, rate, noise = _unseen_arrays(unseen, truth)
    residual = _rms(_ardupilot_correct(p, 2, gyro, temp) - rate)
    assert residual <= 1.05 * _rms(noise), (residual, _rms(noise))
    mavparm = pytest.importorskip("pymavlink.mavparm")
    path = tmp_path / "tcal.param"
    path.write_text(text)
    loaded = mavparm.MAVParmDict()
    loaded.load(str(path))   # MAVProxy's own reader takes every line
    assert set(loaded) == set(p)


def test_float32_error_is_far_below_the_noise(device):
    cal = device[0]
    for fmt in ("px4", "ardupilot"):
        _, report = render(cal, fmt, device_ids=[1] if fmt == "px4" else None)
        ratio = float(report[-1].split(", ")[-1].split(" × ")[0])
        assert ratio < 1e-3, report


def _write_cal(tmp_path, model: str, p: int, q: int = 0):
    dev = {"device": "imu0", "status": "ok", "beta": [[1e-3] * p] * 3, "theta": [math.log(300.0)] * q,
           "temp_centre": 25.0, "temp_scale": 30.0, "temp_range": [-5.0, 55.0]}
    doc = {"format": "diffgyro-calibration", "format_version": 1, "model": model,
           "dtemp_window": 60.0, "devices": [dev]}
    path = tmp_path / "cal.json"
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("model,p,q,fmt,term", [
    ("bias_poly(2)+thermal_lag", 4, 1, "px4", "thermal_lag"),
    ("bias_poly(4)", 5, 0, "ardupilot", "bias_poly(4)"),
    ("bias_poly(1)+warmup", 3, 1, "c-header", "warmup"),
])
def test_a_model_the_format_cannot_hold_is_refused(tmp_path, capsys, model, p, q, fmt, term):
    path = _write_cal(tmp_path, model, p, q)
    out = tmp_path / "out.txt"
    assert main(["export", str(path), "--format", fmt, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and term in err[0] and fmt in err[0] and "Traceback" not in err[0]
    assert not out.exists()


def test_export_writes_the_file_or_stdout(tmp_path, capsys):
    path = _write_cal(tmp_path, "bias_poly(1)", 2)
    out = tmp_path / "params" / "tc.params"
    assert main(["export", str(path), "--format", "px4", "--out", str(out),
                 "--device-id", "0x230008", "--instance", "1"]) == 0
    p = _px4_parse(out.read_text())
    assert p["TC_G1_ID"] == 0x230008 and p["TC_G1_TREF"] == 25.0
    # bias_poly(1) about the centre: X0 = c0, X1 = c1 / scale, X2 = X3 = 0
    assert p["TC_G1_X0_0"] == pytest.approx(1e-3) and p["TC_G1_X1_2"] == pytest.approx(1e-3 / 30)
    assert p["TC_G1_X2_1"] == 0.0 and p["TC_G1_X3_1"] == 0.0
    capsys.readouterr()
    assert main(["export", str(path), "--format", "ardupilot"]) == 0
    assert "INS_TCAL1_GYR1_X," in capsys.readouterr().out
    assert main(["export", str(path), "--format", "px4", "--instance", "4"]) == 2
    assert "0..3" in capsys.readouterr().err


# ----------------------------------------------------------------------------- kalibr

ARW, RRW, ACC_ND = 1e-3, 1e-4, 2e-3


@pytest.fixture(scope="module")
def static_csv(tmp_path_factory):
    from diffgyro import io

    batch, _ = simulate("static", 1, effects="bias_poly(0)", seed=5, sample_rate=20.0,
                        duration=3 * 3600.0, noise={"arw": ARW, "rrw": RRW, "bias_instability": 0.0,
                                                    "quantum": 0.0, "accel_noise": ACC_ND})
    path = tmp_path_factory.mktemp("kalibr") / "static.csv"
    io.save(batch, path)
    return path


def test_kalibr_yaml_carries_the_known_noise(static_csv, tmp_path, capsys):
    yaml = pytest.importorskip("yaml")
    out = tmp_path / "imu.yaml"
    code = main(["export", str(static_csv), "--format", "kalibr", "--out", str(out),
                 "--accel-random-walk", "3e-4", "--topic", "/imu/data"])
    err = capsys.readouterr().err
    assert code == 0, err
    doc = yaml.safe_load(out.read_text())
    assert doc["rostopic"] == "/imu/data" and doc["update_rate"] == pytest.approx(20.0)
    assert doc["gyroscope_noise_density"] == pytest.approx(ARW, rel=0.05)
    assert doc["gyroscope_random_walk"] == pytest.approx(RRW, rel=0.3)
    assert doc["accelerometer_noise_density"] == pytest.approx(ACC_ND, rel=0.05)
    assert doc["accelerometer_random_walk"] == 3e-4   # given: the simulated accelerometer has none
    assert "accelerometer random walk" in err          # and the export said so


def test_kalibr_from_allan_json_needs_the_accelerometer(static_csv, tmp_path, capsys):
    assert main(["allan", str(static_csv), "--json"]) == 0
    allan_json = tmp_path / "allan.json"
    allan_json.write_text(capsys.readouterr().out)
    assert main(["export", str(allan_json), "--format", "kalibr"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "accelerometer_noise_density" in err[0]
    assert main(["export", str(allan_json), "--format", "kalibr", "--accel-noise-density", "2e-3",
                 "--accel-random-walk", "3e-4"]) == 0
    doc = pytest.importorskip("yaml").safe_load(capsys.readouterr().out)
    assert doc["gyroscope_noise_density"] == pytest.approx(ARW, rel=0.05)
    assert doc["accelerometer_noise_density"] == 2e-3


# ----------------------------------------------------------------------------- C header

C_MAIN = r"""
#include <stdio.h>
#include "cal.h"
int main(void) {
    double temp, temp_ext, a[3], g[3], w[3];
    while (scanf("%lf %lf %lf %lf %lf %lf %lf %lf", &temp, &temp_ext, &a[0], &a[1], &a[2],
                 &g[0], &g[1], &g[2]) == 8) {
        COMPENSATE;
        printf("%.17g %.17g %.17g\n", w[0], w[1], w[2]);
    }
    return 0;
}
"""


@pytest.mark.parametrize("model,call", [
    ("bias_poly(3)", "diffgyro_imu0_compensate(temp, g, w)"),
    ("bias_poly(2)+scale_poly(1)+misalignment+g_sens+temp_diff",
     "diffgyro_imu0_compensate(temp, temp_ext, a, g, w)"),
])
def test_c_header_compiles_and_agrees_with_apply(tmp_path, model, call):
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler (cc or gcc) on PATH to compile the header")
    from diffgyro.model import ErrorModel

    rng = np.random.default_rng(3)
    p = ErrorModel.from_spec(model).n_params
    dev = {"device": "imu0", "status": "ok", "beta": (rng.normal(size=(3, p)) * 1e-3).tolist(),
           "theta": [], "temp_centre": 24.0, "temp_scale": 31.0, "temp_range": [-8.0, 56.0]}
    doc = {"format": "diffgyro-calibration", "format_version": 1, "model": model,
           "dtemp_window": 60.0, "devices": [dev]}
    cal = calibration.from_json(doc)
    text, _ = render(cal, "c-header")
    (tmp_path / "cal.h").write_text(text)
    (tmp_path / "main.c").write_text(C_MAIN.replace("COMPENSATE", call))
    exe = tmp_path / "check"
    subprocess.run([cc, "-std=c99", "-Wall", "-Werror", "-O2", "-o", str(exe),
                    str(tmp_path / "main.c")], check=True, cwd=tmp_path)
    n = 500
    temp = rng.uniform(-20.0, 70.0, n)       # beyond the range on both sides: clamped
    temp_ext = temp - rng.uniform(0.0, 8.0, n)
    accel = rng.normal(size=(n, 3)) * 9.81
    gyro = rng.normal(size=(n, 3))
    rows = np.column_stack([temp, temp_ext, accel, gyro])
    res = subprocess.run([str(exe)], input="\n".join(" ".join(repr(float(x)) for x in r)
                                                     for r in rows) + "\n",
                         capture_output=True, text=True, check=True)
    omega_c = np.array([[float(x) for x in line.split()] for line in res.stdout.splitlines()])
    omega_ref = ref_apply.compensate(doc, "imu0", np.arange(n, dtype=float), gyro, temp=temp,
                                     temp_ext=temp_ext, accel=accel)
    assert omega_c.shape == (n, 3)
    np.testing.assert_allclose(omega_c, omega_ref, rtol=0, atol=1e-12)


def test_several_devices_take_consecutive_slots(tmp_path, capsys):
    path = _write_cal(tmp_path, "bias_poly(1)", 2)
    doc = json.loads(path.read_text())
    doc["devices"].append({**doc["devices"][0], "device": "imu1", "temp_range": [0.0, 40.0]})
    path.write_text(json.dumps(doc))
    assert main(["export", str(path), "--format", "px4", "--device-id", "11,12"]) == 0
    p = _px4_parse(capsys.readouterr().out)
    assert (p["TC_G0_ID"], p["TC_G1_ID"], p["TC_G1_TREF"]) == (11, 12, 20.0)
    assert main(["export", str(path), "--format", "px4", "--device-id", "11"]) == 2
    assert "1 id(s) for 2 device(s)" in capsys.readouterr().err
    assert main(["export", str(path), "--format", "ardupilot", "--device", "imu1",
                 "--instance", "3"]) == 0
    assert "INS_GYR3OFFS_Z," in capsys.readouterr().out
    assert main(["export", str(path), "--format", "c-header"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--device" in err and "imu0, imu1" in err and len(err.splitlines()) == 1
