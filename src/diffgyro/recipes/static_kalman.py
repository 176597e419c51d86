"""static-kalman (Wuxi Lingsi patent, 2018): track the zero-rate offset in static windows.

The published procedure, on all three axes (the patent writes it for z):

1. factory rest: the first ``init`` samples (1000, 5 s) give
   ``E(0) = mean``, ``COV(0) = var`` of the rate;
2. static thresholds from that same window, per signal
   ``T = M · (max − min)`` for Ax, Ay, Az and the rates (``M``, the margin,
   is chosen for the environment);
3. in use, windows of ``window`` samples; a window is *static* when the
   peak-to-peak range of every signal stays below its threshold;
4. for the k-th static window ``E(k) = mean``, ``COV(k) = var`` and a scalar
   Kalman update of the offset (random walk): ``P ← P + Q`` with
   ``Q = 1e−4``, ``Kg = P / (P + R(k))``, ``R(k) = COV(k)``,
   ``X ← X + Kg·(E(k) − X)``, ``P ← (1 − Kg)·P``; ``X(0) = E(0)``,
   ``P(0) = COV(0)``. Non-static windows leave the filter alone;
5. the corrected rate ``R − Offset`` is integrated to heading (yaw).

``Q`` is published without a unit; here it is in ``(q_unit)²`` (default
(°/s)², the unit such sensors report) and converted to (rad/s)². ``R(k)``
is the variance of the window's samples, not of its mean, exactly as
published. The filter itself is :func:`diffgyro.kalman.s1_offset_filter`.

Heading: ``yaw_*`` integrate the corrected z rate (the published level-
vehicle heading). With a reference attitude (``quat``), ``heading_error_*``
integrate the full corrected rate vector from the reference's first
attitude and take the heading part of the difference
(:func:`diffgyro.reference.heading_error`).
"""

from __future__ import annotations

from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..kalman import s1_offset_filter
from ..reference import heading_error, integrate_gyro
from ._common import RecipeResult

UNITS = {"rad/s": 1.0, "deg/s": np.pi / 180.0, "dps": np.pi / 180.0}


@dataclass(frozen=True)
class StaticKalmanResult(RecipeResult):
    """Thresholds, static windows, the offset trajectory and heading with and without it."""

    thresholds: np.ndarray      # (6,) ax, ay, az, gx, gy, gz
    window_start: np.ndarray    # (k,) first sample of each window after the initial one
    static: np.ndarray          # (k,) bool
    offset_track: np.ndarray    # (k, 3) X(k|k) after each window
    variance_track: np.ndarray  # (k, 3) P(k|k)
    initial_offset: np.ndarray  # (3,) E(0)
    offset: np.ndarray          # (n, 3) offset in force at each sample (causal)
    t: np.ndarray               # (n,)
    yaw_raw: np.ndarray         # (n,) ∫ gz
    yaw_fixed: np.ndarray       # (n,) ∫ (gz − E(0))
    yaw_tracked: np.ndarray     # (n,) ∫ (gz − offset)
    heading_error_raw: np.ndarray | None      # (n,) vs the reference attitude
    heading_error_fixed: np.ndarray | None
    heading_error_tracked: np.ndarray | None
    margin: float
    window: int
    q: float                    # (rad/s)²

    name = "static-kalman"

    def compensate(self, gyro: np.ndarray) -> np.ndarray:
        return np.asarray(gyro) - self.offset

    def to_dict(self) -> dict:
        """Per-window tracks and heading summaries (per-sample arrays stay on the object)."""
        per_sample = {"offset", "t", "yaw_raw", "yaw_fixed", "yaw_tracked", "heading_error_raw",
                      "heading_error_fixed", "heading_error_tracked"}
        out = {k: v for k, v in super().to_dict().items() if k not in per_sample}
        out["n_static_windows"] = int(np.sum(self.static))
        out["duration"] = float(self.t[-1] - self.t[0])
        out["yaw_end"] = {"raw": float(self.yaw_raw[-1]), "fixed": float(self.yaw_fixed[-1]),
                          "tracked": float(self.yaw_tracked[-1])}
        if self.heading_error_tracked is not None:
            out["heading_error"] = {
                name: {"final": float(e[np.isfinite(e)][-1]), "worst": float(np.nanmax(np.abs(e)))}
                for name, e in (("raw", self.heading_error_raw), ("fixed", self.heading_error_fixed),
                                ("tracked", self.heading_error_tracked))}
        return out


def window_thresholds(accel: np.ndarray, gyro: np.ndarray, init: int, margin: float) -> np.ndarray:
    """``M·(max − min)`` of Ax, Ay, Az, Rx, Ry, Rz over the initial static window."""
    sig = np.concatenate([accel[:init], gyro[:init]], axis=1)
    return margin * (sig.max(0) - sig.min(0))


def static_windows(accel: np.ndarray, gyro: np.ndarray, thresholds: np.ndarray, init: int,
                   window: int) -> np.ndarray:
    """Per window after the initial one: every signal's peak-to-peak below its threshold."""
    sig = np.concatenate([accel, gyro], axis=1)
    k = (sig.shape[0] - init) // window
    win = sig[init:init + k * window].reshape(k, window, 6)
    return np.all(win.max(1) - win.min(1) < thresholds, axis=1)


def _integrate(t: np.ndarray, rate: np.ndarray) -> np.ndarray:
    """Rectangle-rule integral, rate held over each interval, starting at 0."""
    return np.concatenate([[0.0], np.cumsum(rate[:-1] * np.diff(t))])


def static_kalman(
    gyro: np.ndarray,
    accel: np.ndarray,
    t: np.ndarray,
    *,
    quat: np.ndarray | None = None,
    init: int = 1000,
    window: int = 100,
    margin: float = 1.5,
    q: float = 1e-4,
    q_unit: str = "deg/s",
) -> StaticKalmanResult:
    """Run static-kalman on one recording (rates in rad/s); ``quat`` is an optional reference attitude."""
    gyro = np.asarray(gyro, float)
    accel = np.asarray(accel, float)
    t = np.asarray(t, float)
    n = gyro.shape[0]
    if q_unit not in UNITS:
        raise DataError(f"unknown unit {q_unit!r} for Q", hint="rad/s or deg/s")
    if n < init + window:
        raise DataError(f"static-kalman needs at least {init + window} samples, the data has {n}",
                        hint="the first samples must be a factory rest of --init samples")
    q_si = float(q) * UNITS[q_unit] ** 2
    thresholds = window_thresholds(accel, gyro, init, margin)
    static = static_windows(accel, gyro, thresholds, init, window)
    tracks = [s1_offset_filter(jnp.asarray(gyro[:, i]), jnp.asarray(static), window, init, q_si)
              for i in range(3)]
    x = np.stack([np.asarray(tr.x) for tr in tracks], axis=1)
    p = np.stack([np.asarray(tr.p) for tr in tracks], axis=1)
    offset = np.stack([np.asarray(tr.offset) for tr in tracks], axis=1)
    e0 = gyro[:init].mean(0)
    he = [None, None, None]
    if quat is not None:
        q_ref = jnp.asarray(quat, jnp.float64)
        ok = np.all(np.isfinite(quat), axis=1)
        if not ok[0]:
            raise DataError("the reference attitude must be known at the first sample")
        he = []
        for rate in (gyro, gyro - e0, gyro - offset):
            q_est = integrate_gyro(q_ref[0], jnp.asarray(rate), jnp.asarray(t))
            err = np.asarray(heading_error(q_est, q_ref))
            he.append(np.where(ok, err, np.nan))
    k = static.size
    return StaticKalmanResult(
        thresholds=thresholds, window_start=init + window * np.arange(k), static=static,
        offset_track=x, variance_track=p, initial_offset=e0, offset=offset, t=t,
        yaw_raw=_integrate(t, gyro[:, 2]), yaw_fixed=_integrate(t, gyro[:, 2] - e0[2]),
        yaw_tracked=_integrate(t, gyro[:, 2] - offset[:, 2]),
        heading_error_raw=he[0], heading_error_fixed=he[1], heading_error_tracked=he[2],
        margin=float(margin), window=int(window), q=q_si)
