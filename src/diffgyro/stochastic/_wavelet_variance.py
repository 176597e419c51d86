"""Empirical Haar wavelet variance on dyadic scales, from the overlapping Allan variance.

At cluster size ``m = 2^j`` (τ = m·dt) the MODWT Haar coefficient of a rate
series is half the difference of two adjacent means of m samples; the mean of
its square over every position is half the overlapping Allan variance. The
latter comes from :func:`diffgyro.allan.oadev`: one prefix sum of the series,
then O(n) per scale, every device and axis in one call. Scales run from
m = 1 while ``m ≤ n/4`` (Stable32's stop ratio): longer clusters have too few
terms to say anything.
"""

from __future__ import annotations

import math
import threading

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ..allan import STOP_RATIO, oadev


def n_scales(n: int) -> int:
    """Dyadic scales m = 1, 2, 4 … with m ≤ n/4 (at least 1)."""
    return max(1, int(math.floor(math.log2(max(n // STOP_RATIO, 1)))) + 1)


def dyadic_m(n: int) -> np.ndarray:
    """Cluster sizes 1, 2, 4, … ≤ n/4."""
    return (2 ** np.arange(n_scales(n))).astype(np.int64)


def haar_wv(y: Float[Array, "... n"], dt, n_valid: Int[Array, "..."] | None = None,
            m: Int[Array, " J"] | None = None) -> tuple[Float[Array, "... J"], Int[Array, "... J"]]:
    """Haar wavelet variance (rad²/s²) at τ = m·dt for every leading index of ``y``, and the
    number of terms averaged at each scale, as numpy arrays (one compiled program, no
    eager operation after it). NaN where a series is too short for the scale."""
    y = jnp.asarray(y)
    if m is None:
        m = dyadic_m(y.shape[-1])
    adev, count = oadev(y, dt, np.asarray(m), n_valid)
    adev = np.asarray(adev)
    return 0.5 * adev**2, np.asarray(count)


def haar_wv_ahead(lead: tuple[int, ...], n: int) -> threading.Thread:
    """Start compiling (or reading from the persistent cache) the program :func:`haar_wv`
    runs for float64 series of shape ``lead + (n,)`` with a float64 interval per series
    and no ``n_valid``, on a thread of its own; join it before the call."""
    spec = jax.ShapeDtypeStruct
    m = dyadic_m(n)
    return oadev.compile_ahead(
        spec((*lead, n), np.dtype(np.float64)), spec(tuple(lead), np.dtype(np.float64)),
        spec(m.shape, m.dtype), None)
