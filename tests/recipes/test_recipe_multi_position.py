"""multi-position (IMU-TK's method): known truth, and IMU-TK's own Xsens example data."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from diffgyro.errors import DataError
from diffgyro.recipes import multi_position

DATA = Path(__file__).resolve().parents[1] / "data" / "imu_tk"


def _rot(q, v):
    """Rotate body vectors into the navigation frame (q: w, x, y, z)."""
    w, x, y, z = q
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    return v @ r  # = (R^T v^T)^T: navigation vector seen in the body frame


def _qmul(p, q):
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array([pw * qw - px * qx - py * qy - pz * qz, pw * qx + px * qw + py * qz - pz * qy,
                     pw * qy - px * qz + py * qw + pz * qx, pw * qz + px * qy - py * qx + pz * qw])


def simulate_poses(truth, n_poses=24, fs=100.0, rest=12.0, hold=3.0, move=1.5, seed=0,
                   acc_noise=0.01, gyro_noise=0.002):
    """A rest, then poses joined by turns about fixed body axes (exact orientations)."""
    rng = np.random.default_rng(seed)
    g_nav = np.array([0.0, 0.0, 9.81])
    q = np.array([1.0, 0.0, 0.0, 0.0])
    f, w = [], []
    m_rest, m_hold, m_move = int(rest * fs), int(hold * fs), int(move * fs)
    f.append(np.tile(_rot(q, g_nav), (m_rest, 1)))
    w.append(np.zeros((m_rest, 3)))
    s = (np.arange(m_move) + 0.5) / m_move
    bump = 30.0 * s**2 * (1 - s) ** 2  # integrates to 1 over [0, 1]
    for _ in range(n_poses):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        angle = rng.uniform(0.8, 2.2)
        theta = angle * np.cumsum(bump) / m_move
        rates = np.outer(bump * angle / move, axis)
        for th in theta:
            qk = _qmul(q, np.concatenate([[np.cos(th / 2)], np.sin(th / 2) * axis]))
            f.append(_rot(qk, g_nav)[None])
        w.append(rates)
        q = _qmul(q, np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis]))
        f.append(np.tile(_rot(q, g_nav), (m_hold, 1)))
        w.append(np.zeros((m_hold, 3)))
    f = np.concatenate(f)
    w = np.concatenate(w)
    n = f.shape[0]
    t = np.arange(n) / fs
    accel = f @ np.linalg.inv(truth["accel_matrix"]).T + truth["accel_bias"]
    gyro = w @ np.linalg.inv(truth["gyro_matrix"]).T + truth["gyro_bias"]
    accel += acc_noise * rng.normal(size=accel.shape)
    gyro += gyro_noise * rng.normal(size=gyro.shape)
    return t, accel, gyro


TRUTH = {
    # raw counts: ~ 400 counts per g, offsets near mid-range
    "accel_matrix": np.array([[0.0245, -8e-5, -2e-4], [0.0, 0.0243, -5e-4], [0.0, 0.0, 0.0241]]),
    "accel_bias": np.array([512.0, 498.0, 530.0]),
    "gyro_matrix": np.array([[2.1e-3, 1.2e-5, 2e-6], [1.7e-5, 2.09e-3, -1.1e-4], [5e-5, -5e-6, 2.11e-3]]),
    "gyro_bias": np.array([510.0, 495.0, 501.0]),
}


def test_recovers_known_calibration_from_simulated_poses():
    t, accel, gyro = simulate_poses(TRUTH)
    res = multi_position(accel, gyro, t, gravity=9.81, init_seconds=10.0)
    assert len(res.intervals) == 25           # the rest plus every pose
    np.testing.assert_allclose(res.accel_matrix, TRUTH["accel_matrix"], rtol=0, atol=2e-5)
    np.testing.assert_allclose(res.accel_bias, TRUTH["accel_bias"], atol=0.3)
    np.testing.assert_allclose(res.gyro_bias, TRUTH["gyro_bias"], atol=0.05)
    np.testing.assert_allclose(res.gyro_matrix, TRUTH["gyro_matrix"], rtol=0, atol=1e-5)
    assert np.max(np.abs(res.pose_norm_error)) < 0.003
    assert np.max(res.motion_residual) < 5e-3


def test_too_few_poses_is_a_clear_error():
    t, accel, gyro = simulate_poses(TRUTH, n_poses=4)
    with pytest.raises(DataError, match="static poses"):
        multi_position(accel, gyro, t, init_seconds=10.0)


@pytest.fixture(scope="module")
def imutk():
    """IMU-TK's own output on this data, with how it was obtained (imutk_reference.json)."""
    ref = json.loads((DATA / "imutk_reference.json").read_text())
    for sensor in ("accelerometer", "gyroscope"):
        r = ref[sensor]
        r["matrix"] = np.asarray(r["T"]) @ np.diag(r["K"])  # calibrated = T·K·(raw − B)
        r["B"] = np.asarray(r["B"])
    return ref


@pytest.fixture(scope="module")
def xsens():
    acc = np.loadtxt(DATA / "xsens_acc.mat")
    gyr = np.loadtxt(DATA / "xsens_gyro.mat")
    assert np.array_equal(acc[:, 0], gyr[:, 0])
    return acc[:, 0], acc[:, 1:], gyr[:, 1:]


@pytest.fixture(scope="module")
def xsens_result(xsens, imutk):
    t, acc, gyr = xsens
    # IMU-TK's example settings: 50 s initial rest, multipliers 2..10, first 100 samples per pose
    return multi_position(acc, gyr, t, gravity=imutk["gravity"], init_seconds=50.0)


def _imutk_pose_errors(imutk, acc, intervals, n_samples=100):
    """IMU-TK's accelerometer calibration on the given poses: per pose ‖mean a‖ − g, and the
    RMS of ‖a‖ − g over the first ``n_samples`` of every pose."""
    r, g = imutk["accelerometer"], imutk["gravity"]
    cal = (acc - r["B"]) @ r["matrix"].T
    whole = np.array([np.linalg.norm(cal[a:b].mean(0)) - g for a, b in intervals])
    first = np.concatenate([np.linalg.norm(cal[a:a + n_samples], axis=1) - g for a, _ in intervals])
    return whole, float(np.sqrt(np.mean(first**2)))


def test_imutk_xsens_static_poses_and_accelerometer(xsens, xsens_result, imutk):
    res, ref = xsens_result, imutk["accelerometer"]
    # IMU-TK's detection: the same threshold multiplier and number of static intervals
    assert res.threshold_multiplier == ref["threshold_multiplier"]
    assert len(res.intervals) == ref["static_intervals"]
    # the same calibration: IMU-TK's cost at its minimum, matrix and bias (in counts)
    assert res.accel_cost == pytest.approx(ref["residual"], rel=1e-5)
    np.testing.assert_allclose(res.accel_matrix, ref["matrix"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(res.accel_bias, ref["B"], rtol=0, atol=1e-3)
    # and so the same gravity errors on the poses: IMU-TK's worst pose 0.0025 m/s² (0.026 %),
    # RMS 0.008 m/s² over the first 100 samples of each pose
    whole, rms = _imutk_pose_errors(imutk, xsens[1], res.intervals)
    assert np.abs(res.pose_norm_error).max() == pytest.approx(np.abs(whole).max(), rel=1e-3)
    assert res.pose_rms == pytest.approx(rms, rel=1e-3)
    assert np.abs(res.pose_norm_error).max() / imutk["gravity"] < 5e-4
    assert np.abs(res.pose_norm_error_first).max() / imutk["gravity"] < 5e-4


def test_imutk_xsens_pose_means_beat_imutk(xsens, xsens_result, imutk):
    t, acc, gyr = xsens
    res = multi_position(acc, gyr, t, gravity=imutk["gravity"], init_seconds=50.0, pose_means=True)
    np.testing.assert_array_equal(res.intervals, xsens_result.intervals)  # IMU-TK's poses
    whole, rms = _imutk_pose_errors(imutk, acc, res.intervals)
    # diffgyro's variant fits whole-pose means: worst pose 0.0021 m/s² against IMU-TK's
    # 0.0025 m/s² (about 15 % better); the first-100-sample RMS stays within 1 % of IMU-TK's
    assert np.abs(res.pose_norm_error).max() < 0.9 * np.abs(whole).max()
    assert res.pose_rms == pytest.approx(rms, rel=0.01)


def test_imutk_xsens_gyro_scales(xsens_result, imutk):
    res, ref = xsens_result, imutk["gyroscope"]
    # IMU-TK's gyro scales, about 4770 counts per rad/s: within 0.05 % per axis; the whole
    # matrix within 0.025 % of the scale, the bias (counts) within 0.02
    np.testing.assert_allclose(res.gyro_scale_counts, 1.0 / np.asarray(ref["K"]), rtol=5e-4)
    np.testing.assert_allclose(res.gyro_matrix, ref["matrix"], rtol=0, atol=5e-8)
    np.testing.assert_allclose(res.gyro_bias, ref["B"], rtol=0, atol=0.02)
    # the motions close: median gravity-direction residual after integration below 0.05 rad
    assert np.median(res.motion_residual) < 0.05
