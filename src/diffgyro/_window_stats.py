"""The motion check's window statistics: one read of each device's samples.

:mod:`diffgyro.motion` judges a recording from statistics of its windows (their means,
local noise and half-window differences) and a rest noise from their quantiles. A large
batch is read by a compiled pass (:mod:`diffgyro._window_pass`, numba, on the host's
cores): XLA on a CPU reduces short windows several times slower than one compiled loop
does, and the check would then cost more than the fit it guards. A small batch is read by
numpy here (about 0.25 µs a sample, against 0.02 µs compiled), which costs a command
less than numba's import and the load of its compiled pass (half a second). Both give the same numbers (sums in float64, the
statistics stored in float32).
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float, Int

#: Batches of at least this many samples (devices × samples) are read by the compiled pass
#: (and any batch, once a process has loaded it).
COMPILED_SAMPLES = 1 << 19
#: Whether this process has loaded the compiled pass (then every batch takes it).
_loaded = False


def window_stats(x: Float[np.ndarray, "d n 3"], mask: Bool[np.ndarray, "d n"], w: int,
                 rows: Int[np.ndarray, " r"], windows: int, quantiles: tuple[float, ...],
                 limit: int, out_rows: int | None = None,
                 rate: Float[np.ndarray, "d n 3"] | None = None
                 ) -> tuple[Float[np.ndarray, "R K 3 3"], Float[np.ndarray, "R K"],
                            Bool[np.ndarray, "R K"], Float[np.ndarray, "R 2 3"]]:
    """Window statistics of devices ``rows`` of ``x − rate`` (``rate`` where given), in
    windows of ``w`` valid-masked samples: per window and axis the mean, the local noise
    (``√(mean Δ²/2)`` over successive valid pairs inside the window) and the difference of
    the means of its two halves; per window the valid samples and whether it is valid
    (half its samples, two pairs, both halves, every value finite). And per device the
    rest noise per axis, of one sample (σ) and of a window mean, from the ``quantiles``
    (the local noise's, the half differences', and the normal quantiles that correct
    them, :func:`diffgyro.motion.noise_quantiles`) of at most ``limit`` valid windows
    spread evenly over the device's, and the quantum (the smallest nonzero change
    between neighbouring valid samples); NaN where it has no valid window. The outputs hold
    ``out_rows`` devices (default ``len(rows)``) and ``windows`` windows: those past the
    data are empty (invalid)."""
    rows = np.ascontiguousarray(rows, np.int64)
    total = len(rows) if out_rows is None else out_rows
    stats = np.zeros((total, windows, 3, 3), np.float32)
    count = np.zeros((total, windows), np.float32)
    valid = np.zeros((total, windows), bool)
    noise = np.full((total, 2, 3), np.nan, np.float32)
    x = np.asarray(x)
    mask = np.asarray(mask, bool)
    q = np.asarray(quantiles, np.float64)
    if compiled(len(rows) * x.shape[1]):
        from ._window_pass import compiled_pass  # numba: imported for a large batch only

        rate = np.zeros((0, 1, 3), x.dtype) if rate is None else np.asarray(rate, x.dtype)
        compiled_pass(x, mask, rate, rows, int(w), stats, count, valid, noise, q, int(limit))
    elif len(rows):
        _numpy_pass(x, mask, rate, rows, int(w), stats, count, valid, noise, q, int(limit))
    return stats, count, valid, noise


def _numpy_pass(x, mask, rate, rows, w: int, stats, count, valid, noise, q, limit: int) -> None:
    """:func:`window_stats` of a small batch, into its outputs (the compiled pass's numbers)."""
    r, k, n = len(rows), stats.shape[1], x.shape[1]
    m = np.zeros((r, k * w), bool)
    v = np.zeros((r, k * w, 3))
    used = min(n, k * w)
    m[:, :used] = mask[rows, :used]
    v[:, :used] = x[rows, :used]
    if rate is not None:
        v[:, :used] -= rate[rows, :used]
    v = np.where(m[..., None], v, 0.0).reshape(r, k, w, 3)
    m = m.reshape(r, k, w)
    h = w // 2
    first, total = v[:, :, :h].sum(axis=2), v.sum(axis=2)
    c1, c = m[:, :, :h].sum(axis=2).astype(float), m.sum(axis=2).astype(float)
    pair = m[:, :, 1:] & m[:, :, :-1]
    d = np.where(pair[..., None], v[:, :, 1:] - v[:, :, :-1], 0.0)
    cp = pair.sum(axis=2).astype(float)
    with np.errstate(invalid="ignore", over="ignore"):
        mean = total / np.maximum(c, 1.0)[..., None]
        half = first / np.maximum(c1, 1.0)[..., None] - (total - first) / np.maximum(c - c1, 1.0)[..., None]
        local = np.sqrt((d * d).sum(axis=2) / (2.0 * np.maximum(cp, 1.0))[..., None])
        stats[:r, :, 0], stats[:r, :, 1], stats[:r, :, 2] = mean, local, half
        count[:r] = c
        finite = np.all(np.isfinite(mean) & np.isfinite(local), axis=2)
        valid[:r] = (c >= max(h, 2)) & (cp >= 2) & (c1 > 0) & (c > c1) & finite
        step = np.where(pair[..., None] & (d != 0.0), np.abs(d), np.inf)
        quantum = step.reshape(r, -1, 3).min(axis=1) if step.size else np.full((r, 3), np.inf)
    quantum = np.where(np.isfinite(quantum), quantum, 0.0)
    _rest_noise(stats[:r], valid[:r], quantum, w, q, limit, noise[:r])


def _rest_noise(stats, valid, quantum, w: int, q, limit: int, noise) -> None:
    """Every device's rest noise (the compiled pass's ``_rest_noise``), into ``noise``."""
    rest_q, half_q, z, zh = q
    chi = max(1.0 - z / np.sqrt(2.0 * max(w - 1, 1)), 0.5)
    sigma = np.maximum(spread_quantile(stats[:, :, 1], valid, rest_q, limit) / chi,
                       quantum / np.sqrt(12.0))
    half = spread_quantile(np.abs(stats[:, :, 2]), valid, half_q, limit)
    noise[:, 0], noise[:, 1] = sigma, np.maximum(sigma / np.sqrt(w), half / zh / 2.0)


def spread_quantile(x: Float[np.ndarray, "r k 3"], valid: Bool[np.ndarray, "r k"], q: float,
                    limit: int) -> Float[np.ndarray, "r 3"]:
    """The ``q`` quantile (linear between order statistics, as the compiled pass's
    ``_quantile`` forms it from float32 values) per device and axis of ``x`` over its valid
    windows among at most ``limit`` spread evenly from its first window to its last valid
    one; NaN where none."""
    r, k = valid.shape
    if not k:
        return np.full((r, 3), np.nan)
    if k <= limit:  # every window (none lies past a device's last valid one)
        use, picked = valid, x
    else:
        span = np.where(valid.any(axis=1), k - np.argmax(valid[:, ::-1], axis=1), 0)[:, None]
        j = np.arange(limit)[None]
        at = np.minimum(np.where(span > limit, (j * span) // limit, j), k - 1)
        use = np.take_along_axis(valid, at, axis=1) & (j < span)
        picked = np.take_along_axis(x, at[..., None], axis=1)
    v = np.sort(np.where(use[..., None], picked, np.inf), axis=1)
    u = use.sum(axis=1)[:, None]
    pos = q * np.maximum(u - 1, 0)
    lo = np.floor(pos).astype(int)
    hi = np.minimum(lo + 1, np.maximum(u - 1, 0))
    a = np.take_along_axis(v, np.repeat(lo[..., None], 3, axis=2), axis=1)[:, 0]
    b = np.take_along_axis(v, np.repeat(hi[..., None], 3, axis=2), axis=1)[:, 0]
    with np.errstate(invalid="ignore"):
        out = a + (b - a) * (pos - lo)
    return np.where(u > 0, out, np.nan)


def window_means(x: Float[np.ndarray, "d n *c"], mask: Bool[np.ndarray, "d n"],
                 rows: Int[np.ndarray, " r"], h: int, k: int) -> Float[np.ndarray, "r k *c"]:
    """The means of the valid samples of devices ``rows`` of ``x`` over ``k`` windows of
    ``h`` samples (those past the samples empty); a window without a valid sample holds
    its nearest earlier neighbour's mean (the first one's, before any). A large batch (or
    any, once the compiled pass is loaded) is read by the compiled pass, one read of each
    device's samples; a small one by numpy."""
    x = np.asarray(x)
    rows = np.ascontiguousarray(rows, np.int64)
    if compiled(len(rows) * x.shape[1]):
        from ._window_pass import compiled_means

        out = compiled_means(x.reshape(x.shape[:2] + (-1,)), np.asarray(mask, bool), rows, h, k)
        return out.reshape((len(rows), k) + x.shape[2:])
    m = min(x.shape[1], k * h)
    valid = np.asarray(mask, bool)[rows, :m]
    part = x[rows, :m]
    counts = windowed_sums(valid, h, k)
    if not valid.all():
        part = np.where(valid.reshape(valid.shape + (1,) * (part.ndim - 2)), part, 0.0)
    s = windowed_sums(part, h, k)
    safe = np.maximum(counts, 1.0)
    return _held(s / safe.reshape(safe.shape + (1,) * (s.ndim - 2)), counts > 0)


def windowed_sums(x: np.ndarray, h: int, k: int) -> np.ndarray:
    """Sums over windows of ``h`` samples along axis 1, ``k`` of them (those past the
    samples empty; a boolean ``x`` counts its True entries)."""
    d, n = x.shape[:2]
    whole = n // h
    out = np.zeros((d, k) + x.shape[2:])
    out[:, :whole] = x[:, :whole * h].reshape((d, whole, h) + x.shape[2:]).sum(
        axis=2, dtype=np.int32 if x.dtype == bool else None)
    if n > whole * h:
        out[:, whole] = x[:, whole * h:].sum(axis=1)
    return out


def _held(x: np.ndarray, has: Bool[np.ndarray, "r m"]) -> np.ndarray:
    """``x`` (rows, m, ...) with the entries without ``has`` holding the nearest earlier
    one (the first one, before any)."""
    if has.all():
        return x
    at = np.where(has, np.arange(has.shape[1]), -1)
    at = np.maximum.accumulate(at, axis=1)
    first = np.argmax(has, axis=1)[:, None]
    at = np.where(at < 0, first, at)
    return np.take_along_axis(x, at.reshape(at.shape + (1,) * (x.ndim - 2)), axis=1)


def compiled(samples: int) -> bool:
    """Whether a batch of ``samples`` (devices × samples) is read by the compiled pass
    (which then reads every batch of this process)."""
    global _loaded
    _loaded = _loaded or samples >= COMPILED_SAMPLES
    return _loaded


__all__ = ["window_stats", "window_means", "windowed_sums", "spread_quantile", "compiled",
           "COMPILED_SAMPLES"]
