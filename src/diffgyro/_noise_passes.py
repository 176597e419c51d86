"""The compiled passes of the host noise floor (numba): :mod:`diffgyro._noise`.

The floor of a long row reads every difference a few times: to form it from
the samples, to place the window (a subsample) and to count and sum those
inside. numpy would pass over a row once per operation (transpose and
subtract, subtract, compare, sum, dot), each with its own temporary; here
each pass reads the row once. The window's two order statistics (the subsample's
median and MAD) are selected without a branch per value (:mod:`diffgyro._select`):
numpy's ``ndarray.partition`` took about three times as long on the same rows. The
sums are reassociated into vector lanes: their rounding differs from a sequential
sum's by a few ulps.

Compiled on first use and cached on disk (``cache=True``); imported only when a
floor is computed (numba's import takes about half a second). ``nogil``: the
threads of :func:`diffgyro._noise.start` run them side by side.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Float, Int
from numba import njit

from ._select import select


@njit(cache=True, nogil=True)
def _differences(y, rate, ranks, rows, sub):  # pragma: no cover - compiled
    for i in range(y.shape[0]):
        x, r0, r1, r2 = y[i], rows[3 * i], rows[3 * i + 1], rows[3 * i + 2]
        if rate.shape[0]:
            x = x - rate[i]  # the numbers numpy's y − rate gives
        for j in range(x.shape[0] - 1):  # the three axes side by side: one read of the samples
            r0[j] = x[j + 1, 0] - x[j, 0]
            r1[j] = x[j + 1, 1] - x[j, 1]
            r2[j] = x[j + 1, 2] - x[j, 2]
        for k in range(3):  # while the device's rows are in cache
            for q in range(ranks.shape[0]):
                sub[3 * i + k, q] = rows[3 * i + k, ranks[q]]


def differences(y: Float[np.ndarray, "d n 3"], rate: Float[np.ndarray, "d n 3"] | None,
                ranks: Int[np.ndarray, " k"]
                ) -> tuple[Float[np.ndarray, "r m"], Float[np.ndarray, "r k"]]:
    """Lag-1 differences of ``y − rate``, a row per device and axis (the numbers
    ``np.diff(y − rate, axis=1)`` gives), and their columns ``ranks``."""
    y = np.ascontiguousarray(y)
    rate = np.zeros((0, 1, 3), y.dtype) if rate is None else np.ascontiguousarray(rate, y.dtype)
    rows = np.empty((3 * y.shape[0], y.shape[1] - 1), y.dtype)
    sub = np.empty((rows.shape[0], ranks.shape[0]), y.dtype)
    _differences(y, rate, np.ascontiguousarray(ranks, np.int64), rows, sub)
    return rows, sub


@njit(cache=True, nogil=True)
def _place(sub, centre, half_width, ties):  # pragma: no cover - compiled
    k = sub.shape[1]
    mid = k // 2
    low, high, dev = np.empty(k, sub.dtype), np.empty(k, sub.dtype), np.empty(k, sub.dtype)
    for i in range(sub.shape[0]):
        c = select(sub[i], k, mid, low, high)
        t = 0
        for j in range(k):  # (the numbers numpy's ``|sub − centre|`` gives)
            v = abs(sub[i, j] - c)
            dev[j] = v
            t += v == 0
        centre[i] = c
        ties[i] = t
        half_width[i] = 4.0 * 1.4826 * select(dev, k, mid, low, high)


def place(sub: Float[np.ndarray, "r k"]
          ) -> tuple[Float[np.ndarray, " r"], Float[np.ndarray, " r"], Int[np.ndarray, " r"]]:
    """Each row's window from its subsample of an odd count ``k``: the median, the half
    width 4 × 1.4826 × the median of the deviations from it (MAD), and how many of the
    deviations are 0. The order statistics numpy's partition gives (:func:`diffgyro._noise._middle`:
    the same values), selected without a branch per value (:func:`diffgyro._select.select`)."""
    sub = np.ascontiguousarray(sub)
    r = sub.shape[0]
    centre, half_width = np.empty(r, sub.dtype), np.empty(r, sub.dtype)
    ties = np.empty(r, np.int64)
    _place(sub, centre, half_width, ties)
    return centre, half_width, ties


@njit(cache=True, nogil=True, fastmath={"reassoc"})
def _row_sums(row, centre, half_width):  # pragma: no cover - compiled
    w2 = half_width * half_width
    count = 0
    s1 = 0.0
    s2 = 0.0
    for j in range(row.shape[0]):
        s = row[j] - centre
        q = s * s
        inside = q <= w2  # NaN and ±inf never are, but s·0 is NaN: so are the row's sums
        count += inside
        s1 += s * inside
        s2 += q * inside
    return count, s1, s2


@njit(cache=True, nogil=True)
def _sums(rows, centre, half_width, out):  # pragma: no cover - compiled
    for i in range(rows.shape[0]):
        c, s1, s2 = _row_sums(rows[i], centre[i], half_width[i])
        out[i, 0] = c
        out[i, 1] = s1
        out[i, 2] = s2


def window_sums(rows: Float[np.ndarray, "r m"], centre: Float[np.ndarray, " r"],
                half_width: Float[np.ndarray, " r"]) -> Float[np.ndarray, "r 3"]:
    """Per row: the count of ``|Δy − centre| ≤ half_width``, the sum of those ``Δy − centre``
    and of their squares (NaN sums for a row holding a NaN or an infinity)."""
    rows = np.ascontiguousarray(rows)
    out = np.empty((rows.shape[0], 3), rows.dtype)
    _sums(rows, np.ascontiguousarray(centre, rows.dtype),
          np.ascontiguousarray(half_width, rows.dtype), out)
    return out
