"""The motion check's judgement of a group of devices from their window statistics
(:mod:`diffgyro._window_stats`) on the host in numpy, written over a leading axis of
devices: the baseline of the window means, the windows that leave it, the rule on runs,
the angle turned and gravity's tilt, and the numbers the host reads
(:func:`diffgyro.motion.motion_check` says what they mean). A small batch's windows number
a few thousand, which numpy judges in milliseconds with no compiled code to load; a large
batch is judged by the same rules in one compiled loop over its devices
(:mod:`diffgyro._judgement_pass`, numba), which this module's numbers check: the same
flags and windows (elementwise steps in the same order, IEEE float32 arithmetic: the same
bits), and the numbers formed from sums over many windows (accumulated in float64, in
numpy's order here and window order there) to float32's last bits.
"""

from __future__ import annotations

import numpy as np

from ._motion_constants import (
    ACCEL_FLOOR,
    BLOCK_WINDOWS,
    EARTH_RATE,
    K_SIGMA,
    LOUDER_CAP,
    STRETCH_CHUNK,
    TILT_FLOOR,
)

F32 = np.float32


def _sum3(x):
    """The sum over the last axis of three components (explicit adds, in order)."""
    return (x[..., 0] + x[..., 1]) + x[..., 2]


def _reduce3(x):
    """The sum over the last axis of three components, the first and last added first (the
    order of the rest rate, the rest noise and the threshold over their axes)."""
    return (x[..., 0] + x[..., 2]) + x[..., 1]


def _norm(x):
    return np.sqrt(_sum3(x * x))


def _sum(x, axis: int):
    """A float32 sum along ``axis`` of many terms, accumulated in float64 (numpy's pairwise
    order; the compiled loop's is the windows': the two agree to float32's last bits)."""
    return np.sum(x, axis=axis, dtype=np.float64).astype(x.dtype)


def _shift(x, fill, back: bool = False):
    """``x`` along axis 1 one step later (``back``: earlier), ``fill`` at the open end."""
    pad = np.full_like(x[:, :1], fill)
    return np.concatenate([x[:, 1:], pad], 1) if back else np.concatenate([pad, x[:, :-1]], 1)


def _cummax(x):
    return np.maximum.accumulate(x, axis=1)


def _cummin_back(x):
    return np.minimum.accumulate(x[:, ::-1], axis=1)[:, ::-1]


def _median_few(x, valid):
    """The median (linear between order statistics) of the ``valid`` entries of ``x`` along
    axis 2 (at most :data:`BLOCK_WINDOWS`), NaN where none: a sorting network of
    elementwise min/max."""
    n = np.sum(valid, axis=2, keepdims=True)
    h = (0.5 * (np.maximum(n, 1) - 1).astype(x.dtype)).astype(x.dtype)
    lo = np.floor(h).astype(np.int32)
    hi = np.minimum(lo + 1, np.maximum(n - 1, 0)).astype(np.int32)
    col = list(np.moveaxis(np.where(valid, x, np.inf).astype(x.dtype), 2, 0))
    for r in range(len(col)):  # odd-even transposition
        for j in range(r % 2, len(col) - 1, 2):
            col[j], col[j + 1] = np.minimum(col[j], col[j + 1]), np.maximum(col[j], col[j + 1])
    a = np.zeros(lo.shape[:2] + x.shape[3:], x.dtype)
    b = np.zeros_like(a)
    for j, v in enumerate(col):
        a = a + np.where(lo[:, :, 0] == j, v, x.dtype.type(0))
        b = b + np.where(hi[:, :, 0] == j, v, x.dtype.type(0))
    out = a + (b - a) * (h[:, :, 0] - lo[:, :, 0].astype(x.dtype))
    return np.where(n[:, :, 0] > 0, out, x.dtype.type(np.nan))


def _spread(has, limit: int):
    """At most ``limit`` window indices spread evenly from the first window to the last one
    ``has`` (along its last axis): those the windows hold, not the padded batch's; and
    which of them lie in that span (all, unless it holds fewer windows)."""
    k = has.shape[-1]
    span = np.max(np.where(has, np.arange(k), -1), axis=-1, keepdims=True) + 1
    j = np.arange(limit)
    return np.where(span > limit, (j * span) // limit, j), j < span


def _baseline(mean, use, valid, b: int):
    """Slow baseline of the window means (devices, windows, 3): the median over blocks of
    ``b`` windows of the windows in ``use`` (of the ``valid`` ones; at most
    :data:`BLOCK_WINDOWS` of them spread evenly over the block). A block without windows
    in use (all moving) holds the last block before it that has some (the first such block
    before any). Past the recording's end (padding) the blocks follow the line through its
    last two, so that its last block's second half is extrapolated as without the padding
    (a device's baseline does not depend on the length of the batch it is checked in).
    Between block centres it is linear, and extrapolated from the nearest two at the ends
    (a warm-up's drift is fastest in the first half block): window i of block B lies
    between the centres of blocks B − 1 (first half) or B (second half), clipped."""
    d, k, c = mean.shape
    kb = -(-k // b)
    pad = kb * b - k
    vals = np.concatenate([mean, np.zeros((d, pad, c), mean.dtype)], 1).reshape(d, kb, b, c)
    ok = np.concatenate([use, np.zeros((d, pad), bool)], 1).reshape(d, kb, b)
    padded = np.concatenate([valid, np.zeros((d, pad), bool)], 1).reshape(d, kb, b)
    if b > BLOCK_WINDOWS:
        pick, inside = _spread(padded, BLOCK_WINDOWS)
        vals = np.take_along_axis(vals, pick[..., None], axis=2)
        ok = np.take_along_axis(ok, pick, axis=2) & inside
    med = _median_few(vals, np.broadcast_to(ok[..., None], vals.shape))  # (d, kb, c)
    has = ~np.isnan(med[:, :, 0])
    idx = np.arange(kb)
    last = _cummax(np.where(has, idx, -1))
    first = np.argmax(has, axis=1)
    med = np.take_along_axis(med, np.where(last >= 0, last, first[:, None])[..., None], axis=1)
    end = np.max(np.where(np.any(padded, axis=2), idx, 0), axis=1)
    at = lambda i: np.take_along_axis(med, i[:, None, None], axis=1)[:, 0]  # noqa: E731
    line = F32(2.0) * at(end) - at(np.maximum(end - 1, 0))
    med = np.where((idx[None, :] > end[:, None])[..., None], line[:, None, :], med)
    if kb == 1:
        return np.broadcast_to(med, mean.shape)
    pos = (np.arange(k).astype(F32) + F32(0.5)) / F32(b) - F32(0.5)
    j = np.clip(np.floor(pos).astype(np.int32), 0, kb - 2)
    frac = (pos - j.astype(F32))[:, None]
    blocks = np.arange(kb)
    second = (np.arange(b) >= b // 2)[None, None, :, None]

    def spread(jb_first, jb_second):
        v = np.where(second, med[:, jb_second][:, :, None, :], med[:, jb_first][:, :, None, :])
        return v.reshape(d, kb * b, c)[:, :k]

    first_j, second_j = np.clip(blocks - 1, 0, kb - 2), np.clip(blocks, 0, kb - 2)
    lo, hi = spread(first_j, second_j), spread(first_j + 1, second_j + 1)
    return lo + frac * (hi - lo)


def _run_start(flag):
    """Per window, the index of the last window at or before it that is not ``flag`` (−1
    where none): the window before the run of ``flag`` it belongs to."""
    return _cummax(np.where(flag, -1, np.arange(flag.shape[1])))


def _runs_with(flag, mark):
    """``flag`` with every run of True that holds no ``mark`` cleared (running maxima
    forwards and minima backwards)."""
    k = flag.shape[1]
    idx = np.arange(k)
    ahead = _cummax(np.where(flag & mark, idx, -1)) > _run_start(flag)
    end = _cummin_back(np.where(flag, k, idx))
    behind = _cummin_back(np.where(flag & mark, idx, k)) < end
    return flag & (ahead | behind)


def _flag(dev, var, ok, floor: float):
    """Windows whose deviation ``dev`` stands out of the noise ``var`` its mean can have."""
    thr = np.maximum(F32(K_SIGMA) * np.sqrt(var), F32(floor))
    r = dev / thr
    return (_sum3(r * r) > 1.0) & ok


def _windows(stats, w: int, floor: float) -> dict:
    """A signal's windows as the judgement reads them: means and validity, the rest noise
    and threshold per axis, the variance a window mean has at rest (raised by its own
    noise: vibration raises the local noise, and with it what a window mean may scatter,
    but at most :data:`LOUDER_CAP` times, so that a window cannot hide a turn), the jumps
    between neighbouring windows, whether a window was louder than the cap allows
    (shaken or knocked, though its mean may not show it), and the floor."""
    wins, c, valid, noise = (np.asarray(x) for x in stats)
    mean, local = wins[:, :, 0], wins[:, :, 1]
    sigma = np.where(np.isnan(noise[:, 0]), F32(0), noise[:, 0])
    mean_noise = np.where(np.isnan(noise[:, 1]), F32(0), noise[:, 1])
    thr0 = np.maximum(F32(K_SIGMA) * mean_noise, F32(floor))
    louder = np.clip(local / np.where(sigma > 0, sigma, F32(np.inf))[:, None, :], F32(1),
                     F32(LOUDER_CAP))
    var = (mean_noise[:, None, :] * louder) ** 2 * (F32(w) / np.maximum(c, F32(1)))[..., None]
    ok = valid & _shift(valid, False)
    prev = np.concatenate([mean[:, :1], mean[:, :-1]], 1)
    var_prev = np.concatenate([var[:, :1], var[:, :-1]], 1)
    jump = _flag(mean - prev, var + var_prev, ok, floor)  # a change between neighbours
    with np.errstate(invalid="ignore"):
        loud = np.any(valid[..., None] & (local > F32(LOUDER_CAP) * sigma[:, None, :]), axis=(1, 2))
    return dict(mean=mean, valid=valid, sigma=sigma, threshold=thr0, var=var, jump=jump,
                loud=loud, floor=floor)


def _moving(win: dict, b: int):
    """The moving windows and each window's deviation from the baseline: the first pass
    (the baseline of all valid windows), and where some window left it, the rule on runs
    (a run of such windows is motion when it starts or holds a jump: a turn starts within
    a window or two, thermal drift creeps) and then again with the baseline of the windows
    the first pass left static (where it left none, its own baseline stands)."""
    mean, valid, var, floor = win["mean"], win["valid"], win["var"], win["floor"]
    dev = mean - _baseline(mean, valid, valid, b)
    dev = np.where(np.isnan(dev), F32(0), dev)
    flags = _flag(dev, var, valid, floor)
    if not flags.any():  # (a device without flags: no move, the same deviations)
        return np.zeros_like(flags), dev
    jump = win["jump"] | _shift(win["jump"], False, back=True)
    moving = _runs_with(flags, jump)
    again = mean - _baseline(mean, valid & ~moving, valid, b)
    dev = np.where(np.isnan(again), dev, again)
    return _runs_with(_flag(dev, var, valid, floor), jump), dev


def _turned(moving, dev):
    """The largest angle turned within one run of moving windows (in window-mean rate ×
    windows; the host scales it by the window's length): the rate less the baseline,
    summed from the run's start."""
    turned = np.cumsum(np.where(moving[..., None], dev, F32(0)), axis=1, dtype=np.float64).astype(F32)
    before = _run_start(moving)
    start = np.take_along_axis(turned, np.maximum(before, 0)[..., None], axis=1)
    turned = turned - np.where(before[..., None] >= 0, start, F32(0))
    return np.max(np.where(moving, _norm(turned), F32(0)), axis=1, initial=F32(0))


def _tilted(accel, valid, moving, thr):
    """Windows whose specific force leaves the mean of its chunk of :data:`STRETCH_CHUNK`
    windows by more than a tilt of :data:`TILT_FLOOR` (or the accelerometer's threshold),
    in chunks where nothing else moved (a chunk with a move in it is left to
    :mod:`diffgyro._rest_stretches`, which splits it there), and the largest such tilt (rad)."""
    d, k, _ = accel.shape
    c = STRETCH_CHUNK
    kc = -(-k // c)
    pad = kc * c - k
    a = np.concatenate([accel, np.zeros((d, pad, 3), accel.dtype)], 1).reshape(d, kc, c, 3)
    use = np.concatenate([valid & ~moving, np.zeros((d, pad), bool)], 1).reshape(d, kc, c)
    still = ~np.any(np.concatenate([moving, np.zeros((d, pad), bool)], 1).reshape(d, kc, c), axis=2)
    count = np.sum(use, axis=2)
    mean = _sum(np.where(use[..., None], a, F32(0)), 2) / np.maximum(count, 1).astype(F32)[..., None]
    off = _norm(a - mean[:, :, None, :])
    floor = np.maximum(F32(TILT_FLOOR), np.sqrt(_reduce3(thr * thr)))
    flag = use & (still & (count >= c // 2))[..., None] & (off > floor[:, None, None])
    g = np.maximum(_norm(mean), F32(1e-9))[..., None]
    tilt = np.max(np.where(flag, np.arcsin(np.minimum(off / g, F32(1))), F32(0)).reshape(d, -1),
                  axis=1, initial=F32(0))
    return flag.reshape(d, -1)[:, :k], tilt


def _numbers(win: dict, moving, dev, turn, tilt, count) -> dict:
    """The devices' numbers (:data:`~diffgyro._motion_result.NUMBERS`, but the resolution
    the host forms) and their windows not at rest (moving, or next to a moving one: the
    transitions)."""
    mean, valid = win["mean"], win["valid"]
    rate = _norm(dev)
    n_mov = np.sum(moving, axis=1)
    peak = np.max(np.where(moving, rate, F32(0)), axis=1, initial=F32(0))
    rms = np.sqrt(_sum(np.where(moving, rate * rate, F32(0)), 1) / np.maximum(n_mov, 1).astype(F32))
    near = moving | _shift(moving, False, back=True) | _shift(moving, False)
    still = valid & ~moving
    held = _sum(np.where(still[..., None], mean, F32(0)), 1) \
        / np.maximum(np.sum(still, axis=1), 1).astype(F32)[:, None]
    rest_rate = np.sqrt(_reduce3(held * held))
    some = np.any(valid, axis=1)
    frac = _sum(np.where(moving, count, F32(0)), 1) / np.maximum(_sum(count, 1), F32(1))
    nan = F32(np.nan)
    # (the mean of three: their sum times 1/3)
    root_mean = lambda x: np.sqrt(_reduce3(x * x) * F32(1 / 3))  # noqa: E731
    return dict(moving_fraction=np.where(some, frac, nan), rate_peak=np.where(some, peak, nan),
                rate_rms=np.where(some, rms, nan), turn_peak=np.where(some, turn, nan),
                tilt_peak=np.where(some, tilt, nan), rest_rate=np.where(some, rest_rate, nan),
                rest_noise=np.where(some, root_mean(win["sigma"]), nan),
                threshold=np.where(some, root_mean(win["threshold"]), nan),
                n_windows=np.sum(valid, axis=1).astype(F32), window_near=near, loud=win["loud"])


def judge(gyro, accel, w: int, b: int) -> dict:
    """The judgement of a (small) group of devices from their window statistics (gyro, and
    accelerometer or None; :mod:`diffgyro._window_stats`, float32): per device the
    numbers, and per window the flags and means the host reads, as numpy arrays.

    **Arguments:**

    - ``gyro``: the gyro's window statistics (means and local noise, counts, validity,
      rest noise), devices first.
    - ``accel``: the accelerometer's, or None.
    - ``w``, ``b``: samples per window, windows per baseline block.
    """
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        win = _windows(gyro, w, 2.0 * EARTH_RATE)
        moving, dev = _moving(win, b)
        out = dict(window_rate=win["mean"], window_valid=win["valid"],
                   threshold_axes=win["threshold"])
        tilt = np.zeros(moving.shape[:1], F32)
        if accel is not None:
            acc = _windows(accel, w, ACCEL_FLOOR)
            moving = moving | acc["jump"]
            tilted, tilt = _tilted(acc["mean"], win["valid"], moving, acc["threshold"])
            moving = moving | tilted
            out |= dict(window_accel=acc["mean"], accel_threshold=acc["threshold"])
        turn = _turned(moving, dev) if moving.any() else np.zeros(moving.shape[:1], F32)
        count = np.asarray(gyro[1])
        return out | _numbers(win, moving, dev, turn, tilt, count) | dict(window_moving=moving)


__all__ = ["judge"]
