"""The non-overlapping and modified Allan deviations (NIST SP 1065 §5.2.2, §5.2.5), in numpy
on the same phase as :func:`~diffgyro.allan.oadev`: for comparison with published tables and
other tools."""

from __future__ import annotations

import numpy as np
from jaxtyping import Float, Int


def _phase(y: np.ndarray, dt: float) -> np.ndarray:
    """The phase (angle) ``x = dt·[0, cumsum(y − mean y)]`` of a rate series (n + 1 points)."""
    y = np.asarray(y, dtype=np.float64)
    yc = y - y.mean(axis=-1, keepdims=True)  # the deviations ignore the mean; x stays small
    zero = np.zeros(y.shape[:-1] + (1,))
    return np.concatenate([zero, np.cumsum(yc, axis=-1) * dt], axis=-1)


def adev_nonoverlapping(y: Float[np.ndarray, "... n"], dt: float,
                        m: Int[np.ndarray, " k"]) -> Float[np.ndarray, "... k"]:
    """Non-overlapping Allan deviation of ``y`` (..., n) at τ = m·dt; NaN where K < 1::

        σ²(τ) = 1 / (2 τ² K) · Σ_j (x[(j+2)m] − 2 x[(j+1)m] + x[jm])²,  K = ⌊n/m⌋ − 1

    **Arguments:**

    - ``y``: the rates (..., n).
    - ``dt``: the sample interval, s.
    - ``m``: the cluster sizes (k,).
    """
    x = _phase(y, dt)
    n = x.shape[-1] - 1
    out = np.full(x.shape[:-1] + (len(m),), np.nan)
    for j, mj in enumerate(np.asarray(m, dtype=np.int64)):
        k = n // mj - 1
        if mj < 1 or k < 1:
            continue
        xd = x[..., : (k + 2) * mj : mj]  # x[0], x[m], ..., x[(K+1)m]
        d = xd[..., 2:] - 2.0 * xd[..., 1:-1] + xd[..., :-2]
        out[..., j] = np.sqrt(np.sum(d * d, axis=-1) / (2.0 * k)) / (mj * dt)
    return out


def mdev(y: Float[np.ndarray, "... n"], dt: float,
         m: Int[np.ndarray, " k"]) -> Float[np.ndarray, "... k"]:
    """Modified Allan deviation of ``y`` (..., n) at τ = m·dt; NaN where N − 3m + 1 < 1::

        Mod σ²(τ) = 1 / (2 m² τ² (N − 3m + 1)) · Σ_j (Σ_{i=j}^{j+m−1} x[i+2m] − 2 x[i+m] + x[i])²

    with N = n + 1 phase points.

    **Arguments:**

    - ``y``: the rates (..., n).
    - ``dt``: the sample interval, s.
    - ``m``: the cluster sizes (k,).
    """
    x = _phase(y, dt)
    big_n = x.shape[-1]
    out = np.full(x.shape[:-1] + (len(m),), np.nan)
    for j, mj in enumerate(np.asarray(m, dtype=np.int64)):
        count = big_n - 3 * mj + 1
        if mj < 1 or count < 1:
            continue
        d = x[..., 2 * mj:] - 2.0 * x[..., mj:-mj] + x[..., : big_n - 2 * mj]
        c = np.concatenate([np.zeros(d.shape[:-1] + (1,)), np.cumsum(d, axis=-1)], axis=-1)
        s = c[..., mj:] - c[..., :-mj]  # the m-term window sums, N − 3m + 1 of them
        out[..., j] = np.sqrt(np.sum(s * s, axis=-1) / (2.0 * count)) / (mj * mj * dt)
    return out
