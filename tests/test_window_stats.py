"""The motion check's window statistics (:mod:`diffgyro._window_stats`): closed-form
values, and the compiled pass of a large batch equal to numpy's of a small one."""

from __future__ import annotations

import numpy as np
import pytest

from diffgyro._window_pass import compiled_pass
from diffgyro._window_stats import _numpy_pass, window_stats
from diffgyro.motion import noise_quantiles

Q = np.asarray(noise_quantiles())


def test_window_statistics_in_closed_form():
    """A ramp of slope 1 per sample on x, a constant on y, an alternating ±1 on z, in
    windows of 8: means, half differences and local noise are known exactly; a window
    with one valid sample is invalid."""
    n, w = 64, 8
    x = np.zeros((1, n, 3))
    x[0, :, 0] = np.arange(n)
    x[0, :, 1] = 2.5
    x[0, :, 2] = np.where(np.arange(n) % 2, 1.0, -1.0)
    mask = np.ones((1, n), bool)
    mask[0, 57:] = False  # the last window holds one sample
    stats, count, valid, _ = window_stats(x, mask, w, np.arange(1), n // w, tuple(Q), 512)
    k = np.arange(7)
    np.testing.assert_allclose(stats[0, k, 0, 0], 8 * k + 3.5)
    np.testing.assert_allclose(stats[0, k, 0, 1], 2.5)
    np.testing.assert_allclose(stats[0, k, 2, 0], -4.0)  # first half's mean less the second's
    np.testing.assert_allclose(stats[0, k, 1], np.tile([np.sqrt(0.5), 0.0, np.sqrt(2.0)], (7, 1)),
                               rtol=1e-6)
    assert count[0].tolist() == [8.0] * 7 + [1.0]
    assert valid[0].tolist() == [True] * 7 + [False]


@pytest.mark.parametrize("w,windows,limit,referenced", [(4, 800, 512, False), (32, 100, 16, True)])
def test_the_compiled_pass_gives_numpys_numbers(w, windows, limit, referenced):
    """Gaps, a NaN sample, a quantised device, a device with no valid sample and a rate
    reference: the same statistics to float32 rounding (sums in another order) and the
    same validity and rest noise."""
    rng = np.random.default_rng(0)
    d, n = 5, 3001
    x = rng.normal(size=(d, n, 3)) * 1e-3 + 0.01
    x[2, 50] = np.nan
    x[3] = np.round(x[3] * 1e4) / 1e4
    mask = rng.random((d, n)) > 0.05
    mask[4] = False
    rate = rng.normal(size=(d, n, 3)) * 1e-4 if referenced else None
    rows = np.array([4, 0, 2, 3, 1])
    outs = []
    for compiled in (True, False):
        out = (np.zeros((6, windows, 3, 3), np.float32), np.zeros((6, windows), np.float32),
               np.zeros((6, windows), bool), np.full((6, 2, 3), np.nan, np.float32))
        if compiled:
            compiled_pass(x, mask, np.zeros((0, 1, 3)) if rate is None else rate, rows, w, *out, Q,
                          limit)
        else:
            _numpy_pass(x, mask, rate, rows, w, *out, Q, limit)
        outs.append(out)
    (s1, c1, v1, n1), (s2, c2, v2, n2) = outs
    np.testing.assert_allclose(s1, s2, rtol=1e-6, atol=1e-15)
    np.testing.assert_array_equal(c1, c2)
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_allclose(n1, n2, rtol=1e-6)
    assert np.isnan(n1[0]).all() and not v1[0].any()  # the device with no valid sample


@pytest.mark.parametrize("channels", [(), (3,)])
def test_window_means_compiled_equal_numpys(channels, monkeypatch):
    """Means over windows of a signal with gaps, leading and trailing empty windows and
    windows past the samples: the compiled pass gives numpy's numbers (an empty window
    holds its earlier neighbour's, the first one's before any), and a window of one valid
    sample its value."""
    import diffgyro._window_stats as ws

    rng = np.random.default_rng(1)
    d, n, h, k = 4, 203, 8, 30  # 26 windows hold samples, 4 lie past them
    x = rng.normal(size=(d, n) + channels)
    mask = rng.random((d, n)) > 0.3
    mask[1, :40] = False  # leading empty windows
    mask[2, 100:136] = False
    mask[2, 131] = True  # a window holding one sample
    rows = np.array([2, 0, 1])
    outs = []
    for compiled in (True, False):
        monkeypatch.setattr(ws, "_loaded", compiled)
        monkeypatch.setattr(ws, "COMPILED_SAMPLES", 1 << 40)
        outs.append(ws.window_means(x, mask, rows, h, k))
    np.testing.assert_allclose(outs[0], outs[1], rtol=1e-12, atol=1e-15)
    m = outs[0]
    assert m.shape == (3, k) + channels
    np.testing.assert_allclose(m[0, 16], x[2, 131])  # the window 128..135 holds one sample
    first = next(j for j in range(k) if mask[1, j * h:(j + 1) * h].any())
    np.testing.assert_allclose(m[2, :first], np.broadcast_to(m[2, first], m[2, :first].shape))
    np.testing.assert_allclose(m[1, 26:], np.broadcast_to(m[1, 25], m[1, 26:].shape))
    j = 5
    sel = mask[0, j * h:(j + 1) * h]
    np.testing.assert_allclose(m[1, j], x[0, j * h:(j + 1) * h][sel].mean(axis=0))


@pytest.mark.parametrize("w,windows,limit", [(16, 40, 512), (8, 300, 64)])
def test_the_explanation_compiled_equals_numpys(w, windows, limit, monkeypatch):
    """What a model leaves, at the windows (diffgyro._window_explain.explained): the compiled
    loop gives numpy's numbers exactly, with invalid windows, a device whose residual holds
    a NaN in a valid window (it keeps the recording's), one in an invalid window (ignored),
    one not explained, and one with no valid window (NaN noise)."""
    import diffgyro._window_stats as ws
    from diffgyro._window_explain import explained

    rng = np.random.default_rng(2)
    r = 6
    stats = rng.normal(size=(r, windows, 3, 3)).astype(np.float32) * 1e-3
    noise = np.abs(rng.normal(size=(r, 2, 3))).astype(np.float32) * 1e-3
    noise[5] = np.nan
    valid = rng.random((r, windows)) > 0.2
    valid[5] = False
    residual = rng.normal(size=(r, windows, 2, 3)) * 1e-3
    residual[1, np.flatnonzero(valid[1])[3], 0, 1] = np.nan
    residual[2, np.flatnonzero(~valid[2])[0], 1, 2] = np.inf
    rows = np.array([True, True, True, False, True, True])
    outs = []
    for compiled in (True, False):
        monkeypatch.setattr(ws, "_loaded", compiled)
        monkeypatch.setattr(ws, "COMPILED_SAMPLES", 1 << 40)
        outs.append(explained(stats, noise, valid, residual, rows, w, tuple(Q), limit))
    (s1, n1), (s2, n2) = outs
    np.testing.assert_array_equal(s1, s2)
    np.testing.assert_array_equal(n1, n2)
    np.testing.assert_array_equal(s1[[1, 3]], stats[[1, 3]])  # kept: a NaN, not explained
    assert not np.array_equal(s1[2], stats[2])  # an infinity in an invalid window: explained
    assert np.isnan(n1[5, 1]).all() and not np.array_equal(n1[0, 1], noise[0, 1])
