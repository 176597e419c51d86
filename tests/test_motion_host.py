"""The motion check's judgement of a large batch (one compiled loop over its devices) against
a small batch's on the host (numpy) of the same window statistics: the same flags and
window arrays, the same numbers to float32's last bits, over recordings at rest, turning,
shaken, tilted, short, partly invalid and empty, with and without the accelerometer, in
groups of one device, of a few, and of many at rest with a few that move (judged on
threads, chunks of devices side by side); and random devices with invalid values (NaN in
either signal, a device without a valid gyro window), quantised outputs and padding."""

from __future__ import annotations

import numpy as np
import pytest

from diffgyro.internal import check_windows, judge_on_host, window_stats
from diffgyro.motion import QUANTILE_WINDOWS, noise_quantiles, window_sizes


def _signals(kind: str, n: int, fs: float, seed: int):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    gyro = np.array([0.004, -0.0025, 0.0011]) + rng.normal(0.0, 0.003, (n, 3))
    gyro[:, 0] += 2e-5 * t  # thermal drift
    accel = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 0.02, (n, 3))
    if kind in ("turns", "tilt"):
        for k, start in enumerate(np.arange(min(20.0, t[-1] / 3), t[-1] - 5.0, 40.0)):
            on = (t >= start) & (t < start + 4.0)
            gyro[on, 2] += 0.6 if k % 2 == 0 else -0.6
            if kind == "tilt":  # gravity leaves z after the turn
                accel[t >= start + 4.0, 0] += 0.4 if k % 2 == 0 else -0.4
    if kind == "shaken":
        gyro += 0.05 * np.sin(2 * np.pi * 37.0 * t)[:, None]
    if kind == "knock":
        gyro[n // 2:n // 2 + 3] += 2.0
    return gyro, accel


def _stats(kinds, n: int, fs: float, rows: int, windows_pad: int = 0, gaps: bool = False):
    w, b = window_sizes(1.0 / fs)
    sig = [_signals(k, n, fs, s) for s, k in enumerate(kinds)]
    gyro = np.stack([g for g, _ in sig])
    accel = np.stack([a for _, a in sig])
    mask = np.ones((len(kinds), n), bool)
    if gaps:
        mask[0, n // 3:n // 3 + 5 * w] = False
        mask[-1] = False  # a device without a valid sample
    k = -(-n // w) + windows_pad
    idx = np.minimum(np.arange(rows), len(kinds) - 1)
    read = [window_stats(x, mask, w, idx, k, noise_quantiles(), QUANTILE_WINDOWS)
            for x in (gyro, accel)]
    return read, w, b


CASES = {
    "at rest": (["rest"], 6000, 10.0, 1, 0, False),
    "turns and a knock": (["turns", "knock"], 6000, 10.0, 2, 64, False),
    "tilted": (["tilt", "rest", "shaken"], 8000, 20.0, 4, 0, True),
    "short": (["turns"], 400, 10.0, 1, 0, False),
    "one block": (["turns"], 200, 10.0, 1, 0, False),
    "many devices": (["rest", "turns", "shaken", "tilt", "knock"] * 2, 3000, 10.0, 16, 0, True),
    "slow rate": (["turns", "rest"], 7200, 2.0, 2, 20, False),
    # 64 devices of 750 windows: judged on threads (THREAD_WINDOWS), chunks side by side
    "many at rest, a few moving": (["rest"] * 30 + ["turns"] + ["rest"] * 30 + ["tilt", "knock"],
                                   3000, 10.0, 64, 0, True),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("with_accel", [False, True])
def test_the_compiled_loop_judges_as_the_host(case, with_accel):
    kinds, n, fs, rows, pad, gaps = CASES[case]
    (gyro, accel), w, b = _stats(kinds, n, fs, rows, pad, gaps)
    accel = accel if with_accel else None
    host = judge_on_host(gyro, accel, w, b)
    compiled = check_windows(gyro, accel, w, b)
    assert list(compiled) == list(host)
    for key, want in host.items():
        got = np.asarray(compiled[key])
        assert got.shape == want.shape and got.dtype == want.dtype, key
        if want.dtype == bool:
            np.testing.assert_array_equal(got, want, err_msg=key)
        else:
            np.testing.assert_allclose(got, want, rtol=1e-6, atol=0, equal_nan=True, err_msg=key)
    if case != "at rest":
        assert host["window_moving"].any()  # the cases hold the rule's work
    if case == "many at rest, a few moving":  # most devices skip the second pass; a few take it
        assert 0 < host["window_moving"].any(axis=1).sum() < len(kinds) // 4


def _random_stats(rng):
    """Window statistics of a few random devices: noise of random level, steps on random
    axes, accelerometer tilts, stretches of NaN in either signal (or a whole device's gyro),
    quantised outputs, missing samples, and padded windows and devices."""
    d, n = int(rng.integers(1, 8)), int(rng.integers(50, 3000))
    w, b = int(rng.choice([4, 8, 32])), int(rng.choice([4, 8, 16, 64]))
    gyro = rng.normal(0, 10 ** rng.uniform(-4, -1), (d, n, 3)) + rng.normal(0, 0.01, (d, 1, 3))
    accel = np.array([0.0, 0.0, 9.81]) + rng.normal(0, 0.02, (d, n, 3))
    for i in range(d):
        for _ in range(int(rng.integers(0, 4))):
            s, length = int(rng.integers(0, n)), int(rng.integers(1, 200))
            gyro[i, s:s + length, int(rng.integers(3))] += rng.normal(0, 1)
            accel[i, s + length:, int(rng.integers(3))] += rng.normal(0, 0.3) * (rng.random() < 0.3)
        for x in (gyro, accel):
            if rng.random() < 0.2:
                s = int(rng.integers(0, n))
                x[i, s:s + int(rng.integers(1, 300))] = np.nan
        if rng.random() < 0.05:
            gyro[i] = np.nan
        if rng.random() < 0.1:
            gyro[i] = np.round(gyro[i] / 1e-3) * 1e-3
    mask = rng.random((d, n)) > rng.choice([0.0, 0.01, 0.3])
    k = -(-n // w) + int(rng.integers(0, 3)) * b
    rows = int(rng.integers(d, d + 4))
    idx = np.minimum(np.arange(rows), d - 1)
    read = [window_stats(x, mask, w, idx, k, noise_quantiles(), QUANTILE_WINDOWS, rows)
            for x in (gyro, accel)]
    return read, w, b


@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_loop_judges_random_devices_as_the_host(seed):
    """Random devices, invalid values and paddings: the same flags and window arrays, the
    numbers equal to float32's last bits (every window's sums in float64 either way)."""
    rng = np.random.default_rng(seed)
    moved = 0
    for _ in range(10):
        (gyro, accel), w, b = _random_stats(rng)
        for acc in (None, accel):
            host = judge_on_host(gyro, acc, w, b)
            compiled = check_windows(gyro, acc, w, b)
            moved += host["window_moving"].any()
            for key, want in host.items():
                got = compiled[key]
                assert got.dtype == want.dtype and got.shape == want.shape, key
                if want.dtype == bool:
                    np.testing.assert_array_equal(got, want, err_msg=key)
                else:
                    np.testing.assert_allclose(got, want, rtol=1e-6, atol=0, equal_nan=True,
                                               err_msg=key)
    assert moved >= 5  # (the rule on runs and the second baseline are exercised)
