"""The model-free white-noise level the decision uses, and the temperature read-out's resolution."""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import Bool, Float

from ..data import Batch
from ..noise import sigma_from_differences


def white_noise_rms(
    y: Float[np.ndarray, "n 3"],
    mask: Bool[np.ndarray, " n"],
    rate: Float[np.ndarray, "n 3"] | None = None,
) -> Float[np.ndarray, " 3"]:
    """White-noise σ per axis of ``y = gyro − rate``, without any model: the level
    the decision measures held-out errors against (``white_noise_rms`` in the JSON).

    The reported ``noise_floor`` (:mod:`diffgyro.noise`, the same in ``fit``) on
    the lag-1 differences, with two guards the decision needs: pairs where the
    reference rate jumps (a rate table spinning up, where a scale-factor error
    would leak in) are left out, and the same on lag-2 differences guards
    against output samples that are correlated (a sensor's internal low-pass
    filter): the larger is kept.
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


# --------------------------------------------------------------------------- temperature read-out


def temperature_quantum(temp: np.ndarray) -> float:
    """Read-out step of a quantised temperature (°C), 0 when it is not quantised.

    Quantised read-outs change by whole steps: the nonzero successive
    differences are (within 5 %) integer multiples of their median.
    """
    temp = np.asarray(temp, float)
    d = np.abs(np.diff(temp[np.isfinite(temp)]))
    nz = d[d > 1e-9]
    if nz.size < 10:
        return 0.0
    q = float(np.median(nz))
    r = nz / q
    return q if np.mean(np.abs(r - np.round(r)) < 0.05) >= 0.9 else 0.0


def suggest_dtemp_window(batch: Batch, default: float = 60.0) -> float:
    """dT/dt window (s) for a batch: wide enough that read-out noise and steps do not flip
    the heating/cooling latch or swamp the gradient column.

    The centred slope over ``W`` seconds of a read-out with noise σ_T (or a
    quantised one, σ_T ≈ step/√12) has σ ≈ σ_T·√(12/(f_s·W³)); ``W`` is
    chosen so that this is a fifth of the latch's threshold (0.05 °C/min),
    never below ``default``, then rounded up to 60, 90, 120, 180, 240, 360,
    480 or 600 s (few distinct values: each compiles once).
    """
    from ..signals import HEATING_THRESHOLD

    if batch.temp is None:
        return default
    need = default
    for i in range(batch.n_devices):
        n = int(batch.n_valid[i])
        temp = np.asarray(batch.temp[i, :n], float)
        if n < 10:
            continue
        q = temperature_quantum(temp)
        d = np.diff(temp)
        sigma = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
        sigma = max(sigma, q / math.sqrt(12.0))
        fs = 1.0 / max(float(np.median(np.diff(batch.t[i, :n]))), 1e-9)
        if sigma > 0:
            w = (5.0 * sigma * math.sqrt(12.0 / fs) / HEATING_THRESHOLD) ** (2.0 / 3.0)
            need = max(need, w)
    for w in (60.0, 90.0, 120.0, 180.0, 240.0, 360.0, 480.0, 600.0):
        if w >= need:
            return max(w, default)
    return 600.0
