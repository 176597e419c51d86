"""fog-one-run (fibre-optic gyro patent): one thermal-chamber run calibrates scale factor and bias together.

The published procedure (fibre-optic gyro on a rate table in a chamber):

1. the run: cool to ``T_min``, then step up by 10 °C; at every soak the
   table turns clockwise, then counter-clockwise, at ``ω``; the gyro output
   ``D``, the coil's internal temperature ``T_in`` and an outside
   temperature ``T_out`` are logged throughout;
2. ``dT_in(t)`` = mean of ``T_in`` over the last ``2^n`` samples minus the
   mean over the ``2^n`` before (n = 6): :func:`diffgyro.signals.moving_average_difference`;
3. drop ``±m`` samples around every change of sign of the rate (the table
   is still accelerating there, the input rate is unknown);
4. least squares ``y = X·A`` with ``y = K0·Ω`` and
   ``X = [D, T_in·D, T_in²·D, T_in, T_in − T_out, dT_in]``,
   ``A = [a0, a1, a2, b1, b2, b3]``;
5. compensated output
   ``(a0 + a1·T_in + a2·T_in²)·D + b1·T_in + b2·(T_in − T_out) + b3·dT_in``.

The published model is the *inverse* one (true rate from the output) and has
no constant term; both are kept. One axis at a time (the table's). The sign
changes are taken from the reference rate's sign (−1, 0, +1) by default —
the table's direction changes, which is what the step removes; ``signs_from =
"gyro"`` takes them from the sign of ``D`` literally, which also removes
every zero crossing of a static output.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..signals import moving_average_difference
from ._common import RecipeResult

COLUMNS = ("D", "T*D", "T^2*D", "T", "T-T_out", "dT")


@dataclass(frozen=True)
class FogOneRunResult(RecipeResult):
    """The coefficient vector ``A`` and where the regression looked."""

    coefficients: np.ndarray    # (6,) a0, a1, a2, b1, b2, b3
    columns: tuple
    axis: int
    k0: float
    n_avg: int
    m: int
    kept: np.ndarray            # (n,) bool: samples used in the regression
    rms: float                  # RMS of y − X·A over the kept samples

    name = "fog-one-run"

    def to_dict(self) -> dict:
        out = {k: v for k, v in super().to_dict().items() if k != "kept"}
        out["n_kept"] = int(np.sum(self.kept))
        out["n_removed"] = int(self.kept.size - np.sum(self.kept))
        return out

    def design(self, d: np.ndarray, temp: np.ndarray, temp_ext: np.ndarray) -> np.ndarray:
        return s2_design(d, temp, temp_ext, self.n_avg)

    def compensate(self, d: np.ndarray, temp: np.ndarray, temp_ext: np.ndarray) -> np.ndarray:
        """The published compensated output ``X·A`` (in ``K0·Ω`` units)."""
        return self.design(d, temp, temp_ext) @ self.coefficients


def s2_design(d: np.ndarray, temp: np.ndarray, temp_ext: np.ndarray, n_avg: int) -> np.ndarray:
    """``[D, T·D, T²·D, T, T − T_out, dT]`` with the patent's moving-average-difference dT."""
    d = np.asarray(d, float)
    temp = np.asarray(temp, float)
    dtemp = np.asarray(moving_average_difference(jnp.asarray(temp), int(n_avg)))
    return np.stack([d, temp * d, temp**2 * d, temp, temp - np.asarray(temp_ext, float), dtemp],
                    axis=1)


def sign_change_mask(sign: np.ndarray, m: int) -> np.ndarray:
    """False within ``m`` samples of every change of ``sign``."""
    n = sign.size
    change = np.flatnonzero(np.diff(sign) != 0)
    keep = np.ones(n, bool)
    if change.size:
        # a change between samples c and c+1: drop c-m+1 .. c+m
        lo = np.clip(change - m + 1, 0, n)
        hi = np.clip(change + m + 1, 0, n)
        delta = np.zeros(n + 1, int)
        np.add.at(delta, lo, 1)
        np.add.at(delta, hi, -1)
        keep = np.cumsum(delta[:-1]) == 0
    return keep


def fog_one_run(
    gyro: np.ndarray,
    temp: np.ndarray,
    temp_ext: np.ndarray,
    rate: np.ndarray,
    *,
    axis: int = 2,
    k0: float = 1.0,
    n: int = 6,
    m: int = 50,
    signs_from: str = "rate",
    rate_deadband: float = 1e-3,
) -> FogOneRunResult:
    """Fit fog-one-run's six coefficients for one gyro axis.

    ``gyro``/``rate``: ``(N, 3)`` (or ``(N,)`` for the axis alone); ``k0`` is
    the room-temperature scale factor (output units per rad/s; 1 for data
    already in rad/s); ``n``: dT over ``2^n`` samples; ``m``: samples removed
    on each side of a sign change; rates within ``rate_deadband`` (rad/s) of
    zero count as sign 0 (table at rest).

    **Arguments:**

    - ``gyro``: the gyro's output (N, 3), or (N,) for the axis alone.
    - ``temp``: the internal temperature (N,), °C.
    - ``temp_ext``: the external temperature (N,), °C.
    - ``rate``: the table's rate (N, 3), or (N,), rad/s.
    - ``axis``: the table's axis.
    - ``k0``: the room-temperature scale factor.
    - ``n``: dT is taken over ``2^n`` samples.
    - ``m``: samples removed on each side of a sign change.
    - ``signs_from``: ``"rate"`` (the table's direction) or ``"gyro"`` (the sign of ``D``).
    - ``rate_deadband``: the rate (rad/s) within which the table counts as at rest.
    """
    d = np.asarray(gyro, float)
    om = np.asarray(rate, float)
    d = d[:, axis] if d.ndim == 2 else d
    om = om[:, axis] if om.ndim == 2 else om
    n_avg = 2 ** int(n)
    if signs_from == "rate":
        sign = np.sign(np.where(np.abs(om) > rate_deadband, om, 0.0))
    elif signs_from == "gyro":
        sign = np.sign(d)
    else:
        raise DataError(f"signs_from must be 'rate' or 'gyro', not {signs_from!r}")
    x = s2_design(d, temp, temp_ext, n_avg)
    y = k0 * om
    kept = sign_change_mask(sign, int(m))
    kept[: 2 * n_avg - 1] = False     # dT is defined from sample 2·2^n − 1 on
    if kept.sum() < 6 * 10:
        raise DataError(f"only {int(kept.sum())} samples left after removing ±{m} samples "
                        "around the sign changes", hint="lower m or record longer")
    scale = np.linalg.norm(x[kept], axis=0)
    scale[scale == 0] = 1.0
    a, _, rank, _ = np.linalg.lstsq(x[kept] / scale, y[kept], rcond=None)
    if rank < 6:
        raise DataError("fog-one-run's six columns are not independent on these data",
                        hint="the run needs rotations at several temperatures and temperature "
                        "changes (dT) and an inside-outside difference")
    a = a / scale
    resid = y[kept] - x[kept] @ a
    return FogOneRunResult(coefficients=a, columns=COLUMNS, axis=int(axis), k0=float(k0),
                           n_avg=n_avg, m=int(m), kept=kept, rms=float(np.sqrt(np.mean(resid**2))))
