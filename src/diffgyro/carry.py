"""A calibration carried to another recording of the same unit: its residual against the
noise floor, the honest test of a model (a discovered term above all).

The residual is the compensated rate minus the reference rate (``rx, ry, rz``), or minus
zero for a recording without one (a static unit, whose Earth rate the bias holds when it
was calibrated in the same place). The floor is the model-free white-noise σ of the
recording (:mod:`diffgyro._noise`, the one ``fit`` reports). A ratio near 1 says the
calibration removes every deterministic error of the new recording; well above 1, the
model fitted noise or a profile-specific effect, or the unit changed.
"""

from __future__ import annotations

import math

import numpy as np

from . import _noise as noise
from ._jsonio import number
from .data import Batch

__all__ = ["residuals"]


def residuals(corrected: Batch, original: Batch) -> list[dict]:
    """Per device of ``corrected`` (``calibration.compensate``'s output for ``original``):
    ``residual_rms`` and per axis, ``noise_floor`` and per axis (rad/s), their ``ratio`` and
    ``against`` (``"rate"`` or ``"zero"``); strict-JSON numbers (None when not given).

    **Arguments:**

    - ``corrected``: the compensated batch.
    - ``original``: the batch as loaded (its reference rate, if any, and noise floor)."""

    gyro = np.asarray(original.gyro, np.float64)
    rate = None if original.rate is None else np.asarray(original.rate, np.float64)
    mask = np.asarray(original.mask, bool)
    floor_axes = noise.noise_axes(gyro, rate, mask)
    e = np.asarray(corrected.gyro, np.float64) - (0.0 if rate is None else rate)
    out = []
    for i, dev in enumerate(corrected.devices):
        m = mask[i]
        ei = e[i][m]
        axes = np.sqrt(np.mean(ei**2, axis=0)) if ei.size else np.full(3, np.nan)
        rms = float(np.sqrt(np.mean(axes**2)))
        fl = float(np.sqrt(np.mean(floor_axes[i] ** 2)))
        ratio = rms / fl if fl > 0 and math.isfinite(fl) else math.nan
        out.append({"device": dev, "residual_rms": number(rms),
                    "residual_rms_axes": [number(float(v)) for v in axes],
                    "noise_floor": number(fl),
                    "noise_floor_axes": [number(float(v)) for v in floor_axes[i]],
                    "ratio": number(ratio), "against": "zero" if rate is None else "rate"})
    return out
