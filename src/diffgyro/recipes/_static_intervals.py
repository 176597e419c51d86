"""Static-interval detection from the local variance of the accelerometer.

The detector of Tedaldi, Pretto and Menegatti (ICRA 2014, IMU-TK): for every
sample, the variance of each accelerometer axis over a centred window
(default 101 samples); the sample is static while the norm of that
3-vector of variances stays below ``multiplier × ‖var(initial rest)‖``, the
per-axis variances of a known initial rest window. Consecutive static
samples form an interval. Computed with cumulative sums, O(n).
"""

from __future__ import annotations

import numpy as np


def window_variance(x: np.ndarray, half: int) -> np.ndarray:
    """Per-axis variance of ``x`` over samples ``i − half .. i + half`` (NaN where
    the window does not fit). ``x`` is ``(n, k)``; uses the unbiased estimator."""
    x = np.asarray(x, float)
    n = x.shape[0]
    w = 2 * half + 1
    out = np.full(x.shape, np.nan)
    if n < w:
        return out
    xc = x - x.mean(0)
    c1 = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(xc, 0)])
    c2 = np.concatenate([np.zeros((1, x.shape[1])), np.cumsum(xc * xc, 0)])
    s1 = c1[w:] - c1[:-w]
    s2 = c2[w:] - c2[:-w]
    out[half:n - half] = np.maximum(s2 - s1 * s1 / w, 0.0) / (w - 1)
    return out


def runs(flag: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` index ranges of consecutive True values."""
    f = np.concatenate([[False], np.asarray(flag, bool), [False]])
    edges = np.flatnonzero(np.diff(f.astype(np.int8)))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def static_intervals(
    accel: np.ndarray,
    threshold: float,
    window: int = 101,
    min_length: int = 1,
) -> list[tuple[int, int]]:
    """``[start, end)`` ranges where the windowed variance norm is below ``threshold``.

    ``window`` is made odd and at least 11 samples; intervals shorter than
    ``min_length`` samples are dropped.

    **Arguments:**

    - ``accel``: the accelerometer's output (n, 3).
    - ``threshold``: the windowed variance norm below which a sample is static.
    - ``window``: the variance window, samples.
    - ``min_length``: the shortest interval kept, samples.
    """
    window = max(int(window), 11)
    window += 1 - window % 2
    var = window_variance(accel, window // 2)
    norm = np.linalg.norm(var, axis=1)
    flag = np.nan_to_num(norm, nan=np.inf) < threshold
    return [(a, b) for a, b in runs(flag) if b - a >= min_length]


def rest_variance_norm(accel: np.ndarray, n_init: int) -> float:
    """``‖(var a_x, var a_y, var a_z)‖`` over the first ``n_init`` samples (known rest)."""
    return float(np.linalg.norm(np.var(np.asarray(accel, float)[:n_init], axis=0, ddof=1)))
