"""The motion check's compiled pass over a large batch's samples (numba): window
statistics (:mod:`diffgyro._window_stats` says what they are), formed in one read of each
device's samples (the three axes side by side), on the host's cores (chunks of devices
on threads, one per core). Sums accumulate in float64; the statistics are stored in float32 (what the
judgement reads).

Compiled on first use and cached on disk (``cache=True``); imported only when a check
runs.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._jit import on_threads
from ._select import select
from .data import aligned_empty


@njit(cache=True, nogil=True)
def _quantile(values, n, q):  # pragma: no cover - compiled
    """The ``q`` quantile of ``values[:n]`` (linear between order statistics; NaN if none)."""
    if n == 0:
        return math.nan
    h = q * (n - 1)
    lo = int(math.floor(h))
    hi = min(lo + 1, n - 1)
    low, high = np.empty_like(values[:n]), np.empty_like(values[:n])
    a = select(values, n, lo, low, high)
    b = a
    if hi > lo:  # the next order statistic: a again where it repeats, else the smallest above it
        ties = 0
        low[0] = math.inf
        above = low[0]  # (an infinity of the values' type)
        for i in range(n):
            x = values[i]
            ties += x <= a
            above = min(above, x if x > a else above)  # (in the values' type)
        b = a if ties > hi else above
    return a + (b - a) * (h - lo)


@njit(cache=True, nogil=True, inline="always")
def _half(xi, lo, hi, a0, a1, a2, p0, p1, p2, e0, e1, e2, r0, r1, r2):  # pragma: no cover
    """Samples ``lo`` to ``hi`` of a window of valid samples (``xi``: a device's (n, 3)) in
    one read, each sum carried on in the samples' order: the sums per axis from ``a``, and
    with ``p`` the sample before ``lo``, the squared successive differences' from ``e`` and
    the smallest nonzero difference from ``r`` (``min`` of a select compiles without a
    branch, and a NaN never wins)."""
    for t in range(lo, hi):
        v0, v1, v2 = xi[t, 0], xi[t, 1], xi[t, 2]
        a0 += v0
        a1 += v1
        a2 += v2
        d0, d1, d2 = v0 - p0, v1 - p1, v2 - p2
        e0 += d0 * d0
        e1 += d1 * d1
        e2 += d2 * d2
        r0 = min(r0, abs(d0) if d0 != 0.0 else math.inf)
        r1 = min(r1, abs(d1) if d1 != 0.0 else math.inf)
        r2 = min(r2, abs(d2) if d2 != 0.0 else math.inf)
        p0, p1, p2 = v0, v1, v2
    return a0, a1, a2, e0, e1, e2, r0, r1, r2


@njit(cache=True, nogil=True, inline="always")
def _whole(xi, lo, h, w):  # pragma: no cover - compiled
    """A window of valid samples from ``lo``: its halves' sums and its differences (each
    in the samples' order), read once."""
    p0, p1, p2 = xi[lo, 0], xi[lo, 1], xi[lo, 2]  # (the first has no difference inside)
    inf = math.inf
    a0, a1, a2, e0, e1, e2, r0, r1, r2 = _half(xi, lo + 1, lo + h, 0.0 + p0, 0.0 + p1, 0.0 + p2,
                                               p0, p1, p2, 0.0, 0.0, 0.0, inf, inf, inf)
    q0, q1, q2 = xi[lo + h - 1, 0], xi[lo + h - 1, 1], xi[lo + h - 1, 2]
    b0, b1, b2, e0, e1, e2, r0, r1, r2 = _half(xi, lo + h, lo + w, 0.0, 0.0, 0.0, q0, q1, q2,
                                               e0, e1, e2, r0, r1, r2)
    return a0, a1, a2, b0, b1, b2, e0, e1, e2, r0, r1, r2


@njit(cache=True, nogil=True)
def _pass(x, mask, full, rate, rows, w, stats, count, valid, noise, quantiles,
          limit):  # pragma: no cover - compiled
    h = w // 2
    need = max(h, 2)
    for r in range(rows.shape[0]):
        i = rows[r]
        n = x.shape[1]
        k = (n + w - 1) // w
        q0 = q1 = q2 = math.inf
        xi = x[i]
        for j in range(min(k, stats.shape[1])):
            a0 = a1 = a2 = b0 = b1 = b2 = e0 = e1 = e2 = 0.0
            c1 = c = cp = 0.0
            p0 = p1 = p2 = 0.0
            prev = False
            lo = j * w
            # every sample valid (the device's): the same sums without a branch per sample
            whole = full[r] and not rate.shape[0] and lo + w <= n
            if whole:
                a0, a1, a2, b0, b1, b2, e0, e1, e2, r0, r1, r2 = _whole(xi, lo, h, w)
                q0, q1, q2 = min(q0, r0), min(q1, r1), min(q2, r2)
                c1, c, cp = float(h), float(w), float(w - 1)
            for s in range(0 if not whole else w, min(w, n - j * w)):
                t = j * w + s
                if not mask[i, t]:
                    prev = False
                    continue
                v0, v1, v2 = x[i, t, 0], x[i, t, 1], x[i, t, 2]
                if rate.shape[0]:
                    v0, v1, v2 = v0 - rate[i, t, 0], v1 - rate[i, t, 1], v2 - rate[i, t, 2]
                if s < h:
                    a0 += v0
                    a1 += v1
                    a2 += v2
                    c1 += 1.0
                else:
                    b0 += v0
                    b1 += v1
                    b2 += v2
                c += 1.0
                if prev:
                    d0, d1, d2 = v0 - p0, v1 - p1, v2 - p2
                    e0 += d0 * d0
                    e1 += d1 * d1
                    e2 += d2 * d2
                    cp += 1.0
                    # the quantum: the smallest nonzero change between neighbours
                    if d0 != 0.0 and abs(d0) < q0:
                        q0 = abs(d0)
                    if d1 != 0.0 and abs(d1) < q1:
                        q1 = abs(d1)
                    if d2 != 0.0 and abs(d2) < q2:
                        q2 = abs(d2)
                p0, p1, p2 = v0, v1, v2
                prev = True
            ca, cb, cq = max(c, 1.0), max(c1, 1.0), max(c - c1, 1.0)
            m0, m1, m2 = (a0 + b0) / ca, (a1 + b1) / ca, (a2 + b2) / ca
            cq2 = 2.0 * max(cp, 1.0)
            s0, s1, s2 = math.sqrt(e0 / cq2), math.sqrt(e1 / cq2), math.sqrt(e2 / cq2)
            stats[r, j, 0, 0], stats[r, j, 0, 1], stats[r, j, 0, 2] = m0, m1, m2
            stats[r, j, 1, 0], stats[r, j, 1, 1], stats[r, j, 1, 2] = s0, s1, s2
            stats[r, j, 2, 0] = a0 / cb - b0 / cq
            stats[r, j, 2, 1] = a1 / cb - b1 / cq
            stats[r, j, 2, 2] = a2 / cb - b2 / cq
            count[r, j] = c
            finite = (math.isfinite(m0) and math.isfinite(m1) and math.isfinite(m2)
                      and math.isfinite(s0) and math.isfinite(s1) and math.isfinite(s2))
            valid[r, j] = c >= need and cp >= 2.0 and c1 > 0.0 and c > c1 and finite
        _rest_noise(stats[r], valid[r], (q0, q1, q2), w, quantiles, limit, noise[r])


@njit(cache=True, nogil=True)
def _rest_noise(stats, valid, quanta, w, quantiles, limit, noise):  # pragma: no cover - compiled
    """One device's rest noise per axis, of one sample (σ) and of a window mean, from at
    most ``limit`` of its valid windows spread evenly over those it holds."""
    rest_q, half_q = quantiles[0], quantiles[1]
    # a quantile of a window's local noise is χ-distributed about σ (≈ normal): the
    # normal quantile of 1 − rest_q and of (1 + half_q)/2 (see diffgyro.motion)
    z, zh = quantiles[2], quantiles[3]
    chi = max(1.0 - z / math.sqrt(2.0 * max(w - 1, 1)), 0.5)
    span = 0
    for j in range(stats.shape[0]):
        if valid[j]:
            span = j + 1
    m = min(span, limit)
    local = np.empty(m, np.float32)
    half = np.empty(m, np.float32)
    for a in range(3):
        u = 0
        for j in range(m):
            at = (j * span) // limit if span > limit else j
            if valid[at]:
                local[u] = stats[at, 1, a]
                half[u] = abs(stats[at, 2, a])
                u += 1
        quantum = quanta[a] if quanta[a] < math.inf else 0.0
        sigma = max(_quantile(local, u, rest_q) / chi, quantum / math.sqrt(12.0))
        mean_noise = max(sigma / math.sqrt(w), _quantile(half, u, half_q) / zh / 2.0)
        noise[0, a] = sigma if u else math.nan
        noise[1, a] = mean_noise if u else math.nan


def compiled_pass(x, mask, rate, rows, w: int, stats, count, valid, noise, quantiles,
                  limit: int) -> None:
    """:func:`diffgyro._window_stats.window_stats` of a large batch, into its outputs
    (``rate`` of shape (0, 1, 3) where there is none): chunks of devices side by side on
    threads, one per core (the pass holds no GIL)."""
    full = _full(mask, rows)
    on_threads(len(rows), x.shape[1], lambda a, b: _pass(
        x, mask, full[a:b], rate, rows[a:b], w, stats[a:b], count[a:b], valid[a:b], noise[a:b],
        quantiles, limit), "windows", THREAD_SAMPLES)


def _full(mask, rows):
    """Whether every sample of each device ``rows`` is valid (numpy's vectorised reduction;
    the passes then read no mask). A few devices of a large batch (a second look) read
    their own rows only."""
    if 2 * len(rows) < len(mask):
        return np.all(mask[rows], axis=1)
    return np.ascontiguousarray(np.all(mask, axis=1)[rows])


#: Device-samples below which a pass runs on the caller's thread (starting threads costs
#: about a millisecond, what the pass of this many samples takes).
THREAD_SAMPLES = 1 << 18


@njit(cache=True, nogil=True)
def _means(x, mask, full, rows, h, out):  # pragma: no cover - compiled
    n, c = x.shape[1], x.shape[2]
    k = out.shape[1]
    for r in range(rows.shape[0]):
        i = rows[r]
        xi, mi = x[i], mask[i]
        last = -1  # the last window with a valid sample (an empty one holds it)
        for j in range(k):
            lo, hi = j * h, min(j * h + h, n)
            m = max(hi - lo, 0)
            if not full[r]:
                m = 0
                for t in range(lo, hi):
                    m += mi[t]
            if m:
                for a in range(c):  # a channel at a time: a loop without branches
                    s = 0.0
                    if m == hi - lo:  # (every sample valid: the same sum, no mask read)
                        for t in range(lo, hi):
                            s += xi[t, a]
                    else:
                        for t in range(lo, hi):
                            s += xi[t, a] if mi[t] else 0.0
                    out[r, j, a] = s / m
                if last < 0:  # windows before the first valid one hold it
                    for e in range(j):
                        out[r, e] = out[r, j]
                last = j
            elif last >= 0:
                out[r, j] = out[r, last]


def compiled_means(x, mask, rows, h: int, k: int):
    """:func:`diffgyro._window_stats.window_means` of a large batch: one read of each device's
    samples (``x`` with its channels last, a view)."""
    out = np.zeros((len(rows), k, x.shape[2]))
    full = _full(mask, rows)
    on_threads(len(rows), x.shape[1], lambda a, b: _means(x, mask, full[a:b], rows[a:b], int(h),
                                                         out[a:b]), "windows", THREAD_SAMPLES)
    return out


@njit(cache=True, nogil=True)
def _explained(stats, noise, valid, residual, rows, w, half_q, zh, limit):  # pragma: no cover
    r, k = valid.shape
    half = np.empty(min(k, limit), np.float32)
    for i in range(r):
        if not rows[i]:
            continue
        finite = True  # (a NaN or an infinity in a valid window keeps the recording's)
        for j in range(k):
            if not valid[i, j]:
                continue
            small = True  # (values this small sum to a finite number: no chain of adds)
            for p in range(2):
                for a in range(3):
                    small = small and abs(residual[i, j, p, a]) < 1e300
            if small:
                continue
            s = 0.0
            for p in range(2):
                for a in range(3):
                    s += residual[i, j, p, a]
            if not math.isfinite(s):
                finite = False
                break
        if not finite:
            continue
        span = 0
        for j in range(k):
            p0, p1, p2 = residual[i, j, 0, 0], residual[i, j, 0, 1], residual[i, j, 0, 2]
            q0, q1, q2 = residual[i, j, 1, 0], residual[i, j, 1, 1], residual[i, j, 1, 2]
            stats[i, j, 0, 0] = 0.5 * (p0 + q0)
            stats[i, j, 0, 1] = 0.5 * (p1 + q1)
            stats[i, j, 0, 2] = 0.5 * (p2 + q2)
            stats[i, j, 2, 0] = p0 - q0
            stats[i, j, 2, 1] = p1 - q1
            stats[i, j, 2, 2] = p2 - q2
            if valid[i, j]:
                span = j + 1
        m = min(span, limit)
        for a in range(3):
            u = 0
            for j in range(m):
                at = (j * span) // limit if span > limit else j
                if valid[i, at]:
                    half[u] = abs(stats[i, at, 2, a])
                    u += 1
            sigma = np.float64(noise[i, 0, a]) / math.sqrt(w)
            h = _quantile(half, u, half_q) / zh / 2.0
            noise[i, 1, a] = math.nan if math.isnan(sigma) or math.isnan(h) else max(sigma, h)


def compiled_explained(stats, noise, valid, residual, rows, w: int, quantiles, limit: int):
    """:func:`diffgyro._window_explain.explained` in one compiled loop over the windows (its
    numbers), into copies of ``stats`` and ``noise``."""
    stats, noise = stats.copy(), noise.copy()
    valid, rows = np.ascontiguousarray(valid, bool), np.ascontiguousarray(rows, bool)
    residual = np.ascontiguousarray(residual, np.float64)
    on_threads(len(rows), stats.shape[1] * w, lambda a, b: _explained(
        stats[a:b], noise[a:b], valid[a:b], residual[a:b], rows[a:b], int(w),
        float(quantiles[1]), float(quantiles[3]), int(limit)), "windows", THREAD_SAMPLES)
    return stats, noise


@njit(cache=True, nogil=True)
def _halves(stats, out):  # pragma: no cover - compiled
    for i in range(stats.shape[0]):
        for j in range(stats.shape[1]):
            for a in range(3):
                mean = np.float64(stats[i, j, 0, a])
                half = np.float64(np.float32(0.5) * stats[i, j, 2, a])
                out[i, 2 * j, a] = mean + half
                out[i, 2 * j + 1, a] = mean - half


def compiled_halves(stats):
    """The gyro's means over each half window (rows, 2 × windows, 3; float64) from the window
    statistics (rows, windows, 3, 3; float32): the window mean ± half the half-window
    difference, as :func:`diffgyro._window_explain.half_windows` forms them."""
    out = aligned_empty((stats.shape[0], 2 * stats.shape[1], 3), np.float64)  # (a Batch keeps it)
    _halves(stats, out)
    return out


__all__ = ["compiled_pass", "compiled_means", "compiled_explained", "compiled_halves"]
