"""The overlapping Allan deviation itself: one prefix sum, then the sums of squared second
differences block by block (NIST SP 1065 eq. 11, allantools' counting)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._jit import filter_jit
from .._xla_options import FAST_COMPILE
from ..signals import prefix_sums

#: Stable32's stop ratio for overlapping ADEV: largest m is N / 4.
STOP_RATIO = 4


def default_m(n: int, per_decade: int = 10, stop_ratio: int = STOP_RATIO) -> np.ndarray:
    """Cluster sizes 1 .. n // stop_ratio, about ``per_decade`` per decade (integers, unique).

    **Arguments:**

    - ``n``: the series' samples.
    - ``per_decade``: cluster sizes per decade.
    - ``stop_ratio``: the longest cluster is ``n / stop_ratio`` samples.
    """
    top = max(1, int(n) // int(stop_ratio))
    k = int(math.floor(per_decade * math.log10(top))) + 1
    m = np.unique(np.round(np.logspace(0.0, math.log10(top), max(k, 1))).astype(np.int64))
    return m[m >= 1]


#: Samples per step of the loop over series: one 1M-sample series at a time keeps its padded
#: phase (12 MB) in cache while all τ are summed (with one whole-series pass per τ, two
#: series at a time were ~1.6× slower per series and all at once, the former vmap, slower
#: still; measured).
_CHUNK_SAMPLES = 1 << 20
#: Terms (τ × samples) summed per step of the loop over blocks: all τ of one block of
#: samples at once, so the three windows of a small-m τ are read from a block already in
#: cache and the (τ, block) temporary stays a few MB. Blocks of 16 384 samples for 51 τ
#: were ~1.2-1.7× faster than one whole-series pass per τ (measured; 65 536 was slower).
_BLOCK_TERMS = 1 << 20
#: The same two budgets on a GPU or TPU, where each loop step must carry far more work (one
#: step per series and block would leave the device mostly idle): up to 128 series of 1M
#: samples per step, a (τ, series, block) temporary of at most 512 MB. Not measured (no
#: accelerator was available when they were set); the code path is the CPU one.
_ACCEL_CHUNK_SAMPLES = 1 << 27
_ACCEL_BLOCK_TERMS = 1 << 26


def _block_length(n: int, k: int, terms: int) -> int:
    """Samples per block: a power of two with k · block ≈ ``terms`` (k: τ × series summed
    together), at least 256, at most n."""
    target = max(terms // max(k, 1), 256)
    return max(1, min(n, 1 << (target.bit_length() - 1)))


def _oadev_one(y, n_valid, dt, m, stop_ratio, batch, block_terms, padded=True):
    """Overlapping ADEV of one padded series; returns (adev, count) per m (NaN if too few).

    One prefix sum gives the phase x (mean removed first, as allantools does, so
    that x stays small and its second differences do not cancel). The sums of
    squared second differences are then accumulated block by block of samples,
    all τ of a block at once: for τ = m the block's terms read three contiguous
    windows of x at offsets 0, m, 2m (a fused gather; no (τ, n) temporary).
    Only m ≤ n / stop_ratio can be defined, so x is zero-padded by 2·that.
    ``batch`` series run together (vmapped), so their blocks share ``block_terms``;
    ``padded=False`` (static) says that all n samples are real.
    """
    n = y.shape[0]
    k = m.shape[0]
    mmax = max(n // stop_ratio, 1) if stop_ratio > 0 else n
    blk = _block_length(n, k * batch, block_terms)
    nblocks = -(-n // blk)  # terms i < n suffice: count ≤ n − 1 for m ≥ 1
    if padded:
        valid = jax.lax.iota(jnp.int32, n) < n_valid
        mean = jnp.sum(jnp.where(valid, y, 0.0)) / jnp.maximum(n_valid, 1)
        yc = jnp.where(valid, y - mean, 0.0)
    else:  # every sample real (n_valid not given): no masked copy of y for the mean
        mean = jnp.sum(y) / n
        yc = y - mean
    # phase x[0..n] (x[0] = 0), then zeros so that every window below stays in bounds
    x = jnp.concatenate([prefix_sums(yc[:, None])[:, 0] * dt,
                         jnp.zeros((nblocks * blk - n - 1 + 2 * mmax,), y.dtype)])
    mc = jnp.clip(m, 1, mmax)  # larger m are NaN below; clipped only to stay in bounds
    count = n_valid + 1 - 2 * m

    def block(acc, start):
        window = lambda off: jax.lax.dynamic_slice(x, (start + off,), (blk,))  # noqa: E731
        d = jax.vmap(window)(2 * mc) - 2.0 * jax.vmap(window)(mc) + window(0)[None, :]
        i = start + jax.lax.broadcasted_iota(count.dtype, (k, blk), 1)
        return acc + jnp.sum(jnp.where(i < count[:, None], d * d, 0.0), axis=1), None

    s, _ = jax.lax.scan(block, jnp.zeros((k,), y.dtype), jnp.arange(nblocks) * blk)
    good = (count > 1) & (m * stop_ratio <= n_valid) & (m >= 1)
    adev = jnp.sqrt(s / (2.0 * jnp.maximum(count, 1))) / (m * dt)
    return jnp.where(good, adev, jnp.nan), count


#: :func:`oadev`'s XLA options, here and where its body is compiled for a batch's size
#: (``diagnose``): XLA's loop emitters (:data:`~diffgyro._xla_options.FAST_COMPILE`): the
#: same sums bit for bit, run as fast, and compiled in about two thirds of the fusion
#: emitters' time (benchmarks/README.md, noise identification).
OADEV_OPTIONS = FAST_COMPILE


@filter_jit(compiler_options=OADEV_OPTIONS)  # (kept traced on disk under the command line)
def oadev(
    y: Float[Array, "... n"],
    dt: Float[Array, "..."] | float,
    m: Int[Array, " k"],
    n_valid: Int[Array, "..."] | None = None,
    stop_ratio: int = STOP_RATIO,
) -> tuple[Float[Array, "... k"], Int[Array, "... k"]]:
    """Overlapping Allan deviation at ``τ = m·dt`` for every leading index of ``y``.

    ``n_valid`` (default: all) counts the real samples of each padded series;
    ``dt`` broadcasts against the leading axes. Returns (adev, count): count is
    the number of overlapping second differences, N + 1 − 2m. Entries with
    fewer than 2 terms or ``m > n_valid / stop_ratio`` are NaN.

    **Arguments:**

    - ``y``: the rates (..., n).
    - ``dt``: the sample interval, s.
    - ``m``: the cluster sizes (k,).
    - ``n_valid``: the real samples of each padded series (default: all).
    - ``stop_ratio``: the longest cluster is ``n_valid / stop_ratio`` samples.
    """
    y = jnp.asarray(y)
    lead = y.shape[:-1]
    n = y.shape[-1]
    nv = jnp.broadcast_to(jnp.asarray(n if n_valid is None else n_valid), lead)
    dtb = jnp.broadcast_to(jnp.asarray(dt, y.dtype), lead)
    m = jnp.asarray(m)
    flat = (y.reshape(-1, n), nv.reshape(-1), dtb.reshape(-1))
    cpu = jax.default_backend() == "cpu"
    chunk, terms = ((_CHUNK_SAMPLES, _BLOCK_TERMS) if cpu
                    else (_ACCEL_CHUNK_SAMPLES, _ACCEL_BLOCK_TERMS))
    series = flat[0].shape[0]
    batch = max(1, min(series, chunk // max(n, 1)))
    f = lambda yy, nn, dd: _oadev_one(yy, nn, dd, m, stop_ratio, batch, terms,  # noqa: E731
                                      n_valid is not None)
    # the same steps in batches of one size: a remainder would be a second copy of the loop
    # in the program, compiled again. The blocks stay those of ``batch``, so every series'
    # sums are the same bit for bit; the last batch is filled with copies of the first
    # series, dropped
    steps = -(-series // batch)
    even = -(-series // steps)
    fill = steps * even - series
    if fill:
        flat = tuple(jnp.concatenate([a, jnp.repeat(a[:1], fill, axis=0)]) for a in flat)
    # batch_size=1 would copy the whole input into the loop state; a plain map does not
    adev, count = jax.lax.map(lambda a: f(*a), flat, batch_size=even if even > 1 else None)
    return adev[:series].reshape(*lead, -1), count[:series].reshape(*lead, -1)
