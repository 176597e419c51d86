"""The model-free white-noise floor on the accelerator: the statistic of
:mod:`diffgyro._noise` (the host's version) as a pure JAX function, for the paths that
compile their fit or differentiate through it (the direct path, the state-space path).

Per device and axis, from the successive differences of ``gyro − rate`` over pairs of
valid samples: one integer sort of the differences gives every order statistic
(:func:`masked_median`, the MAD and the trim quantile without a second sort), and rows
longer than :data:`diffgyro._noise.SUBSAMPLE` place their window from a subsample, as
the host does.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from . import _noise as noise

__all__ = ["device_noise_floor", "masked_median"]

def _sort_key(x):
    """Float bits as integers of the same order. XLA on CPU sorts integers ~5× faster
    than floats, whose comparator must also order NaN."""
    itype = jnp.int64 if x.dtype == jnp.float64 else jnp.int32
    i = jax.lax.bitcast_convert_type(x, itype)
    return jnp.where(i < 0, i ^ jnp.iinfo(itype).max, i)


def _sorted_valid(x, valid):
    """Valid (non-NaN) entries sorted to the front of the last axis, and their count."""
    valid = valid & ~jnp.isnan(x)
    key = _sort_key(x)
    key = jnp.sort(jnp.where(valid, key, jnp.iinfo(key.dtype).max), axis=-1)
    key = jnp.where(key < 0, key ^ jnp.iinfo(key.dtype).max, key)  # back to the float bits
    return jax.lax.bitcast_convert_type(key, x.dtype), jnp.sum(valid, axis=-1)


def _at(s, k):
    return jnp.take_along_axis(s, jnp.clip(k, 0, s.shape[-1] - 1)[..., None], -1)[..., 0]


def masked_median(x: Float[Array, "... n"], valid: Bool[Array, "... n"]) -> Float[Array, "..."]:
    """Median of the valid (non-NaN) entries along the last axis, NaN if none
    (``jnp.nanmedian`` of the masked values, through one integer sort)."""
    if x.shape[-1] == 0:
        return jnp.full(x.shape[:-1], jnp.nan, x.dtype)
    s, n = _sorted_valid(x, valid)
    return jnp.where(n > 0, 0.5 * (_at(s, (n - 1) // 2) + _at(s, n // 2)), jnp.nan)


def _middle_deviations(s, n, med, split, k):
    """The k-th and (k+1)-th smallest |s_i − med| of sorted s (n valid) without sorting
    again: the deviations below ``split`` and from it on are two ascending runs; a
    binary search finds how many of the k+1 smallest come from the lower run, and the
    next smallest is the lesser of the two runs' next ones."""
    def lower(i):  # i-th smallest deviation of the lower run
        return med - _at(s, split - 1 - i)

    def upper(j):
        return _at(s, split + j) - med

    lo, hi = jnp.maximum(0, k + 1 - (n - split)), jnp.minimum(k + 1, split)

    def step(_, bounds):
        lo, hi = bounds
        i = (lo + hi) // 2
        more = (i < hi) & (lower(i) < upper(k - i))  # the lower run's next is among them
        return jnp.where(more, i + 1, lo), jnp.where(more, hi, i)

    lo, _ = jax.lax.fori_loop(0, max(1, int(s.shape[-1]).bit_length() + 1), step, (lo, hi))
    j = k + 1 - lo
    kth = jnp.maximum(jnp.where(lo > 0, lower(lo - 1), -jnp.inf),
                      jnp.where(j > 0, upper(j - 1), -jnp.inf))
    after = jnp.minimum(jnp.where(lo < split, lower(lo), jnp.inf),
                        jnp.where(j < n - split, upper(j), jnp.inf))
    return kth, after


def device_noise_floor(y: Float[Array, "n 3"], mask: Bool[Array, " n"]) -> Float[Array, " 3"]:
    """White-noise σ per axis from successive differences (model-free), over pairs of
    valid samples: :func:`diffgyro._noise.sigma_from_differences` from one sort (and a
    sort of the subsample on rows longer than :data:`diffgyro._noise.SUBSAMPLE`)."""
    if y.shape[0] < 2:
        return jnp.full((3,), jnp.nan, y.dtype)
    dy = jnp.diff(y, axis=0).T  # (3, n-1)
    pair = jnp.broadcast_to(mask[1:] & mask[:-1], dy.shape)
    s, n = _sorted_valid(dy, pair)  # one sort gives every order statistic
    med = 0.5 * (_at(s, (n - 1) // 2) + _at(s, n // 2))
    split = jnp.sum((s < med[:, None]) & (jnp.arange(s.shape[-1]) < n[:, None]), axis=-1)
    # the median deviation: the middle one, or the mean of the middle two (one search)
    kth, after = _middle_deviations(s, n, med, split, (n - 1) // 2)
    scale = 1.4826 * jnp.where(n % 2 == 1, kth, 0.5 * (kth + after))
    h = (1.0 - noise.TRIM) * (n - 1)
    lo = jnp.floor(h).astype(n.dtype)
    t = h - lo
    a, b = _middle_deviations(s, n, med, split, lo)
    b = jnp.where(lo + 1 < n, b, a)
    trim = jnp.where(t >= 0.5, b - (b - a) * (1.0 - t), a + (b - a) * t)
    valid = jnp.arange(s.shape[-1]) < n[:, None]
    dev = jnp.where(valid, jnp.abs(s - med[:, None]), jnp.inf)
    sq = jnp.where(valid, dev * dev, 0.0)

    def mean_count(keep):
        count = jnp.sum(keep, -1)
        return jnp.sum(jnp.where(keep, sq, 0.0), -1) / jnp.maximum(count, 1), count

    ms, inside = mean_count(dev <= 4.0 * scale[:, None])
    ms_trim, _ = mean_count(dev <= trim[:, None])
    ms_trim = jnp.where(ms_trim > 0, ms_trim, mean_count(valid)[0])  # a nearly constant output
    ms = jnp.where(inside < noise.COLLAPSED * n, ms_trim, ms / noise.TRUNC4)
    if dy.shape[-1] > noise.SUBSAMPLE:  # rows long enough to place the window from a subsample
        ms = jnp.where(n > noise.SUBSAMPLE, _subsampled_ms(dy, pair, n, ms), ms)
    return jnp.where(n > 0, jnp.sqrt(ms / 2.0), jnp.nan)


def _subsampled_ms(dy: Float[Array, "3 m"], pair: Bool[Array, "3 m"], n: Int[Array, " 3"],
                   exact: Float[Array, " 3"]) -> Float[Array, " 3"]:
    """Twice the squared floor of rows of more than :data:`diffgyro._noise.SUBSAMPLE` valid
    differences, as :func:`diffgyro._noise._sigma_subsampled` gives it: the window placed
    from the median and MAD of the subsample, the variance of the differences inside it;
    ``exact`` where that function keeps the exact statistic."""
    k = noise.SUBSAMPLE
    valid = pair & ~jnp.isnan(dy)
    rank = (2 * jnp.arange(k)[None, :] + 1) * n[:, None] // (2 * k)  # noise.subsample_ranks
    at = jax.vmap(jnp.searchsorted)(jnp.cumsum(valid, axis=-1), rank + 1)  # the rank-th valid
    sub = jnp.take_along_axis(dy, jnp.clip(at, 0, dy.shape[-1] - 1), axis=-1)
    every = jnp.ones(sub.shape, bool)
    centre = masked_median(sub, every)
    dev = jnp.abs(sub - centre[:, None])
    half_width = 4.0 * 1.4826 * masked_median(dev, every)
    s = dy - centre[:, None]
    q = s * s
    inside = valid & (q <= (half_width * half_width)[:, None])  # noise_passes.window_sums
    count = jnp.sum(inside, axis=-1)
    mean = jnp.sum(jnp.where(inside, s, 0.0), axis=-1) / jnp.maximum(count, 1)
    ms = jnp.sum(jnp.where(inside, q, 0.0), axis=-1) / jnp.maximum(count, 1) - mean * mean
    keep = ((count < noise.EXACT_INSIDE * n) | (jnp.sum(dev == 0, axis=-1) >= noise.EXACT_TIES * k)
            | jnp.any(valid & jnp.isinf(dy), axis=-1))
    return jnp.where(keep, exact, jnp.maximum(ms, 0.0) / noise.TRUNC4)
