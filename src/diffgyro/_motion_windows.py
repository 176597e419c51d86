"""The motion check's compiled judgement of a group of devices from their window statistics
(:mod:`diffgyro._window_stats`): the baseline of the window means, the windows that leave
it, the rule on runs, the angle turned and gravity's tilt, and the numbers the host reads
(:func:`diffgyro.motion.motion_check` says what they mean). JAX, compiled once per shape
and window sizes: a large batch is judged as at rest vmapped over all its devices, then
again, chunk by chunk of :data:`CHECK_CHUNK` devices, where some window moved (the rule on
runs). A small batch is judged by the same rules on the host
(:mod:`diffgyro._motion_host`).
"""

from __future__ import annotations

import functools
import operator
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float

from ._jit import filter_jit
from ._motion_constants import (
    ACCEL_FLOOR,
    BLOCK_WINDOWS,
    CHECK_CHUNK,
    EARTH_RATE,
    K_SIGMA,
    LOUDER_CAP,
    PAD_SAMPLES,
    STRETCH_CHUNK,
    TILT_FLOOR,
)
from ._motion_host import HostCheck
from .data import device_bucket


def _sum(x, axis: int):
    """``x`` summed over a short ``axis`` (a vector's three components) as explicit adds.
    XLA's CPU code for a reduction over a few minor elements runs many times slower than
    the elementwise adds (the rule's flag of 10⁶ windows: 7 ms against 0.5 ms)."""
    parts = [jax.lax.index_in_dim(x, i, axis, keepdims=False) for i in range(x.shape[axis])]
    return functools.reduce(operator.add, parts)


def _norm(x, axis: int = -1):
    """The Euclidean norm over ``axis`` (a vector's components)."""
    return jnp.sqrt(_sum(x * x, axis))


def _masked_quantile(x, valid, q: float, axis: int = 0):
    """The ``q`` quantile (linear between order statistics) of the ``valid`` entries of ``x``
    along ``axis``, NaN where none: for a few values (up to 16) a sorting network of
    elementwise min/max, else one integer sort (XLA on CPU sorts integers several times
    faster than floats, whose comparator must also order NaN)."""
    n = jnp.sum(valid, axis=axis, keepdims=True)
    h = q * (jnp.maximum(n, 1) - 1).astype(x.dtype)
    lo = jnp.floor(h).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, jnp.maximum(n - 1, 0)).astype(jnp.int32)
    if x.shape[axis] <= 16:  # a few values (a baseline block): a sorting network
        col = list(jnp.moveaxis(jnp.where(valid, x, jnp.inf), axis, 0))
        for r in range(len(col)):  # odd-even transposition: len(col) rounds sort
            for j in range(r % 2, len(col) - 1, 2):
                col[j], col[j + 1] = jnp.minimum(col[j], col[j + 1]), jnp.maximum(col[j], col[j + 1])
        a = sum(jnp.where(lo == j, jnp.expand_dims(v, axis), 0.0) for j, v in enumerate(col))
        b = sum(jnp.where(hi == j, jnp.expand_dims(v, axis), 0.0) for j, v in enumerate(col))
    else:
        itype = jnp.int32 if x.dtype == jnp.float32 else jnp.int64
        top = jnp.iinfo(itype).max
        i = jax.lax.bitcast_convert_type(x, itype)
        key = jnp.where(i < 0, i ^ top, i)  # the float order as integers
        key = jnp.sort(jnp.where(valid, key, top), axis=axis)
        key = jnp.where(key < 0, key ^ top, key)
        s = jax.lax.bitcast_convert_type(key, x.dtype)
        a = jnp.take_along_axis(s, lo, axis=axis)
        b = jnp.take_along_axis(s, hi, axis=axis)
    out = jnp.where(n > 0, a + (b - a) * (h - lo), jnp.nan)
    return jnp.squeeze(out, axis)


def _spread(has, limit: int):
    """At most ``limit`` window indices spread evenly from the first window to the last one
    ``has`` (along its last axis): those the windows hold, not the padded batch's; and
    which of them lie in that span (all, unless it holds fewer windows)."""
    k = has.shape[-1]
    span = jnp.max(jnp.where(has, jnp.arange(k), -1), axis=-1, keepdims=True) + 1
    j = jnp.arange(limit)
    return jnp.where(span > limit, (j * span) // limit, j), j < span


def _baseline(mean, use, valid, b: int):
    """Slow baseline of the window means: the median over blocks of ``b`` windows of the
    windows in ``use`` (of the ``valid`` ones; at most :data:`BLOCK_WINDOWS` of them spread
    evenly over the block), linearly interpolated between block centres."""
    k = mean.shape[0]
    kb = -(-k // b)
    pad = kb * b - k
    vals = jnp.concatenate([mean, jnp.zeros((pad, mean.shape[1]), mean.dtype)])
    ok = jnp.concatenate([use, jnp.zeros((pad,), bool)])
    vals, ok = vals.reshape(kb, b, -1), ok.reshape(kb, b)
    if b > BLOCK_WINDOWS:  # spread over the windows each block holds (a last block may be short)
        pick, inside = _spread(jnp.concatenate([valid, jnp.zeros((pad,), bool)]).reshape(kb, b),
                               BLOCK_WINDOWS)
        vals = jnp.take_along_axis(vals, pick[..., None], axis=1)
        ok = jnp.take_along_axis(ok, pick, axis=1) & inside
    med = _masked_quantile(vals, jnp.broadcast_to(ok[..., None], vals.shape), 0.5, axis=1)  # (kb, c)
    # a block without windows in use (all moving) holds the last block before it that has
    # some (the first such block before any)
    has = ~jnp.isnan(med[:, 0])
    idx = jnp.arange(kb)
    last = jax.lax.cummax(jnp.where(has, idx, -1))
    first = jnp.argmax(has)
    med = med[jnp.where(last >= 0, last, first)]  # NaN only where no window is in use
    # past the recording's end (padding), the line through its last two blocks: the last
    # block's second half is then extrapolated as without the padding, so a device's
    # baseline does not depend on the length of the batch it is checked in
    data = jnp.any(jnp.concatenate([valid, jnp.zeros((pad,), bool)]).reshape(kb, b), axis=1)
    end = jnp.max(jnp.where(data, idx, 0))
    line = 2.0 * med[end] - med[jnp.maximum(end - 1, 0)]
    med = jnp.where((idx > end)[:, None], line[None, :], med)
    if kb == 1:
        return jnp.broadcast_to(med, mean.shape)
    # linear between block centres, and extrapolated from the nearest two at the ends
    # (a warm-up's drift is fastest in the first half block): window i of block B lies
    # between the centres of blocks j = B − 1 (first half) or B (second half), clipped;
    # the block values are spread over the windows by broadcasting, not gathered
    dtype = np.dtype(mean.dtype.name)
    pos = (np.arange(k).astype(dtype) + dtype.type(0.5)) / dtype.type(b) - dtype.type(0.5)
    j = np.clip(np.floor(pos).astype(np.int32), 0, kb - 2)
    frac = jnp.asarray((pos - j.astype(dtype))[:, None])
    blocks = np.arange(kb)
    second = (np.arange(b) >= b // 2)[None, :, None]

    def spread(jb_first, jb_second):  # med[j] per window, j per block and half
        v = jnp.where(second, med[jb_second][:, None, :], med[jb_first][:, None, :])
        return v.reshape(kb * b, -1)[:k]

    first_j, second_j = np.clip(blocks - 1, 0, kb - 2), np.clip(blocks, 0, kb - 2)
    lo, hi = spread(first_j, second_j), spread(first_j + 1, second_j + 1)
    return lo + frac * (hi - lo)


def _run_start(flag):
    """Per window, the index of the last window at or before it that is not ``flag`` (−1
    where none): the window before the run of ``flag`` it belongs to."""
    idx = jnp.arange(flag.shape[0])
    return jax.lax.cummax(jnp.where(flag, -1, idx))


def _runs_with(flag, mark):
    """``flag`` with every run of True that holds no ``mark`` cleared (running maxima
    forwards and minima backwards: no scatter, no sort)."""
    k = flag.shape[0]
    idx = jnp.arange(k)
    ahead = jax.lax.cummax(jnp.where(flag & mark, idx, -1)) > _run_start(flag)
    end = jax.lax.cummin(jnp.where(flag, k, idx), reverse=True)
    behind = jax.lax.cummin(jnp.where(flag & mark, idx, k), reverse=True) < end
    return flag & (ahead | behind)


class _Windows(NamedTuple):
    """One signal's windows as the judgement reads them: means and validity, the rest noise
    and threshold per axis, the variance a window mean has at rest (raised by its own
    noise), the jumps between neighbouring windows, and the floor."""

    mean: Float[jax.Array, "k 3"]
    valid: Bool[jax.Array, " k"]
    sigma: Float[jax.Array, " 3"]
    threshold: Float[jax.Array, " 3"]
    var: Float[jax.Array, "k 3"]
    jump: Bool[jax.Array, " k"]
    loud: Bool[jax.Array, ""]
    floor: float


def _windows(stats, w: int, floor: float) -> _Windows:
    """A signal's :class:`_Windows` from its window statistics (:mod:`diffgyro._window_stats`)."""
    wins, c, valid, noise = stats
    mean, local = wins[:, 0], wins[:, 1]
    sigma, mean_noise = noise[0], noise[1]
    sigma = jnp.where(jnp.isnan(sigma), 0.0, sigma)
    mean_noise = jnp.where(jnp.isnan(mean_noise), 0.0, mean_noise)
    thr0 = jnp.maximum(K_SIGMA * mean_noise, floor)
    # vibration raises the local noise, and with it what a window mean may scatter; but a
    # window may not hide a turn of more than the resolution a window at rest noise has
    # (motion raises the local noise of a slowly sampled recording too)
    louder = jnp.clip(local / jnp.where(sigma > 0, sigma, jnp.inf)[None, :], 1.0, LOUDER_CAP)
    var = (mean_noise[None, :] * louder) ** 2 * (w / jnp.maximum(c, 1.0))[:, None]
    prev = jnp.concatenate([mean[:1], mean[:-1]])
    ok = valid & jnp.concatenate([jnp.zeros((1,), bool), valid[:-1]])
    var_prev = jnp.concatenate([var[:1], var[:-1]])
    jump = _flag(mean - prev, var + var_prev, ok, floor)  # a change between neighbours
    # a window louder than the cap allows: shaken or knocked, though its mean may not show it
    loud = jnp.any(valid[:, None] & (local > LOUDER_CAP * sigma[None, :]))
    return _Windows(mean, valid, sigma, thr0, var, jump, loud, floor)


def _flag(dev, var, ok, floor: float):
    """Windows whose deviation ``dev`` stands out of the noise ``var`` its mean can have."""
    thr = jnp.maximum(K_SIGMA * jnp.sqrt(var), floor)
    r = dev / thr
    return (_sum(r * r, 1) > 1.0) & ok


def _first_pass(win: _Windows, b: int):
    """The deviation of each window from the baseline of all valid windows, and the windows
    that leave it (before the rule on runs)."""
    dev = win.mean - _baseline(win.mean, win.valid, win.valid, b)
    dev = jnp.where(jnp.isnan(dev), 0.0, dev)
    return dev, _flag(dev, win.var, win.valid, win.floor)


def _runs(win: _Windows, dev, flags, b: int):
    """The moving windows and their deviations, where some window left the first pass's
    baseline: a run of such windows is motion when it starts or holds a jump (a turn
    starts within a window or two; thermal drift creeps). Then again, with the baseline
    of the windows the first pass left static."""
    jump = win.jump | jnp.concatenate([win.jump[1:], jnp.zeros((1,), bool)])
    moving = _runs_with(flags, jump)
    again = win.mean - _baseline(win.mean, win.valid & ~moving, win.valid, b)
    # where the first pass left no window static, its own baseline stands
    dev = jnp.where(jnp.isnan(again), dev, again)
    return _runs_with(_flag(dev, win.var, win.valid, win.floor), jump), dev


def _turned(moving, dev):
    """The largest angle turned within one run of moving windows (in window-mean rate ×
    windows; the host scales it by the window's length): the rate less the baseline,
    summed from the run's start."""
    turned = jnp.cumsum(jnp.where(moving[:, None], dev, 0.0), axis=0)
    before = _run_start(moving)
    turned = turned - jnp.where(before[:, None] >= 0, turned[jnp.maximum(before, 0)], 0.0)
    return jnp.max(jnp.where(moving, _norm(turned, 1), 0.0))


def _tilted(accel, valid, moving, thr):
    """Windows whose specific force leaves the mean of its chunk of :data:`STRETCH_CHUNK`
    windows by more than a tilt of :data:`TILT_FLOOR` (or the accelerometer's threshold),
    in chunks where nothing else moved (a chunk with a move in it is left to
    :func:`_rest_stretches`, which splits it there), and the largest such tilt (rad)."""
    k = accel.shape[0]
    c = STRETCH_CHUNK
    kc = -(-k // c)
    pad = kc * c - k
    a = jnp.concatenate([accel, jnp.zeros((pad, 3), accel.dtype)]).reshape(kc, c, 3)
    use = jnp.concatenate([valid & ~moving, jnp.zeros((pad,), bool)]).reshape(kc, c)
    still = ~jnp.any(jnp.concatenate([moving, jnp.zeros((pad,), bool)]).reshape(kc, c), axis=1)
    count = jnp.sum(use, axis=1)
    mean = jnp.sum(jnp.where(use[..., None], a, 0.0), axis=1) / jnp.maximum(count, 1)[:, None]
    off = _norm(a - mean[:, None, :], 2)
    floor = jnp.maximum(TILT_FLOOR, jnp.sqrt(jnp.sum(thr**2)))
    flag = use & (still & (count >= c // 2))[:, None] & (off > floor)
    g = jnp.maximum(_norm(mean, 1), 1e-9)[:, None]
    tilt = jnp.max(jnp.where(flag, jnp.arcsin(jnp.minimum(off / g, 1.0)), 0.0))
    return flag.reshape(-1)[:k], tilt


def _chunk(gyro, accel, w: int, b: int, runs: bool = True):
    """The judgement of a chunk of devices (leading axis) from their window statistics
    (gyro, and accelerometer or None): the numbers, and per window the flags and means
    the host reads. The rule on runs, and the angle turned, are worked out only in a chunk
    where some window moved (at rest, nothing does). ``runs=False``: the judgement of
    devices none of whose windows moved (no rule on runs, no angle), and per device
    whether that holds (else it is judged again with ``runs``)."""
    each = jax.vmap
    win = each(lambda st: _windows(st, w, 2.0 * EARTH_RATE))(gyro)
    dev, flags = each(lambda v: _first_pass(v, b))(win)
    if runs:
        moving, dev = jax.lax.cond(jnp.any(flags), each(lambda v, d, f: _runs(v, d, f, b)),
                                   lambda v, d, f: (jnp.zeros_like(f), d), win, dev, flags)
    else:  # (a value, not a constant: XLA would fold every sum over it while compiling)
        moving = jax.lax.optimization_barrier(jnp.zeros_like(flags))
    out = dict(window_rate=win.mean, window_valid=win.valid, threshold_axes=win.threshold)
    tilt = jnp.zeros(moving.shape[:1], jnp.float32)
    if accel is not None:
        acc = each(lambda st: _windows(st, w, ACCEL_FLOOR))(accel)
        moving = moving | acc.jump
        tilted, tilt = each(_tilted)(acc.mean, win.valid, moving, acc.threshold)
        moving = moving | tilted
        out |= dict(window_accel=acc.mean, accel_threshold=acc.threshold)
    if runs:
        turn = jax.lax.cond(jnp.any(moving), each(_turned),
                            lambda m, d: jnp.zeros(m.shape[:1], d.dtype), moving, dev)
    else:
        turn = jax.lax.optimization_barrier(jnp.zeros(moving.shape[:1], dev.dtype))
    out = out | each(_numbers)(win, moving, dev, turn, tilt, gyro[1]) | dict(window_moving=moving)
    if runs:
        return out
    return out, jnp.any(flags, axis=1) | jnp.any(moving, axis=1)


def _numbers(win: _Windows, moving, dev, turn, tilt, count):
    """One device's numbers (:data:`~diffgyro._motion_result.NUMBERS`, but the resolution the host forms) and its
    windows not at rest (moving, or next to a moving one: the transitions)."""
    rate = _norm(dev, 1)
    n_mov = jnp.sum(moving)
    peak = jnp.max(jnp.where(moving, rate, 0.0))
    rms = jnp.sqrt(jnp.sum(jnp.where(moving, rate**2, 0.0)) / jnp.maximum(n_mov, 1))
    near = moving | jnp.concatenate([moving[1:], jnp.zeros((1,), bool)]) | jnp.concatenate(
        [jnp.zeros((1,), bool), moving[:-1]])
    still = win.valid & ~moving
    rest_rate = jnp.sqrt(jnp.sum((jnp.sum(jnp.where(still[:, None], win.mean, 0.0), axis=0)
                                  / jnp.maximum(jnp.sum(still), 1)) ** 2))
    some = jnp.any(win.valid)
    frac = jnp.where(some, jnp.sum(jnp.where(moving, count, 0.0))
                     / jnp.maximum(jnp.sum(count), 1.0), jnp.nan)
    nan = jnp.asarray(jnp.nan, jnp.float32)
    return dict(moving_fraction=frac, rate_peak=jnp.where(some, peak, nan),
                rate_rms=jnp.where(some, rms, nan), turn_peak=jnp.where(some, turn, nan),
                tilt_peak=jnp.where(some, tilt, nan), rest_rate=jnp.where(some, rest_rate, nan),
                rest_noise=jnp.where(some, jnp.sqrt(jnp.mean(win.sigma**2)), nan),
                threshold=jnp.where(some, jnp.sqrt(jnp.mean(win.threshold**2)), nan),
                n_windows=jnp.sum(win.valid).astype(jnp.float32), window_near=near, loud=win.loud)


def _vmapped(gyro, accel, w: int, b: int):
    """The check of every device from its window statistics (devices first, a multiple of
    :data:`CHECK_CHUNK` or fewer): every device as at rest, vmapped over the batch (no rule
    on runs: elementwise work and sums over windows, which a loop over small chunks would
    slow many times), then chunk by chunk, the chunks where some window moved."""
    d = gyro[0].shape[0]
    if d <= CHECK_CHUNK:
        return _chunk(gyro, accel, w, b)
    rest, again = _chunk(gyro, accel, w, b, runs=False)
    return _chunks(gyro, accel, w, b, rest, again)


def _chunks(gyro, accel, w: int, b: int, out, again):
    """The check chunk by chunk (devices first, a multiple of :data:`CHECK_CHUNK`): the
    chunks where ``again`` holds for some device, the others as in ``out``."""
    d = gyro[0].shape[0]
    chunks = d // CHECK_CHUNK
    again = jnp.any(again.reshape(chunks, CHECK_CHUNK), axis=1)
    order = jnp.nonzero(again, size=chunks, fill_value=0)[0]

    def judge(i, out):  # the i-th chunk where some window moved
        at = order[i] * CHECK_CHUNK
        part = jax.tree.map(lambda y: jax.lax.dynamic_slice_in_dim(y, at, CHECK_CHUNK), (gyro, accel))
        got = _chunk(*part, w, b)
        return {k: jax.lax.dynamic_update_slice_in_dim(v, got[k].astype(v.dtype), at, 0)
                for k, v in out.items()}

    return jax.lax.fori_loop(0, jnp.sum(again), judge, out)


#: The check of a large batch; a small (padded) one is judged on the host
#: (:mod:`diffgyro._motion_host`).
_check = filter_jit(_vmapped)
_HOST = HostCheck()


class Layout(NamedTuple):
    """How a group of devices is checked: window and block sizes, the shape of its window
    sums (devices, windows; padded for a small batch) and whether the accelerometer is
    read."""

    w: int
    b: int
    shape: tuple[int, int]
    accel: bool
    padded: bool

    @property
    def check(self):
        """The judgement: on the host for a small batch (:mod:`diffgyro._motion_host`: the
        same flags, numbers to float32's last bits, no program to compile), else the
        compiled program."""
        return _HOST if self.padded else _check


def layout(devices: int, samples: int, w: int, b: int, accel: bool) -> Layout:
    """How a group of devices is judged: its window sums' shape (padded for a small batch,
    which a few shapes serve: a device's numbers do not depend on the padding) and its
    judgement (:attr:`Layout.check`: a small batch's on the host).

    **Arguments:**

    - ``devices``: the devices in the group.
    - ``samples``: the most samples one of them holds.
    - ``w``, ``b``: samples per window, windows per baseline block.
    - ``accel``: whether the accelerometer's windows are judged too.
    """
    k = -(-samples // w)
    if devices * samples > PAD_SAMPLES:  # devices in whole chunks
        rows = devices if devices <= CHECK_CHUNK else -(-devices // CHECK_CHUNK) * CHECK_CHUNK
        return Layout(w, b, (rows, k), accel, False)
    # small batches share a shape: devices to a bucket, windows to a power of two of blocks
    blocks = 1 << (-(-k // b) - 1).bit_length()
    return Layout(w, b, (device_bucket(devices, minimum=1), blocks * b), accel, True)


__all__ = ["layout", "Layout"]
