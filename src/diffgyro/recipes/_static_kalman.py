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
published. The filter itself is :func:`offset_filter`; :func:`heading_errors`
compares it with the learned random walk (:mod:`diffgyro.kalman`).

Heading: ``yaw_*`` integrate the corrected z rate (the published level-
vehicle heading). With a reference attitude (``quat``), ``heading_error_*``
integrate the full corrected rate vector from the reference's first
attitude and take the heading part of the difference
(:func:`diffgyro._reference.heading_error`).
"""

from __future__ import annotations

from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._reference import heading_error, integrate_gyro
from ..errors import DataError
from ..kalman import causal_bias, profile, rts_smoother, rw_filter
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
    """Run static-kalman on one recording (rates in rad/s); ``quat`` is an optional reference attitude.

    **Arguments:**

    - ``gyro``: the measured rate (n, 3), rad/s.
    - ``accel``: the specific force (n, 3).
    - ``t``: sample times (n,), s.
    - ``quat``: a reference attitude (n, 4) (default: none; heading from the z rate alone).
    - ``init``: samples of the factory rest at the start.
    - ``window``: samples per window.
    - ``margin``: the static thresholds' margin ``M``.
    - ``q``: the filter's ``Q``, in ``(q_unit)²``.
    - ``q_unit``: ``"deg/s"`` or ``"rad/s"``.
    """
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
    tracks = [offset_filter(jnp.asarray(gyro[:, i]), jnp.asarray(static), window, init, q_si)
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


# --------------------------------------------------------------------------- the offset filter


class OffsetTrack(eqx.Module):
    """static-kalman's offset track: per window ``x`` (offset after the update) and ``p``; per sample
    ``offset`` (the offset in force while that sample is read: the last update before it)."""

    x: Float[Array, " k"]
    p: Float[Array, " k"]
    offset: Float[Array, " n"]


def offset_filter(
    rz: Float[Array, " n"],
    static: Bool[Array, " k"],
    window: int,
    init: int = 1000,
    q: float = 1e-4,
) -> OffsetTrack:
    """static-kalman's scalar Kalman filter of the z-rate offset (faithful to the patent).

    Initial window (the first ``init`` samples, 5 s static at the factory):
    ``X(0|0) = E(0) = mean``, ``P(0|0) = COV(0) = var``. After it, windows of
    ``window`` samples; window j (``static[j]``, e.g. from
    :func:`diffgyro.detect.s1_range_detector`) updates with ``E = mean``,
    ``R = COV = var`` of its samples, ``P ← P + Q``, ``Kg = P/(P+R)``;
    a non-static window leaves the filter unchanged. ``q`` is the patent's fixed
    ``Q = 1e-4`` in the units of ``rz``. The per-sample offset is causal:
    the samples of window j are corrected with the offset after window j−1.
    """
    rz = jnp.asarray(rz)
    n = rz.shape[0]
    k = (n - init) // window
    win = rz[init:init + k * window].reshape(k, window)
    e = jnp.mean(win, axis=1)
    cov = jnp.var(win, axis=1)
    x0 = jnp.mean(rz[:init])
    p0 = jnp.var(rz[:init])
    st = jnp.asarray(static)[:k]

    def step(carry, inp):
        x, p = carry
        ek, rk, ok = inp
        pp = p + q
        kg = pp / (pp + rk)
        xn = jnp.where(ok, x + kg * (ek - x), x)
        pn = jnp.where(ok, (1.0 - kg) * pp, p)
        return (xn, pn), (xn, pn)

    _, (xs, ps) = jax.lax.scan(step, (x0, p0), (e, cov, st))
    before = jnp.concatenate([x0[None], xs[:-1]]) if k > 0 else jnp.zeros((0,), rz.dtype)
    per_window = jnp.repeat(before, window)
    tail = jnp.full((n - init - k * window,), xs[-1] if k > 0 else x0, rz.dtype)
    offset = jnp.concatenate([jnp.full((init,), x0, rz.dtype), per_window, tail])
    return OffsetTrack(x=xs, p=ps, offset=offset)


# --------------------------------------------------------------------------- compared with the learned random walk


def heading_errors(
    t: Float[Array, " n"],
    gz: Float[Array, " n"],
    rz: Float[Array, " n"],
    static: Bool[Array, " n"],
    q: float,
    r: float,
    *,
    window: int,
    init: int = 1000,
    q_static: float = 1e-4,
) -> dict[str, Float[Array, " n"]]:
    """Heading (yaw) error over time of one z gyro under five bias treatments.

    ``none``: raw rate integrated; ``fixed``: the factory offset E(0) of the
    first ``init`` samples held for ever; ``static_kalman``: the recipe's tracked offset with
    its fixed ``Q = q_static`` (windows of ``window`` samples, static where every sample of
    the window is); ``learned``: the causal Kalman filter with the learned
    ``q``, ``r`` (what a device could run live); ``smoothed``: the RTS
    smoother with the same q, r (post-processing, uses the future too).
    Heading error = ∫ (corrected rate − true rate) dt, trapezoidal, rad.

    **Arguments:**

    - ``t``: sample times (n,), s.
    - ``gz``: the measured z rate (n,), rad/s.
    - ``rz``: the true z rate (n,), rad/s.
    - ``static``: the samples at rest (n,).
    - ``q``: the learned random walk's process variance.
    - ``r``: the learned measurement noise variance.
    - ``window``: samples per window of the recipe's filter.
    - ``init``: samples of the factory rest at the start.
    - ``q_static``: the recipe's fixed ``Q``, (rad/s)².
    """
    gz = jnp.asarray(gz)
    return _heading_errors(jnp.asarray(t, gz.dtype), gz, jnp.asarray(rz, gz.dtype),
                           jnp.asarray(static, bool), jnp.asarray(q, gz.dtype),
                           jnp.asarray(r, gz.dtype), jnp.asarray(q_static, gz.dtype), window, init)


@eqx.filter_jit
def _heading_errors(t, gz, rz, static, q, r, q_static, window, init):
    n = gz.shape[0]
    k = (n - init) // window
    win_static = jnp.all(static[init:init + k * window].reshape(k, window), axis=1)
    tracked = offset_filter(gz, win_static, window, init, q_static)
    e0 = jnp.mean(gz[:init])
    pred, _ = causal_bias(gz, static, t, q, r, e0, jnp.var(gz[:init]) / init)
    fp = rw_filter(gz, jnp.ones((n, 1), gz.dtype), static, t, q, r, 0.0)
    _, beta, _ = profile(fp, static)
    walk, _ = rts_smoother(fp, beta)

    def integrate(err):
        inc = 0.5 * (err[1:] + err[:-1]) * jnp.diff(t)
        return jnp.concatenate([jnp.zeros((1,), err.dtype), jnp.cumsum(inc)])

    return {
        "none": integrate(gz - rz),
        "fixed": integrate(gz - e0 - rz),
        "static_kalman": integrate(gz - tracked.offset - rz),
        "learned": integrate(gz - pred - rz),
        "smoothed": integrate(gz - beta[0] - walk - rz),
    }
