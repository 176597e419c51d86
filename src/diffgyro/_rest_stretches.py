"""Where a recording moved, the stretches of it that are rest (:func:`rest_stretches`): a
device held by hand, turned slowly or spinning steadily between its moves is not at rest.
On the host, from the windows of the devices that moved (numpy), once per device.
"""

from __future__ import annotations

import math

import numpy as np

from ._motion_constants import (
    BIAS_SLEW,
    BLOCK_S,
    BLOCK_WINDOWS,
    EARTH_RATE,
    MAX_BIAS,
    MIN_STRETCH,
    REST_SHARE,
    STRETCH_CHUNK,
    TILT_FLOOR,
)


def rest_stretches(rate, moving, valid, thr, window_s: float, accel=None, accel_thr=None):
    """The stretches of one device's recording that are rest, where it moved (its windows:
    mean rate (k, 3), moving, valid, the threshold per axis; the accelerometer's window
    means and threshold where read).

    Between its moves a device held by hand or turned slowly is not at rest, and neither
    is one that spins steadily:

    * at rest, gravity holds still: a window whose specific force leaves the mean of
      its stretch (over :data:`STRETCH_CHUNK` windows) by more than :data:`TILT_FLOOR`
      (a tilt of half a degree) or the accelerometer's threshold moved;
    * a stretch shorter than :data:`MIN_STRETCH` windows between moves is no rest;
    * gravity that turned across a move (the stretches either side at rest in poses
      apart by more than :data:`TILT_FLOOR`) shows the move turned the device: a tilt;
    * a bias does not step while the device turns: it drifts by at most
      :data:`BIAS_SLEW` (and the window noise, the threshold). Stretches that agree, end
      to start, are one level. The rest is the level the device held longest, or, of the
      levels held at least :data:`REST_SHARE` as long, the one nearest to zero rate (a
      bias is small beside a spin), among the levels a bias can have (:data:`MAX_BIAS`);
      the other levels spin.

    **Arguments:**

    - ``rate``, ``moving``, ``valid``, ``thr``: the device's window means (k, 3), moving
      and valid windows (k,), and its threshold per axis, rad/s.
    - ``window_s``: a window's length, s.
    - ``accel``, ``accel_thr``: the accelerometer's window means and threshold, where read.

    **Returns:** None where the check's own windows stand; else the windows moving, the
    largest rate of a spin against the rest's, the largest angle one turned and the
    largest tilt of gravity (rad)."""
    given = moving
    moving = moving.copy()
    k = moving.size
    thr = np.maximum(np.asarray(thr, float), 2.0 * EARTH_RATE)

    def stretches():
        static = valid & ~moving
        edges = np.flatnonzero(np.diff(np.r_[0, static.astype(np.int8), 0]))
        return list(zip(edges[::2], edges[1::2]))

    runs = stretches()
    tilt = 0.0
    if accel is not None:
        floor = max(TILT_FLOOR, float(np.linalg.norm(accel_thr)))
        g = max(float(np.median(np.linalg.norm(accel[valid], axis=1))), 1e-9) if valid.any() else 1.0
        # chunks of STRETCH_CHUNK windows from each stretch's start (a short last chunk
        # joins its neighbour), their means by one reduction over the stretches' windows
        chunks = []
        for start, end in runs:
            cut = list(range(start, end, STRETCH_CHUNK))
            if len(cut) > 1 and end - cut[-1] < STRETCH_CHUNK // 2:
                cut.pop()
            chunks += list(zip(cut, cut[1:] + [end]))
        if chunks:
            starts, ends = (np.asarray(x) for x in zip(*chunks))
            idx = np.concatenate([np.arange(a, b) for a, b in zip(starts, ends)])
            size = ends - starts
            mean = np.add.reduceat(accel[idx], np.r_[0, np.cumsum(size)[:-1]], axis=0) / size[:, None]
            off = np.linalg.norm(accel[idx] - np.repeat(mean, size, axis=0), axis=1)
            over = off > floor
            moving[idx[over]] = True
            if over.any():
                tilt = max(tilt, math.asin(min(float(off[over].max()) / g, 1.0)))
    runs = stretches()
    for start, end in runs:
        if end - start < MIN_STRETCH and (start > 0 or end < k):
            moving[start:end] = True
    runs = [r for r in stretches() if r[1] - r[0] >= MIN_STRETCH]
    if accel is not None:  # gravity turned across a move: the gyro's run was a turn
        for (a0, a1), (b0, b1) in zip(runs, runs[1:]):
            before = np.median(accel[max(a0, a1 - BLOCK_WINDOWS):a1], axis=0)
            after = np.median(accel[b0:min(b1, b0 + BLOCK_WINDOWS)], axis=0)
            if np.linalg.norm(after - before) > floor:
                cos = before @ after / max(np.linalg.norm(before) * np.linalg.norm(after), 1e-12)
                tilt = max(tilt, math.acos(min(max(cos, -1.0), 1.0)))
    clusters = _levels(rate, runs, thr, window_s)
    if len(clusters) < 2:
        return None if np.array_equal(moving, given) and not tilt else (moving, 0.0, 0.0, tilt)
    # a rate beyond any gyro's bias is no rest (unless every level is: an output in counts
    # with its offset, or a rate about a logged reference)
    small = [c for c in clusters if np.linalg.norm(c["level"]) <= MAX_BIAS] or clusters
    most = max(c["windows"] for c in small)
    rest = min((c for c in small if c["windows"] >= REST_SHARE * most),
               key=lambda c: float(np.linalg.norm(c["level"])))
    peak = turn = 0.0
    for c in clusters:
        if np.sqrt(np.sum(((c["level"] - rest["level"]) / thr) ** 2)) <= 1.0:
            continue  # at the rest's level (a level split only by the drift allowed)
        off = float(np.linalg.norm(c["level"] - rest["level"]))
        for a, b in c["runs"]:
            moving[a:b] = True
            peak, turn = max(peak, off), max(turn, off * (b - a) * window_s)
    return moving, peak, turn, tilt


def _levels(rate, runs, thr, window_s: float) -> list[dict]:
    """The stretches ``runs`` grouped by the rate they hold: a stretch joins the level
    whose last stretch ends at its rate (within the noise of medians of a few windows and
    :data:`BIAS_SLEW` over the gap), else starts one. Each level: its stretches, windows
    and median rate."""
    clusters: list[dict] = []
    for start, end in runs:
        span = min(BLOCK_WINDOWS, end - start)
        head = np.median(rate[start:start + span], axis=0)
        best, dist = None, 1.0
        for c in clusters:
            gap = min((start - c["end"] + span) * window_s, BLOCK_S)
            # medians of a few windows each: their difference's noise is below a window's
            tol = thr * min(1.0, 1.25 * math.sqrt(2.0 / min(span, c["span"]))) + BIAS_SLEW * gap
            z = float(np.sqrt(np.sum(((head - c["tail"]) / tol) ** 2)))
            if z <= dist:
                best, dist = c, z
        if best is None:
            best = {"runs": [], "windows": 0}
            clusters.append(best)
        best["runs"].append((start, end))
        best["windows"] += end - start
        best["end"], best["span"] = end, span
        best["tail"] = np.median(rate[end - span:end], axis=0)
    for c in clusters:
        c["level"] = np.median(np.concatenate([rate[a:b] for a, b in c["runs"]]), axis=0)
    return clusters


__all__ = ["rest_stretches"]
