"""Static-period detection: static-kalman's range thresholds and an IMU-TK-style variance detector.

Both are pure JAX functions of one device's samples with static window sizes,
so they vmap over a batch (:func:`detect_batch`); each is compiled once per
shape and options (``eqx.filter_jit``: arrays traced, the rest static). They return a per-sample
boolean ``static`` (padding excluded through ``mask``).

* :func:`s1_range_detector` — static-kalman's detector, faithfully: thresholds
  ``T = M·(max − min)`` of every signal over an initial static window
  (``init`` samples), then consecutive windows of ``window`` samples are
  static when the peak-to-peak range of *every* signal is below its
  threshold. The signals are Ax, Ay, Az and the gyro axes ``gyro_axes``
  (static-kalman uses the z rate only: ``gyro_axes=(2,)``).
* :func:`variance_detector` — after Tedaldi et al. (IMU-TK, ICRA 2014): the
  magnitude ``ς = ‖(var ax, var ay, var az)‖`` of the accelerometer variance
  over a centred window of ``2·half_window + 1`` samples; static where
  ``ς < k·ς_init`` (``ς_init`` of the initial static window) and the static
  run lasts at least ``min_length`` samples. With ``multiplier=None`` the
  threshold is chosen automatically by Otsu's method on ``log ς`` (the
  split of the log-variance histogram that maximises the between-class
  variance: rest and motion form two modes decades apart), and the
  equivalent multiplier ``k`` is reported. IMU-TK's own criterion (the
  residual of an accelerometer calibration over the intervals) needs many
  distinct poses; Otsu works on any recording with both rest and motion.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .errors import DataError


class RangeDetection(eqx.Module):
    """Range detector output: per-sample ``static``, per-window ``window_static`` (windows start at
    ``start``), the ``thresholds`` (Ax, Ay, Az, then the gyro axes used)."""

    static: Bool[Array, " n"]
    window_static: Bool[Array, " k"]
    thresholds: Float[Array, " s"]


def _windows(x, mask, start: int, window: int):
    """(k, window, ...) blocks from ``start`` and their validity; the last may be partial."""
    n = x.shape[0]
    k = max((n - start + window - 1) // window, 0)
    pad = start + k * window - n
    xs = jnp.concatenate([x[start:], jnp.repeat(x[-1:], pad, axis=0)], axis=0)
    ms = jnp.concatenate([mask[start:], jnp.zeros((pad,), bool)])
    return xs.reshape(k, window, *x.shape[1:]), ms.reshape(k, window)


@eqx.filter_jit
def s1_range_detector(
    accel: Float[Array, "n 3"],
    gyro: Float[Array, "n 3"],
    *,
    window: int,
    init: int = 1000,
    margin: float = 2.0,
    gyro_axes: tuple[int, ...] = (2,),
    mask: Bool[Array, " n"] | None = None,
    start: int | None = None,
) -> RangeDetection:
    """static-kalman's window-by-window static test (see the module docstring).

    ``init`` samples at the start are the factory static window that sets the
    thresholds (and count as static); windows of ``window`` samples follow
    from ``start`` (default ``init``, so ``window_static`` lines up with
    :func:`diffgyro.recipes._static_kalman.offset_filter`). ``margin`` is the patent's ``M``.
    A window needs at least one valid sample; its range is over valid ones.

    **Arguments:**

    - ``accel``: specific force (n, 3), m/s².
    - ``gyro``: rate (n, 3), rad/s.
    - ``window``: samples per window.
    - ``init``: samples of the factory static window at the start.
    - ``margin``: the patent's ``M``.
    - ``gyro_axes``: the gyro axes tested.
    - ``mask``: which samples are valid (default: all).
    - ``start``: where the windows start (default: ``init``).
    """
    accel = jnp.asarray(accel)
    sig = jnp.concatenate([accel, jnp.asarray(gyro, accel.dtype)[:, list(gyro_axes)]], axis=1)
    n = sig.shape[0]
    mask = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
    start = init if start is None else start
    head = sig[:init]
    hm = mask[:init, None]
    span0 = jnp.max(jnp.where(hm, head, -jnp.inf), 0) - jnp.min(jnp.where(hm, head, jnp.inf), 0)
    thr = margin * span0
    blocks, bm = _windows(sig, mask, start, window)
    hi = jnp.max(jnp.where(bm[..., None], blocks, -jnp.inf), axis=1)
    lo = jnp.min(jnp.where(bm[..., None], blocks, jnp.inf), axis=1)
    win_static = jnp.all(hi - lo < thr, axis=1) & jnp.any(bm, axis=1)
    per_sample = jnp.repeat(win_static, window)[: n - start]
    static = jnp.concatenate([jnp.arange(start) < init, per_sample]) & mask
    return RangeDetection(static=static, window_static=win_static, thresholds=thr)


class VarianceDetection(eqx.Module):
    """Variance detector output: per-sample ``static`` and variance magnitude ``sigma``
    ((m/s²)²), the ``threshold`` used, ``multiplier`` = threshold / ς_init, and ``sigma_init``."""

    static: Bool[Array, " n"]
    sigma: Float[Array, " n"]
    threshold: Float[Array, ""]
    multiplier: Float[Array, ""]
    sigma_init: Float[Array, ""]


@eqx.filter_jit
def rolling_variance(x: Float[Array, "n c"], mask: Bool[Array, " n"], half: int) -> Float[Array, "n c"]:
    """Variance of every column over the valid samples of ``i−half .. i+half`` (cumulative sums).

    Columns are centred on their valid mean first so the sums stay accurate.

    **Arguments:**

    - ``x``: the columns (n, c).
    - ``mask``: which samples are valid.
    - ``half``: the window's half-width, samples.
    """
    w = mask.astype(x.dtype)[:, None]
    mean = jnp.sum(x * w, 0) / jnp.maximum(jnp.sum(w), 1.0)
    xc = (x - mean) * w
    n = x.shape[0]

    def csum(v):
        return jnp.concatenate([jnp.zeros((1,) + v.shape[1:], v.dtype), jnp.cumsum(v, 0)])

    c1, cx, cxx = csum(w), csum(xc), csum(xc * xc)
    i = jnp.arange(n)
    lo = jnp.clip(i - half, 0, n)
    hi = jnp.clip(i + half + 1, 0, n)
    s1 = jnp.maximum(c1[hi] - c1[lo], 1.0)
    sx = cx[hi] - cx[lo]
    sxx = cxx[hi] - cxx[lo]
    return jnp.maximum(sxx / s1 - (sx / s1) ** 2, 0.0)


@eqx.filter_jit
def otsu_threshold(values: Float[Array, " n"], mask: Bool[Array, " n"], bins: int = 256) -> Float[Array, ""]:
    """Otsu's threshold of the valid ``values``: maximises the between-class variance
    (the middle of the best split when an empty gap between the modes makes it a plateau).

    **Arguments:**

    - ``values``: the values (n,).
    - ``mask``: which of them are valid.
    - ``bins``: histogram bins.
    """
    v = jnp.where(mask, values, jnp.nan)
    lo, hi = jnp.nanmin(v), jnp.nanmax(v)
    width = jnp.maximum(hi - lo, 1e-12) / bins
    idx = jnp.clip(((values - lo) / width).astype(jnp.int32), 0, bins - 1)
    hist = jax.ops.segment_sum(mask.astype(values.dtype), idx, num_segments=bins)
    centres = lo + (jnp.arange(bins) + 0.5) * width
    w0 = jnp.cumsum(hist)
    total = w0[-1]
    m0 = jnp.cumsum(hist * centres)
    w1 = total - w0
    mu0 = m0 / jnp.maximum(w0, 1e-12)
    mu1 = (m0[-1] - m0) / jnp.maximum(w1, 1e-12)
    between = jnp.where((w0 > 0) & (w1 > 0), w0 * w1 * (mu0 - mu1) ** 2, -1.0)
    # well-separated modes leave a plateau over the empty gap: take its middle
    top = between >= jnp.max(between) * (1.0 - 1e-9)
    first = jnp.argmax(top)
    last = bins - 1 - jnp.argmax(top[::-1])
    return lo + (0.5 * (first + last) + 1.0) * width


@eqx.filter_jit
def drop_short_runs(flag: Bool[Array, " n"], min_length: int) -> Bool[Array, " n"]:
    """``flag`` with every run of True shorter than ``min_length`` samples cleared.

    **Arguments:**

    - ``flag``: the flags (n,).
    - ``min_length``: the shortest run of True kept, samples.
    """
    n = flag.shape[0]
    start = flag & ~jnp.concatenate([jnp.zeros((1,), bool), flag[:-1]])
    run = jnp.cumsum(start) - 1
    run = jnp.where(flag, run, n)
    length = jax.ops.segment_sum(flag.astype(jnp.int32), run, num_segments=n + 1)
    return flag & (length[run] >= min_length)


@eqx.filter_jit
def variance_detector(
    accel: Float[Array, "n 3"],
    *,
    half_window: int,
    init: int,
    min_length: int,
    multiplier: float | Float[Array, ""] | None = None,
    mask: Bool[Array, " n"] | None = None,
) -> VarianceDetection:
    """IMU-TK-style static detection on the accelerometer (see the module docstring).

    ``half_window`` samples each side for the rolling variance, ``init``
    samples of initial rest for ``ς_init``, ``min_length`` the shortest static
    run kept; ``multiplier`` ``k`` (threshold ``k·ς_init``) or ``None`` for
    Otsu's automatic threshold on ``log ς``.

    **Arguments:**

    - ``accel``: specific force (n, 3), m/s².
    - ``half_window``: samples each side for the rolling variance.
    - ``init``: samples of initial rest, for ``ς_init``.
    - ``min_length``: the shortest static run kept, samples.
    - ``multiplier``: ``k`` of the threshold ``k·ς_init``, or None for Otsu's threshold on
      ``log ς``.
    - ``mask``: which samples are valid (default: all).
    """
    accel = jnp.asarray(accel)
    n = accel.shape[0]
    mask = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
    var = rolling_variance(accel, mask, half_window)
    sigma = jnp.sqrt(jnp.sum(var**2, axis=1))
    head = jnp.arange(n) < init
    hm = (head & mask).astype(accel.dtype)
    a0 = jnp.sum(accel * hm[:, None], 0) / jnp.maximum(jnp.sum(hm), 1.0)
    var0 = jnp.sum(hm[:, None] * (accel - a0) ** 2, 0) / jnp.maximum(jnp.sum(hm) - 1.0, 1.0)
    sigma_init = jnp.sqrt(jnp.sum(var0**2))
    if multiplier is None:
        tiny = jnp.finfo(accel.dtype).tiny
        threshold = jnp.exp(otsu_threshold(jnp.log(sigma + tiny), mask))
    else:
        threshold = jnp.asarray(multiplier, accel.dtype) * sigma_init
    static = drop_short_runs((sigma < threshold) & mask, min_length)
    return VarianceDetection(static=static, sigma=sigma, threshold=threshold,
                             multiplier=threshold / jnp.maximum(sigma_init, jnp.finfo(accel.dtype).tiny),
                             sigma_init=sigma_init)


def detect_batch(batch, method: str = "variance", **options) -> Bool[np.ndarray, "d n"]:
    """Static mask of every device of a :class:`~diffgyro.data.Batch` (vmapped).

    ``method="variance"`` (needs accelerometer; options of
    :func:`variance_detector`, windows in samples) or ``"s1"`` (options of
    :func:`s1_range_detector`).

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch`.
    - ``method``: ``"variance"`` or ``"s1"``.
    - ``**options``: the chosen detector's options.
    """

    if batch.accel is None:
        raise DataError("static detection needs the accelerometer", column="ax, ay, az",
                        hint="give ax, ay, az, or pass the static mask yourself")
    acc = jnp.asarray(batch.accel, jnp.float64 if batch.accel.dtype == np.float64 else None)
    mask = jnp.asarray(batch.mask)
    if method == "variance":
        f = jax.vmap(lambda a, m: variance_detector(a, mask=m, **options).static)
        return np.asarray(f(acc, mask))
    if method == "s1":
        gyro = jnp.asarray(batch.gyro, acc.dtype)
        f = jax.vmap(lambda a, g, m: s1_range_detector(a, g, mask=m, **options).static)
        return np.asarray(f(acc, gyro, mask))
    raise ValueError(f"unknown detection method {method!r} (use 'variance' or 's1')")


def precision_recall(pred: Bool[np.ndarray, " n"], truth: Bool[np.ndarray, " n"]) -> tuple[float, float]:
    """Precision and recall of ``pred`` as a detector of ``truth`` (both boolean).

    **Arguments:**

    - ``pred``: the detector's flags (n,).
    - ``truth``: the true flags (n,).
    """
    pred = np.asarray(pred, bool)
    truth = np.asarray(truth, bool)
    tp = np.sum(pred & truth)
    return float(tp / max(np.sum(pred), 1)), float(tp / max(np.sum(truth), 1))


__all__ = ["RangeDetection", "VarianceDetection", "detect_batch", "drop_short_runs",
           "otsu_threshold", "precision_recall", "rolling_variance", "s1_range_detector",
           "variance_detector"]
