"""The motion check's reading of a fitted model (diffgyro._window_explain): the residual's
window statistics in closed form, and a chamber's ramps judged by what the model leaves."""

from __future__ import annotations

import numpy as np
import pytest

from diffgyro import Batch, Recording
from diffgyro._motion_judge import _explanation, judge_motion
from diffgyro._window_explain import explain_windows
from diffgyro._window_stats import window_stats
from diffgyro.fit import fit
from diffgyro.motion import QUANTILE_WINDOWS, motion_check, noise_quantiles


def _chamber(seed: int, turn: float = 0.0) -> Recording:
    """Three hours at 1 Hz in a chamber: ramps between soaks with sharp kinks, a cubic
    bias in temperature, white noise of 1e-4 rad/s; ``turn`` (rad) turned about z in 5 s
    after two hours."""
    rng = np.random.default_rng(seed)
    t = np.arange(10_800.0)
    temp = np.interp(t, [0, 1500, 2500, 4500, 5200, 7000, 8000, 10_800],
                     [20, 20, 60, 60, -10, -10, 35, 35]) + 0.02 * rng.normal(size=t.size)
    x = (temp - 25.0) / 35.0
    coef = np.array([[2e-3, 3e-3, 1e-3, 3e-4], [-1e-3, 2e-3, -1e-3, 2e-4], [5e-4, -3e-3, 5e-4, -3e-4]])
    gyro = (x[:, None] ** np.arange(4)) @ coef.T + 1e-4 * rng.normal(size=(t.size, 3))
    gyro[:, 2] += np.where((t >= 7200) & (t < 7205), turn / 5.0, 0.0)
    return Recording(t=t, gyro=gyro, temp=temp, device=f"chamber{seed}")


@pytest.fixture(scope="module")
def chamber():
    batch = Batch.from_recordings([_chamber(1), _chamber(2, turn=np.radians(5.0))])
    return batch, fit("bias_poly(3)", batch)


def test_the_residuals_window_statistics_in_closed_form():
    """For a model linear in its signals, the residual at the half windows' means is the
    mean of the residual over them: the window means and half-window differences of the
    explained statistics are the per-sample residual's."""
    rec = _chamber(3)
    batch = Batch.from_recordings([rec])
    res = fit("bias_poly(1)", batch, check_motion=False)
    w, k = 16, QUANTILE_WINDOWS  # (every window read for the quantiles)
    q = noise_quantiles()
    stats, _, valid, noise = window_stats(np.asarray(batch.gyro), np.asarray(batch.mask), w,
                                          np.arange(1), k, q, QUANTILE_WINDOWS)
    left, noise2 = explain_windows(batch, _explanation(res, batch), np.arange(1), w, stats, noise,
                                   valid, np.ones(1, bool), q, QUANTILE_WINDOWS)
    r = np.asarray(res.residuals(batch))[0, :k * w].reshape(k, 2, w // 2, 3).mean(axis=2)
    np.testing.assert_allclose(left[0, :, 0], r.mean(axis=1), atol=2e-7)
    np.testing.assert_allclose(left[0, :, 2], r[:, 0] - r[:, 1], atol=2e-7)
    np.testing.assert_array_equal(left[0, :, 1], stats[0, :, 1])  # the local noise as recorded
    np.testing.assert_array_equal(noise2[0, 0], noise[0, 0])
    _, half_q, _, zh = q  # a window mean's noise from the residual's half differences
    half = np.quantile(np.abs(r[:, 0] - r[:, 1]), half_q, axis=0)
    np.testing.assert_allclose(noise2[0, 1], np.maximum(noise[0, 0] / 4, half / zh / 2), rtol=1e-5)


def test_a_chambers_ramps_are_explained_in_the_first_look_and_a_turn_is_not(chamber):
    """The kinks of the ramps leave the baseline of the recording's own windows; the fitted
    cubic explains them, so the device at rest is ok in the first look's long windows. A
    turn of 5° that no model of temperature follows stays motion."""
    batch, res = chamber
    raw = motion_check(batch)
    assert raw.moving_fraction[0] > 0 or raw.window[0] < 32  # the recording alone: not plain rest
    rest, turned = res.records()
    assert rest["status"] == "ok", rest["motion"]
    assert rest["motion"]["moving_fraction"] == 0.0
    assert rest["motion"]["window_s"] > 16.0  # judged in the first look's long windows
    assert turned["status"] == "in_motion"
    assert turned["motion"]["turn_peak"] == pytest.approx(np.radians(5.0), rel=0.15)
    # the rest rate reported is the recording's (the residual's is about zero)
    gyro = np.asarray(batch.gyro)[0][np.asarray(batch.mask)[0]]
    assert rest["motion"]["rest_rate"] == pytest.approx(np.linalg.norm(gyro.mean(axis=0)), rel=0.02)


def test_a_fit_that_does_not_stand_explains_nothing():
    """A short recording whose temperature barely moves cannot support a quadratic in it
    (``insufficient_range``), yet its coefficients absorb a spin that starts a third of
    the way in: the recording's own judgement stands, and the spin is motion."""
    rng = np.random.default_rng(4)
    t = np.arange(0.0, 20.0, 0.1)
    gyro = 1e-3 * rng.normal(size=(t.size, 3))
    gyro[:, 2] += 0.5 * np.clip(t - 20.0 / 3.0, 0.0, 1.0)
    temp = 25.0 + 0.001 * t + 0.01 * rng.normal(size=t.size)
    res = fit("bias_poly(2)", Recording(t=t, gyro=gyro, temp=temp, device="spun"))
    rec = res.records()[0]
    assert rec["status"] == "insufficient_range"
    assert rec["motion"]["verdict"] == "in_motion", rec["motion"]


def test_the_first_look_read_beside_the_fit_is_the_one_read_after_it(chamber):
    """What a fit reads of the recording while it solves (``check_ahead``: the first look's
    window statistics and the half windows its model is evaluated at) gives the judgement
    the check forms by itself afterwards."""
    batch, res = chamber
    again = judge_motion(fit("bias_poly(3)", batch, check_motion=False), batch).motion
    for name in ("verdict", "moving_fraction", "rate_peak", "rest_rate", "threshold", "window",
                 "static"):
        np.testing.assert_array_equal(getattr(res.motion, name), getattr(again, name), err_msg=name)
