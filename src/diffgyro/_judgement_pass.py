"""The motion check's judgement of a large batch from its window statistics (numba): the
rules of :mod:`diffgyro._motion_host` (numpy over a leading device axis, which says what
each step does), as one compiled loop over the devices, each in O(windows), on the host's
cores (chunks of devices on threads, one per core: the loop holds no GIL).

A device is judged window by window: its windows' thresholds, local noise and jumps, the
baseline of its window means (block medians, held over empty blocks, extrapolated past
its end, interpolated between blocks), its flags and the rule on runs, the second
baseline without its moving windows (only where some window left the first: at rest
nothing does), the accelerometer's jumps and tilt, the angle turned, and its numbers.
Elementwise steps are the host's in the same order and type (float32: the same bits);
sums over many windows accumulate in float64 in window order (numpy's pairwise order
differs), so the numbers formed from them match the host's to float32's last bits.

Compiled on first use and cached on disk (``cache=True``); imported only where the
window statistics were read by the compiled pass (:func:`diffgyro._window_stats.compiled`),
so a small batch's command never imports numba.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ._jit import on_threads
from ._motion_constants import (
    ACCEL_FLOOR,
    BLOCK_WINDOWS,
    EARTH_RATE,
    K_SIGMA,
    LOUDER_CAP,
    STRETCH_CHUNK,
    TILT_FLOOR,
)

#: The numbers per device, in the order the compiled loop writes them.
_NUMBERS = ("moving_fraction", "rate_peak", "rate_rms", "turn_peak", "tilt_peak", "rest_rate",
            "rest_noise", "threshold", "n_windows")
#: Windows (devices × windows) below which the judgement runs on the caller's thread: this
#: many take about 1.5 ms (some 50 ns a window), of which handing chunks to the pool's
#: threads and waiting for them would be a noticeable share.
THREAD_WINDOWS = 1 << 15


@njit(cache=True, nogil=True)
def _max(a, b):  # pragma: no cover - compiled
    """``np.maximum`` of two scalars: NaN where either is."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a >= b else b


@njit(cache=True, nogil=True)
def _min(a, b):  # pragma: no cover - compiled
    """``np.minimum`` of two scalars: NaN where either is."""
    if a != a:
        return a
    if b != b:
        return b
    return a if a <= b else b


@njit(cache=True, nogil=True)
def _flag(d0, d1, d2, v0, v1, v2, floor):  # pragma: no cover - compiled
    """Whether a deviation stands out of the noise its mean can have (float32 throughout)."""
    k = np.float32(K_SIGMA)
    r0 = d0 / _max(k * np.sqrt(v0), floor)
    r1 = d1 / _max(k * np.sqrt(v1), floor)
    r2 = d2 / _max(k * np.sqrt(v2), floor)
    return (r0 * r0 + r1 * r1) + r2 * r2 > 1.0


@njit(cache=True, nogil=True)
def _signal(st, count, valid, noise, w, floor, sigma, thr, var):  # pragma: no cover
    """One device's signal as the judgement reads it: its rest noise per axis (``sigma``),
    threshold (``thr``) and the variance each window mean has at rest (``var``); returns
    whether a window was too loud."""
    k = valid.shape[0]
    one, cap, inf = np.float32(1.0), np.float32(LOUDER_CAP), np.float32(np.inf)
    wf = np.float32(w)
    mean_noise = np.empty(3, np.float32)
    for a in range(3):
        s, m = noise[0, a], noise[1, a]
        sigma[a] = np.float32(0.0) if s != s else s
        mean_noise[a] = np.float32(0.0) if m != m else m
        thr[a] = _max(np.float32(K_SIGMA) * mean_noise[a], floor)
    loud = False
    for j in range(k):
        scale = wf / _max(count[j], one)
        for a in range(3):
            local = st[j, 1, a]
            louder = _min(_max(local / (sigma[a] if sigma[a] > 0 else inf), one), cap)
            v = mean_noise[a] * louder
            var[j, a] = v * v * scale
            loud = loud or (valid[j] and local > cap * sigma[a])
    return loud


@njit(cache=True, nogil=True)
def _jumps(st, valid, var, floor, jump):  # pragma: no cover - compiled
    """The jumps between neighbouring valid windows of one device's signal (``jump``): the
    change of their means stands out of the noise both can have."""
    jump[0] = False
    for j in range(1, valid.shape[0]):
        jump[j] = valid[j] and valid[j - 1] and _flag(
            st[j, 0, 0] - st[j - 1, 0, 0], st[j, 0, 1] - st[j - 1, 0, 1],
            st[j, 0, 2] - st[j - 1, 0, 2], var[j, 0] + var[j - 1, 0],
            var[j, 1] + var[j - 1, 1], var[j, 2] + var[j - 1, 2], floor)


@njit(cache=True, nogil=True)
def _block_median(st, use, valid, blk, b, med, buf):  # pragma: no cover - compiled
    """The median of block ``blk``'s windows in ``use`` (at most BLOCK_WINDOWS of them
    spread over the windows it holds) per axis into ``med[blk]`` (NaN where none), by the
    host's sorting network (the windows not in use as infinities: no branch per value);
    returns whether the block holds a valid window."""
    k = valid.shape[0]
    start = blk * b
    stop = min(start + b, k)
    span = 0
    for j in range(start, stop):
        if valid[j]:
            span = j - start + 1
    cols = min(b, BLOCK_WINDOWS)
    inf = np.float32(np.inf)
    n = 0
    for j in range(cols):
        pick = (j * span) // BLOCK_WINDOWS if b > BLOCK_WINDOWS and span > BLOCK_WINDOWS else j
        i = min(start + pick, k - 1)  # (a window past the end is not in use)
        ok = (j < span or b <= BLOCK_WINDOWS) and start + pick < k and use[i]
        n += ok
        for a in range(3):
            buf[j, a] = st[i, 0, a] if ok else inf
    for r in range(cols):  # odd-even transposition: cols rounds sort
        for j in range(r % 2, cols - 1, 2):
            for a in range(3):
                x, y = buf[j, a], buf[j + 1, a]
                buf[j, a], buf[j + 1, a] = min(x, y), max(x, y)
    h = np.float32(0.5) * np.float32(max(n, 1) - 1)
    lo = int(math.floor(h))
    hi = min(lo + 1, max(n - 1, 0))
    frac = h - np.float32(lo)
    for a in range(3):
        lo_v, hi_v = buf[lo, a], buf[hi, a]
        med[blk, a] = lo_v + (hi_v - lo_v) * frac if n else np.float32(np.nan)
    return span > 0


@njit(cache=True, nogil=True)
def _between(k, b, frac, left):  # pragma: no cover - compiled
    """Where each of ``k`` windows lies between block centres (the same for every device):
    the block ``left`` of it whose median it starts from (B − 1 in its block B's first
    half, B in the second, clipped) and how far towards the next one's (``frac``)."""
    kb = -(-k // b)
    half, bf = np.float32(0.5), np.float32(b)
    for i in range(k):
        pos = (np.float32(i) + half) / bf - half
        j = min(max(int(math.floor(pos)), 0), kb - 2)
        frac[i] = pos - np.float32(j)
        blk = i // b
        left[i] = min(max(blk if i % b >= b // 2 else blk - 1, 0), kb - 2)


@njit(cache=True, nogil=True)
def _baseline(st, use, valid, b, out, med, buf, frac, left):  # pragma: no cover - compiled
    """The baseline of a device's window means (``st[:, 0]``) into ``out``: the medians
    of its blocks (``med``: blocks × 3), held over blocks without windows in use,
    extrapolated past the last block with a valid window along the line through its last
    two, and linear between block centres (:func:`_between`)."""
    k = valid.shape[0]
    kb = med.shape[0]
    end = 0
    last = -1
    first = -1
    for blk in range(kb):
        if _block_median(st, use, valid, blk, b, med, buf):
            end = blk
        if med[blk, 0] == med[blk, 0]:
            last = blk
            first = blk if first < 0 else first
        elif last >= 0:
            med[blk, 0], med[blk, 1], med[blk, 2] = med[last, 0], med[last, 1], med[last, 2]
    if first > 0:  # blocks before the first with windows in use hold it
        for blk in range(first):
            med[blk, 0], med[blk, 1], med[blk, 2] = med[first, 0], med[first, 1], med[first, 2]
    prev = max(end - 1, 0)
    two = np.float32(2.0)
    l0 = two * med[end, 0] - med[prev, 0]
    l1 = two * med[end, 1] - med[prev, 1]
    l2 = two * med[end, 2] - med[prev, 2]
    for blk in range(end + 1, kb):
        med[blk, 0], med[blk, 1], med[blk, 2] = l0, l1, l2
    if kb == 1:
        for j in range(k):
            out[j, 0], out[j, 1], out[j, 2] = med[0, 0], med[0, 1], med[0, 2]
        return
    for i in range(k):
        jj, f = left[i], frac[i]
        for a in range(3):
            lo = med[jj, a]
            out[i, a] = lo + f * (med[jj + 1, a] - lo)


@njit(cache=True, nogil=True)
def _runs_with(flag, mark, out):  # pragma: no cover - compiled
    """``out``: ``flag`` with every run of True that holds no ``mark`` cleared."""
    k = flag.shape[0]
    j = 0
    while j < k:
        if not flag[j]:
            out[j] = False
            j += 1
            continue
        stop = j
        keep = False
        while stop < k and flag[stop]:
            keep = keep or mark[stop]
            stop += 1
        for i in range(j, stop):
            out[i] = keep
        j = stop


@njit(cache=True, nogil=True)
def _deviations(st, base, var, valid, floor, dev, flags, replace):  # pragma: no cover
    """Each window's deviation from ``base`` into ``dev`` (``replace``: only where it is a
    number, else a NaN stands as 0) and its flag; returns whether any window is flagged."""
    anyone = False
    for j in range(valid.shape[0]):
        for a in range(3):
            d = st[j, 0, a] - base[j, a]
            if d == d:
                dev[j, a] = d
            elif not replace:
                dev[j, a] = np.float32(0.0)
        flags[j] = valid[j] and _flag(dev[j, 0], dev[j, 1], dev[j, 2], var[j, 0], var[j, 1],
                                      var[j, 2], floor)
        anyone = anyone or flags[j]
    return anyone


@njit(cache=True, nogil=True)
def _tilted(st, valid, moving, thr, flag):  # pragma: no cover - compiled
    """Windows whose specific force leaves its chunk's mean by more than the tilt floor, in
    chunks of STRETCH_CHUNK windows where nothing moved, into ``flag``; returns the largest
    such tilt (rad)."""
    k = valid.shape[0]
    c = STRETCH_CHUNK
    floor = _max(np.float32(TILT_FLOOR), np.sqrt((thr[0] * thr[0] + thr[2] * thr[2])
                                                 + thr[1] * thr[1]))
    tilt = np.float32(0.0)
    for start in range(0, k, c):
        stop = min(start + c, k)
        still = True
        count = 0
        s0 = s1 = s2 = 0.0
        for j in range(start, stop):
            still = still and not moving[j]
            if valid[j] and not moving[j]:
                count += 1
                s0 += st[j, 0, 0]
                s1 += st[j, 0, 1]
                s2 += st[j, 0, 2]
        n = np.float32(max(count, 1))
        m0, m1, m2 = np.float32(s0) / n, np.float32(s1) / n, np.float32(s2) / n
        g = _max(np.sqrt((m0 * m0 + m1 * m1) + m2 * m2), np.float32(1e-9))
        for j in range(start, stop):
            d0, d1, d2 = st[j, 0, 0] - m0, st[j, 0, 1] - m1, st[j, 0, 2] - m2
            off = np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
            flag[j] = (valid[j] and not moving[j] and still and count >= c // 2
                       and off > floor)
            if flag[j]:
                tilt = _max(tilt, np.arcsin(_min(off / g, np.float32(1.0))))
    return tilt


@njit(cache=True, nogil=True)
def _turned(moving, dev):  # pragma: no cover - compiled
    """The largest angle turned within one run of moving windows (rate × windows): the
    deviations summed (float64, from the recording's start) less their sum before the run."""
    s0 = s1 = s2 = 0.0
    z = np.float32(0.0)
    b0 = b1 = b2 = z
    peak = z
    for j in range(moving.shape[0]):
        if moving[j]:
            s0 += dev[j, 0]
            s1 += dev[j, 1]
            s2 += dev[j, 2]
            t0, t1, t2 = np.float32(s0) - b0, np.float32(s1) - b1, np.float32(s2) - b2
            peak = _max(peak, np.sqrt((t0 * t0 + t1 * t1) + t2 * t2))
        else:
            b0, b1, b2 = np.float32(s0), np.float32(s1), np.float32(s2)
    return peak


@njit(cache=True, nogil=True)
def _numbers(st, count, valid, moving, dev, sigma, thr, turn, tilt, near, out):  # pragma: no cover
    """One device's numbers (:data:`_NUMBERS`) into ``out`` and its windows not at rest
    (moving, or next to a moving one) into ``near``."""
    k = valid.shape[0]
    n_mov = n_still = n_valid = 0
    peak = np.float32(0.0)
    sq = moved = total = h0 = h1 = h2 = 0.0
    for j in range(k):
        near[j] = moving[j] or (j + 1 < k and moving[j + 1]) or (j > 0 and moving[j - 1])
        n_valid += valid[j]
        total += count[j]
        if moving[j]:
            d0, d1, d2 = dev[j, 0], dev[j, 1], dev[j, 2]
            rate = np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
            n_mov += 1
            peak = _max(peak, rate)
            sq += rate * rate
            moved += count[j]
        elif valid[j]:
            n_still += 1
            h0 += st[j, 0, 0]
            h1 += st[j, 0, 1]
            h2 += st[j, 0, 2]
    ns = np.float32(max(n_still, 1))
    m0, m1, m2 = np.float32(h0) / ns, np.float32(h1) / ns, np.float32(h2) / ns
    third = np.float32(1 / 3)
    nan = np.float32(np.nan)
    some = n_valid > 0
    out[0] = np.float32(moved) / _max(np.float32(total), np.float32(1.0)) if some else nan
    out[1] = peak if some else nan
    out[2] = np.sqrt(np.float32(sq) / np.float32(max(n_mov, 1))) if some else nan
    out[3] = turn if some else nan
    out[4] = tilt if some else nan
    out[5] = np.sqrt((m0 * m0 + m2 * m2) + m1 * m1) if some else nan
    out[6] = np.sqrt(((sigma[0] * sigma[0] + sigma[2] * sigma[2]) + sigma[1] * sigma[1])
                     * third) if some else nan
    out[7] = np.sqrt(((thr[0] * thr[0] + thr[2] * thr[2]) + thr[1] * thr[1]) * third) \
        if some else nan
    out[8] = np.float32(n_valid)


@njit(cache=True, nogil=True)
def _judge(gs, gc, gv, gn, acs, acc, acv, acn, w, b, thr, athr, moving, near, loud,
           out):  # pragma: no cover - compiled
    """The judgement of devices (the leading axis) from their window statistics (gyro;
    accelerometer where ``acs`` holds rows), into the outputs."""
    k = gv.shape[1]
    kb = -(-k // b)
    med = np.empty((kb, 3), np.float32)
    buf = np.empty((min(b, BLOCK_WINDOWS), 3), np.float32)
    frac, left = np.empty(k, np.float32), np.empty(k, np.int64)
    _between(k, b, frac, left)
    dev = np.empty((k, 3), np.float32)
    var = np.empty((k, 3), np.float32)
    base = np.empty((k, 3), np.float32)
    avar = np.empty((k, 3), np.float32)
    flags, mark, use = np.empty(k, np.bool_), np.empty(k, np.bool_), np.empty(k, np.bool_)
    jump = np.empty(k, np.bool_)
    tflag = np.empty(k, np.bool_)
    sigma = np.empty(3, np.float32)
    asigma = np.empty(3, np.float32)
    gfloor, afloor = np.float32(2.0 * EARTH_RATE), np.float32(ACCEL_FLOOR)
    for r in range(gv.shape[0]):
        loud[r] = _signal(gs[r], gc[r], gv[r], gn[r], w, gfloor, sigma, thr[r], var)
        # the first pass; where some window left its baseline, the rule on runs (a run
        # moves where it starts or holds a jump) and the baseline without the moving windows
        _baseline(gs[r], gv[r], gv[r], b, base, med, buf, frac, left)
        if _deviations(gs[r], base, var, gv[r], gfloor, dev, flags, False):
            _jumps(gs[r], gv[r], var, gfloor, jump)  # (read by the rule on runs alone)
            for j in range(k):
                mark[j] = jump[j] or (j + 1 < k and jump[j + 1])
            _runs_with(flags, mark, moving[r])
            for j in range(k):
                use[j] = gv[r, j] and not moving[r, j]
            _baseline(gs[r], use, gv[r], b, base, med, buf, frac, left)
            _deviations(gs[r], base, var, gv[r], gfloor, dev, flags, True)
            _runs_with(flags, mark, moving[r])
        tilt = np.float32(0.0)
        if acs.shape[0]:
            _signal(acs[r], acc[r], acv[r], acn[r], w, afloor, asigma, athr[r], avar)
            _jumps(acs[r], acv[r], avar, afloor, jump)
            for j in range(k):
                moving[r, j] = moving[r, j] or jump[j]
            tilt = _tilted(acs[r], gv[r], moving[r], athr[r], tflag)
            for j in range(k):
                moving[r, j] = moving[r, j] or tflag[j]
        turn = _turned(moving[r], dev)
        _numbers(gs[r], gc[r], gv[r], moving[r], dev, sigma, thr[r], turn, tilt, near[r], out[r])


def judge(gyro, accel, w: int, b: int) -> dict:
    """The judgement of a group of devices from their window statistics (gyro, and
    accelerometer or None; :mod:`diffgyro._window_stats`, float32): the outputs of
    :func:`diffgyro._motion_host.judge` (the same keys, types and shapes), by one compiled
    loop over the devices, chunks of them side by side on threads.

    **Arguments:**

    - ``gyro``: the gyro's window statistics (means and local noise, counts, validity,
      rest noise), devices first.
    - ``accel``: the accelerometer's, or None.
    - ``w``, ``b``: samples per window, windows per baseline block.
    """
    gs, gc, gv, gn = _inputs(gyro)
    rows, k = gv.shape
    has_accel = accel is not None
    acs, acc, acv, acn = _inputs(accel) if has_accel else (
        np.zeros((0, k, 3, 3), np.float32), np.zeros((0, k), np.float32),
        np.zeros((0, k), bool), np.zeros((0, 2, 3), np.float32))
    thr, athr = np.zeros((rows, 3), np.float32), np.zeros((rows, 3), np.float32)
    moving, near = np.zeros((rows, k), bool), np.zeros((rows, k), bool)
    loud, out = np.zeros(rows, bool), np.zeros((rows, len(_NUMBERS)), np.float32)

    def run(a: int, z: int) -> None:
        part = slice(a, z)
        accel_part = part if has_accel else slice(0, 0)
        _judge(gs[part], gc[part], gv[part], gn[part], acs[accel_part], acc[accel_part],
               acv[accel_part], acn[accel_part], int(w), int(b), thr[part], athr[part],
               moving[part], near[part], loud[part], out[part])

    on_threads(rows, k, run, "judgement", THREAD_WINDOWS)
    result = dict(window_rate=np.asarray(gyro[0])[:, :, 0], window_valid=np.asarray(gyro[2]),
                  threshold_axes=thr)
    if has_accel:
        result |= dict(window_accel=np.asarray(accel[0])[:, :, 0], accel_threshold=athr)
    numbers = {key: out[:, i].copy() for i, key in enumerate(_NUMBERS)}
    return result | numbers | dict(window_near=near, loud=loud, window_moving=moving)


def _inputs(stats) -> tuple:
    """Window statistics as the compiled loop reads them (contiguous, float32, bool)."""
    wins, count, valid, noise = stats
    return (np.ascontiguousarray(wins, np.float32), np.ascontiguousarray(count, np.float32),
            np.ascontiguousarray(valid, bool), np.ascontiguousarray(noise, np.float32))


__all__ = ["judge", "THREAD_WINDOWS"]
