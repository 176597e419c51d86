"""The temperature read-out: its quantisation step, and the dT/dt window it needs.

A coarse or noisy read-out makes the centred slope that gives dT/dt noisy; the
window that slope spans (``dtemp_window``) is chosen from the read-out, the same
way for ``diffgyro fit`` and for diagnose.
"""

from __future__ import annotations

import math

import numpy as np

from .data import Batch
from .signals import HEATING_THRESHOLD


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
