"""The accelerometer in several orientations: a thermal soak held on the six faces gives the
absolute offset, its thermal change and the scale (and misalignment) through the same fit
and spec grammar (``bias_poly(3)+scale_poly(0)+misalignment`` on ``channel="accel"``);
at one temperature it is the six-position recipe's accelerometer calibration. Truth from
simulated devices with known coefficients, and imucal's real Ferraris session.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import DATA

from diffgyro import apply, calibration
from diffgyro.channel import faces
from diffgyro.diagnose import diagnose
from diffgyro.errors import DataError
from diffgyro.fit import fit
from diffgyro.io import load_batch, parse_columns
from diffgyro.recipes._six_position import six_position
from diffgyro.simulate import simulate
from diffgyro.simulate._motion import G0

ORIENTED = "bias_poly(3)+scale_poly(0)+misalignment"
SIX_FACES = "+x,-x,+y,-y,+z,-z"
_OTHERS = ((1, 2), (0, 2), (0, 1))


def _truth_beta(truth, i: int) -> np.ndarray:
    """Device i's true coefficients in the fit's order: the absolute offset (the bias plus
    the thermal constant), the thermal change c1..c3, the scale and the misalignment."""
    k = truth.accel["error_matrix"][i]
    thermal = truth.accel["thermal_beta"][i]
    mis = np.stack([k[a, list(o)] for a, o in enumerate(_OTHERS)])
    return np.concatenate([(truth.accel["bias"][i] + thermal[:, 0])[:, None], thermal[:, 1:],
                           np.diag(k)[:, None], mis], axis=1)


def _matrix(beta: np.ndarray) -> np.ndarray:
    """``I + S + M`` from one device's scale_poly(0) and misalignment columns (after the bias
    columns ``p``)."""
    p = beta.shape[1] - 3
    out = np.eye(3) + np.diag(beta[:, p])
    for a, o in enumerate(_OTHERS):
        out[a, o[0]], out[a, o[1]] = beta[a, p + 1], beta[a, p + 2]
    return out


@pytest.fixture(scope="module")
def faces_soak():
    """Two accelerometers with bias, scale, misalignment and a cubic thermal offset through a
    two-hour soak whose every level is held on the six faces, and their fit."""
    batch, truth = simulate("thermal", 2, effects="bias_poly(3)", seed=3, accel_errors=True,
                            accel_effects="bias_poly(3)", faces=SIX_FACES, sample_rate=2.0,
                            duration=7200.0, keep_components=True)
    result = fit(ORIENTED, batch, norm=truth.norm, channel="accel")
    return batch, truth, result


def test_six_faces_give_absolute_offset_thermal_change_and_scale(faces_soak):
    batch, truth, result = faces_soak
    assert [result.status_detail(i) for i in range(2)] == ["ok", "ok"]
    assert result.static_only and np.all(np.asarray(result.reference) == 0.0)
    for i in range(2):
        beta = np.asarray(result.params.beta[i])
        sd = np.asarray(result.stderr(i).beta)
        assert np.all(np.abs(beta - _truth_beta(truth, i)) < 4.5 * sd), i
        # sharp enough to mean something: scale to 2 % of its spread, offset to 0.1 mg
        assert sd[:, 4:].max() < 2e-5 and sd[:, 0].max() < 1e-3, i
    # the moves between faces are left out, the rest is fitted
    n, kept = np.asarray(result.n_recorded), np.asarray(result.n_samples)
    assert np.all((kept > 0.8 * n) & (kept < n))


def test_six_faces_fitted_as_one_orientation_are_in_motion_with_the_remedy(faces_soak):
    batch, _, _ = faces_soak
    result = fit("bias_poly(3)", batch, channel="accel")
    for i in range(2):
        detail = result.status_detail(i)
        assert detail.startswith("in_motion") and "gravity tilted" in detail, detail
        assert "scale_poly(0)" in detail


def test_scale_from_one_face_is_refused_naming_the_device():
    batch, _ = simulate("thermal", 1, effects="bias_poly(0)", seed=5, sample_rate=2.0,
                        duration=1800.0)
    with pytest.raises(DataError, match=r"several orientations.*one face \(\+z\)") as err:
        fit(ORIENTED, batch, channel="accel")
    assert err.value.device == batch.devices[0]


def _holds(*directions, n=200, noise=1e-3, seed=0):
    """Static stretches of ``n`` samples, one per gravity direction, and their rest mask
    (a gap of 10 moving samples between stretches)."""
    rng = np.random.default_rng(seed)
    parts, still = [], []
    for k, d in enumerate(directions):
        d = np.asarray(d, float) / np.linalg.norm(d)
        if k:
            parts.append(np.tile(d * G0, (10, 1)))
            still.append(np.zeros(10, bool))
        parts.append(d * G0 + noise * rng.standard_normal((n, 3)))
        still.append(np.ones(n, bool))
    return np.concatenate(parts), np.concatenate(still)


def test_faces_are_read_from_the_rest():
    acc, still = _holds([0, 0, 1], [0.05, 0, -1], [1, 0.1, 0])
    nominal, seen = faces(acc, still, G0)
    assert seen == ["+z", "-z", "+x"]
    assert np.all(nominal[~still] == 0.0)
    np.testing.assert_array_equal(nominal[:200], np.tile([0, 0, G0], (200, 1)))
    np.testing.assert_array_equal(nominal[-200:], np.tile([G0, 0, 0], (200, 1)))


def test_a_rest_between_faces_is_refused_with_its_rows():
    acc, still = _holds([0, 0, 1], [1, 0, 1])  # 45° from x and z
    with pytest.raises(DataError, match="rows 210–409 holds gravity 45° from every axis") as err:
        faces(acc, still, G0, device="imu0")
    assert err.value.device == "imu0" and err.value.row == 210


def test_a_turn_inside_a_rest_is_refused_with_its_row():
    acc, still = _holds([0, 0, 1])
    acc[150:] = [G0, 0, 0]  # turned to +x with no move the check saw
    with pytest.raises(DataError, match="row 150 leaves face \\+z"):
        faces(acc, still, G0)


def test_one_temperature_is_the_six_position_recipe():
    """The six faces at one temperature (imucal's sections, no table tilt): the fit's
    offset and ``(I + S + M)⁻¹`` are the recipe's ``accel_bias`` and ``accel_matrix``, both
    within their noise of the truth (the fit reads every heading of every face, the recipe
    the first)."""
    batch, truth = simulate("six_face", 1, seed=0, latitude=45.0, tilt=0.0, dwell=10.0)
    rec = batch.recording(0)
    recipe = six_position(rec.gyro, rec.accel, truth.info["sections"], t=rec.t,
                          rotation_angle=-2 * math.pi, gravity=G0)
    result = fit("bias_poly(0)+scale_poly(0)+misalignment", batch, channel="accel",
                 gravity=G0)
    assert result.status_detail(0) == "ok"
    beta, sd = np.asarray(result.params.beta[0]), np.asarray(result.stderr(0).beta)
    assert np.all(np.abs(beta[:, 0] - truth.accel["bias"][0]) < 4.5 * sd[:, 0])
    matrix = np.linalg.inv(_matrix(beta))
    np.testing.assert_allclose(matrix, truth.accel["matrix"][0], atol=1e-4)
    np.testing.assert_allclose(recipe.accel_bias, beta[:, 0], atol=1e-3)
    np.testing.assert_allclose(recipe.accel_matrix, matrix, atol=2e-4)


def test_real_ferraris_session_agrees_with_the_recipe(tmp_path, capsys):
    """imucal's real six-position session (hand-held faces, 102.4 Hz) through the command
    line: the fit over every rest agrees with the recipe over its sections to 0.02 m/s² and
    2e-3 (the faces are not held exactly level, which each method weighs differently)."""
    from diffgyro.cli import main

    path = DATA / "imucal" / "example_ferraris_session.csv"
    cols = "gx=gyr_x,gy=gyr_y,gz=gyr_z,ax=acc_x,ay=acc_y,az=acc_z"
    batch = load_batch([path], parse_columns(cols), {"gyro": "deg/s"}, sampling_rate=102.4)
    sections = {k: (v["start"], v["end"]) for k, v in
                json.loads(path.with_name(path.stem + "_list.json").read_text()).items()}
    rec = batch.recording(0)
    recipe = six_position(rec.gyro, rec.accel, sections, t=rec.t, rotation_angle=-2 * math.pi,
                          gravity=9.81)
    assert main(["fit", str(path), "--columns", cols, "--gyro-unit", "deg/s", "--sampling-rate",
                 "102.4", "-m", "accel: bias_poly(0)+scale_poly(0)+misalignment",
                 "--gravity", "9.81", "--out", str(tmp_path / "cal.json")]) == 0
    assert "accelerometer on its faces" in capsys.readouterr().out
    cal = calibration.load(tmp_path / "cal.json")
    assert cal.channel == "accel" and cal.devices[0].status == "ok" and cal.gravity == 9.81
    beta = np.asarray(cal.devices[0].beta, float)
    np.testing.assert_allclose(beta[:, 0], recipe.accel_bias, atol=0.02)
    np.testing.assert_allclose(np.linalg.inv(_matrix(beta)), recipe.accel_matrix, atol=2e-3)


def test_compensation_of_several_orientations_leaves_the_noise(faces_soak):
    """apply.compensate_accel (numpy only) with the fit's calibration file turns each rest's
    reading into the true specific force, to the noise the simulator added; before, the
    offset, its thermal change and the scale stood well above it."""
    batch, truth, result = faces_soak
    doc = calibration.from_fit(result, batch).to_json()
    assert doc["gravity"] == G0 and calibration.from_json(doc).gravity == G0
    with pytest.raises(Exception, match="gravity must be"):
        calibration.from_json(doc | {"gravity": -1.0})
    for i in range(2):
        n = int(batch.n_valid[i])
        still = np.asarray(result.motion.static[i, :n])
        raw = np.asarray(batch.accel[i, :n])
        force = truth.env["specific_force"][i]
        clean = force @ (np.eye(3) + truth.accel["error_matrix"][i]).T
        noise = raw - clean - truth.accel["bias"][i] - truth.env["accel_thermal"][i]
        got = apply.compensate_accel(doc, batch.devices[i], np.asarray(batch.t[i, :n]), raw,
                                     np.asarray(batch.temp[i, :n]))
        rms = float(np.sqrt(np.mean((got - force)[still] ** 2)))
        floor = float(np.sqrt(np.mean(noise[still] ** 2)))
        assert rms <= 1.05 * floor, (i, rms, floor)
        assert float(np.sqrt(np.mean((raw - force)[still] ** 2))) > 20 * floor


def test_diagnose_names_the_missing_order_on_the_faces(faces_soak):
    """The discovery loop runs on several orientations too: scored on the rests with gravity
    their input, a linear thermal offset where the truth is cubic is found short, and the
    next order named."""
    batch, _, _ = faces_soak
    diag = diagnose("bias_poly(1)+scale_poly(0)+misalignment", batch, channel="accel",
                    candidates=["bias_poly"], synthesis=False, noise=False, greedy=False)
    for d in diag.devices:
        assert d.verdict == "missing_effect", d.device
        assert d.candidates[0].spec == "bias_poly(2)+scale_poly(0)+misalignment"
        assert d.candidates[0].significant


def test_command_line_takes_gravity_and_refuses_what_it_cannot_stream(tmp_path, capsys):
    from diffgyro.cli import main

    csv = DATA / "imucal" / "example_ferraris_session.csv"
    assert main(["fit", str(csv), "-m", "bias_poly(0)", "--gravity", "9.81"]) == 2
    assert "--gravity" in capsys.readouterr().err
    (tmp_path / "parts").mkdir()
    assert main(["fit", str(tmp_path / "parts"), "-m", "accel: bias_poly(3)"]) == 2
    err = capsys.readouterr().err
    assert "streamed runs" in err and "carries no gravity reference" in err


def test_simulated_accelerometer_thermal_offset_is_bias_terms_only():
    from diffgyro.errors import SpecError

    with pytest.raises(SpecError, match="thermal offset is bias terms only"):
        simulate("thermal", 1, accel_effects="bias_poly(1)+scale_poly(0)", sample_rate=1.0,
                 duration=600.0)


def test_faces_that_leave_an_axis_level_say_what_the_scale_needs():
    """+z, +x and −x: gravity never lies along y, so y's scale is not determined; the device
    is insufficient_range, naming the terms and the faces they need."""
    batch, _ = simulate("thermal", 1, effects="bias_poly(0)", seed=3, accel_errors=True,
                        accel_effects="bias_poly(3)", faces="+z,+x,-x", sample_rate=1.0,
                        duration=3600.0)
    detail = fit(ORIENTED, batch, channel="accel").status_detail(0)
    assert detail.startswith("insufficient_range: scale_poly(0) needs gravity along every axis")
    assert "misalignment needs" in detail and "each axis up, and down" in detail
