"""The model-free white-noise level the decision uses."""

from __future__ import annotations

import numpy as np
from jaxtyping import Bool, Float

from .._noise import sigma_from_differences


def white_noise_rms(
    y: Float[np.ndarray, "n 3"],
    mask: Bool[np.ndarray, " n"],
    rate: Float[np.ndarray, "n 3"] | None = None,
) -> Float[np.ndarray, " 3"]:
    """White-noise σ per axis of ``y = gyro − rate``, without any model: the level
    the decision measures held-out errors against (``white_noise_rms`` in the JSON).

    The reported ``noise_floor`` (:mod:`diffgyro._noise`, the same in ``fit``) on
    the lag-1 differences, with two guards the decision needs: pairs where the
    reference rate jumps (a rate table spinning up, where a scale-factor error
    would leak in) are left out, and the same on lag-2 differences guards
    against output samples that are correlated (a sensor's internal low-pass
    filter): the larger is kept.

    **Arguments:**

    - ``y``: gyro − rate (n, 3), or the gyro at rest.
    - ``mask``: which samples are valid (n,).
    - ``rate``: the reference rate (n, 3), whose jumps are left out; None: no reference.
    """
    y = np.asarray(y, np.float64)
    mask = np.asarray(mask, bool)
    rate = None if rate is None else np.asarray(rate, np.float64)
    out = []
    for lag in (1, 2):
        d = y[lag:] - y[:-lag]
        ok = mask[lag:] & mask[:-lag]
        if rate is not None and ok.any():
            dr = np.linalg.norm(rate[lag:] - rate[:-lag], axis=-1)
            calm = ok & (dr <= 30.0 * np.max(_mad(d[ok])))
            ok = calm if calm.sum() >= 0.2 * ok.sum() else ok
        if not ok.any():
            out.append(np.zeros(y.shape[1]))
            continue
        out.append(sigma_from_differences(np.ascontiguousarray(d.T), ok[None]))
    return np.maximum(out[0], out[1])


def _mad(d: np.ndarray) -> np.ndarray:
    """1.4826 × the median absolute deviation of each column of ``d`` (m, 3)."""
    if d.shape[0] == 0:
        return np.full(d.shape[1:], np.nan)
    return 1.4826 * np.median(np.abs(d - np.median(d, axis=0)), axis=0)
