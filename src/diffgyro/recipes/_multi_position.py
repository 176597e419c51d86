"""multi-position: accelerometer and gyro calibration from hand-placed static poses.

The method of Tedaldi, Pretto and Menegatti (ICRA 2014, IMU-TK), no turntable:

1. the recording starts at rest (``init_seconds``); the per-axis accelerometer
   variance there sets the static threshold, which is searched over
   multipliers ``2 … 10`` (:mod:`.static_intervals`);
2. accelerometer: ``a = C (a_raw − b)`` with ``C`` upper triangular (scale and
   three misalignments; the body frame is the accelerometer's) and bias ``b``,
   minimising ``Σ (g − ‖a‖)²`` over the first ``n_samples`` samples of every
   static pose (Levenberg–Marquardt, optimistix). The multiplier whose fit
   has the smallest cost wins;
3. gyroscope: bias = mean over the initial rest; ``ω = C_g (ω_raw − b_g)``
   with a full 3×3 ``C_g`` (scales and six misalignments), found by
   integrating the corrected rate over every motion between consecutive
   poses and asking that it turn the gravity direction measured before the
   motion into the one measured after it: residual ``R(C_g)ᵀ u_k − u_{k+1}``.

Starting points are found from the data (a sphere fit for the accelerometer,
a 1-D scale search for the gyro), so raw counts need no hand-set initial
values. Units: whatever the input's; ``gravity`` in the calibrated
accelerometer unit (m/s²), the gyro result in rad/s per input unit.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from .._reference import quat_conj, quat_from_rotvec, quat_mul, quat_normalize, rotate
from ..errors import DataError
from ._common import RecipeResult
from ._static_intervals import rest_variance_norm, static_intervals

GRAVITY = 9.81


@dataclass(frozen=True)
class MultiPositionResult(RecipeResult):
    """Calibration and the evidence for it (per pose, per motion)."""

    accel_matrix: np.ndarray      # (3, 3) upper triangular
    accel_bias: np.ndarray        # (3,)
    gyro_matrix: np.ndarray       # (3, 3)
    gyro_bias: np.ndarray         # (3,)
    intervals: list               # [start, end) of the static poses used
    threshold_multiplier: int
    pose_norm_error: np.ndarray   # per pose: ‖mean calibrated a over the whole pose‖ − g
    pose_norm_error_first: np.ndarray  # per pose: the same over its first n_samples
    pose_rms: float               # RMS of ‖a‖ − g over the first n_samples of every pose
    motion_residual: np.ndarray   # per motion: ‖R(C_g)ᵀ u_k − u_{k+1}‖ (rad, small-angle)
    accel_cost: float
    gravity: float

    name = "multi-position"

    @property
    def gyro_scale_counts(self) -> np.ndarray:
        """Raw units per rad/s on each axis (the inverse of the diagonal)."""
        return 1.0 / np.diag(self.gyro_matrix)

    def calibrate_accel(self, accel: np.ndarray) -> np.ndarray:
        return (np.asarray(accel) - self.accel_bias) @ self.accel_matrix.T

    def calibrate_gyro(self, gyro: np.ndarray) -> np.ndarray:
        return (np.asarray(gyro) - self.gyro_bias) @ self.gyro_matrix.T

    def to_dict(self) -> dict:
        out = super().to_dict()
        out["gyro_scale_counts"] = self.gyro_scale_counts.tolist()
        return out


# ------------------------------------------------------------------ accelerometer


def sphere_fit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and radius of the sphere through ``points`` (linear least squares)."""
    p = np.asarray(points, float)
    a = np.concatenate([2 * p, np.ones((p.shape[0], 1))], axis=1)
    sol, *_ = np.linalg.lstsq(a, (p * p).sum(1), rcond=None)
    centre = sol[:3]
    return centre, float(np.sqrt(max(sol[3] + centre @ centre, 0.0)))


def _upper(p):
    return jnp.array([[p[0], p[1], p[2]], [0.0, p[3], p[4]], [0.0, 0.0, p[5]]], dtype=p.dtype)


def _accel_residual(p, args):
    a, w, g = args
    cal = (a - p[6:9]) @ _upper(p).T
    return w * (g - jnp.linalg.norm(cal, axis=1))


@jax.jit
def _accel_solve(p0, a, w, g):
    solver = optx.LevenbergMarquardt(rtol=1e-12, atol=1e-14)
    sol = optx.least_squares(_accel_residual, solver, p0, args=(a, w, g), max_steps=200,
                             throw=False)
    r = _accel_residual(sol.value, (a, w, g))
    return sol.value, 0.5 * jnp.sum(r * r)


def _pad(x: np.ndarray, length: int, fill: float = 0.0) -> np.ndarray:
    out = np.full((length, *x.shape[1:]), fill)
    out[: x.shape[0]] = x
    return out


def fit_accel(samples: np.ndarray, gravity: float) -> tuple[np.ndarray, np.ndarray, float]:
    """``C`` (upper triangular) and ``b`` minimising ``Σ (g − ‖C (a − b)‖)²``.

    Works in normalised units (sphere-fit centre and radius) so raw counts and
    SI data converge alike.
    """
    centre, radius = sphere_fit(samples)
    if not np.isfinite(radius) or radius <= 0:
        raise DataError("static poses do not span enough directions for an accelerometer fit")
    norm = (samples - centre) / radius
    length = max(1024, 2 ** int(np.ceil(np.log2(norm.shape[0]))))  # few shapes, few compiles
    w = _pad(np.ones(norm.shape[0]), length)
    p0 = jnp.array([gravity, 0, 0, gravity, 0, gravity, 0, 0, 0], jnp.float64)
    p, cost = _accel_solve(p0, jnp.asarray(_pad(norm, length, fill=1.0)), jnp.asarray(w), gravity)
    p = np.asarray(p)
    c = np.array([[p[0], p[1], p[2]], [0, p[3], p[4]], [0, 0, p[5]]]) / radius
    b = centre + radius * p[6:9]
    return c, b, float(cost)


# ------------------------------------------------------------------ gyroscope


def _integrate(rates, dt):
    """Body rotation over one motion (padded steps have dt = 0)."""
    def step(q, wd):
        w, d = wd
        return quat_normalize(quat_mul(q, quat_from_rotvec(w * d))), None

    q0 = jnp.array([1.0, 0.0, 0.0, 0.0], rates.dtype)
    q, _ = jax.lax.scan(step, q0, (rates, dt))
    return q


def _gyro_residual(theta, args):
    raw_mid, dt, u0, u1, scale0 = args
    c = theta.reshape(3, 3) * scale0
    rates = jnp.einsum("ij,mnj->mni", c, raw_mid)
    q = jax.vmap(_integrate)(rates, dt)
    # gravity direction after the motion, predicted from the one before it
    pred = rotate(quat_conj(q), u0)
    return (pred - u1).ravel()


@jax.jit
def _gyro_solve(theta0, args):
    solver = optx.LevenbergMarquardt(rtol=1e-10, atol=1e-12)
    sol = optx.least_squares(_gyro_residual, solver, theta0, args=args, max_steps=200, throw=False)
    return sol.value


@jax.jit
def _scale_costs(scales, args):
    raw_mid, dt, u0, u1, _ = args

    def cost(s):
        r = _gyro_residual(jnp.eye(3).ravel(), (raw_mid, dt, u0, u1, s))
        return jnp.sum(r * r)

    return jax.lax.map(cost, scales)


def motions_between(intervals, t, gyro, gyro_bias, length_bucket: int = 256):
    """Padded per-motion arrays: bias-free midpoint rates and steps between poses."""
    segs = []
    for (_, b0), (a1, _) in zip(intervals[:-1], intervals[1:]):
        i0, i1 = b0 - 1, a1  # from the last static sample to the first static sample
        segs.append((i0, i1))
    longest = max(i1 - i0 for i0, i1 in segs)
    length = length_bucket * int(np.ceil(longest / length_bucket))
    raw = np.zeros((len(segs), length, 3))
    dt = np.zeros((len(segs), length))
    g = np.asarray(gyro, float) - gyro_bias
    for m, (i0, i1) in enumerate(segs):
        k = i1 - i0
        raw[m, :k] = 0.5 * (g[i0:i1] + g[i0 + 1:i1 + 1])
        dt[m, :k] = np.diff(t[i0:i1 + 1])
    return raw, dt


def fit_gyro(t, gyro, gyro_bias, intervals, directions, scale_init=None):
    """Full ``C_g`` from the gravity directions before and after every motion."""
    raw, dt = motions_between(intervals, t, gyro, gyro_bias)
    u0 = jnp.asarray(directions[:-1])
    u1 = jnp.asarray(directions[1:])
    base = (jnp.asarray(raw), jnp.asarray(dt), u0, u1)
    if scale_init is None:
        grid = jnp.asarray(10.0 ** np.arange(-7.0, 2.0, 1.0 / 16.0))
        costs = np.asarray(_scale_costs(grid, (*base, 1.0)))
        scale_init = float(grid[int(np.nanargmin(costs))])
    theta = _gyro_solve(jnp.eye(3).ravel(), (*base, jnp.asarray(scale_init)))
    c = np.asarray(theta).reshape(3, 3) * scale_init
    resid = np.asarray(_gyro_residual(jnp.asarray(c).ravel(), (*base, 1.0))).reshape(-1, 3)
    return c, np.linalg.norm(resid, axis=1)


# ------------------------------------------------------------------ the recipe


def multi_position(
    accel: np.ndarray,
    gyro: np.ndarray,
    t: np.ndarray,
    *,
    gravity: float = GRAVITY,
    init_seconds: float = 50.0,
    multipliers=range(2, 11),
    window: int = 101,
    n_samples: int = 100,
    min_intervals: int = 12,
    gyro_scale_init: float | None = None,
    pose_means: bool = False,
) -> MultiPositionResult:
    """Calibrate from a recording that starts at rest and then visits static poses.

    ``n_samples``: samples taken from the start of every pose (IMU-TK's 100);
    poses shorter than that are skipped. ``pose_means=True`` (diffgyro's
    variant) keeps IMU-TK's choice of poses but fits the accelerometer to the
    mean of every whole pose instead of its first ``n_samples`` raw samples:
    noise averages out and every pose counts once. ``gyro_scale_init`` (rad/s per raw unit) replaces the
    automatic 1-D scale search.

    **Arguments:**

    - ``accel``: the accelerometer's output (n, 3), any unit.
    - ``gyro``: the gyro's output (n, 3), any unit.
    - ``t``: sample times (n,), s.
    - ``gravity``: the magnitude of gravity, in the calibrated accelerometer's unit.
    - ``init_seconds``: the length of the initial rest, s.
    - ``multipliers``: the static threshold's multipliers of the initial rest's variance,
      tried in turn.
    - ``window``: the static detector's window, samples.
    - ``n_samples``: samples per pose.
    - ``min_intervals``: the fewest static poses a threshold must find.
    - ``gyro_scale_init``: the gyro's starting scale (default: searched).
    - ``pose_means``: fit the accelerometer to each pose's mean (diffgyro's variant).
    """
    accel = np.asarray(accel, float)
    gyro = np.asarray(gyro, float)
    t = np.asarray(t, float)
    n_init = int(np.searchsorted(t, t[0] + init_seconds))
    if n_init < 50:
        raise DataError(f"the initial rest of {init_seconds} s holds only {n_init} samples",
                        hint="the recording must start with the sensor at rest")
    base = rest_variance_norm(accel, n_init)
    best = None
    for k in multipliers:
        ivs = [iv for iv in static_intervals(accel, k * base, window) if iv[1] - iv[0] >= n_samples]
        if len(ivs) < min_intervals:
            continue
        samples = np.concatenate([accel[a:a + n_samples] for a, _ in ivs])
        c, b, cost = fit_accel(samples, gravity)
        if best is None or cost < best[0]:
            best = (cost, k, ivs, c, b)
    if best is None:
        raise DataError(f"fewer than {min_intervals} static poses of {n_samples} samples found "
                        f"with threshold multipliers {list(multipliers)}",
                        hint="hold each pose still for a few seconds, or lower --min-intervals")
    cost, k, ivs, c, b = best
    if pose_means:  # same poses (IMU-TK's selection), refitted to whole-pose means
        c, b, cost = fit_accel(np.stack([accel[a:b_].mean(0) for a, b_ in ivs]), gravity)
    cal = (accel - b) @ c.T
    firsts = np.stack([cal[a:a + n_samples] for a, _ in ivs])         # (poses, n, 3)
    means = firsts.mean(1)
    whole = np.stack([cal[a:b].mean(0) for a, b in ivs])
    pose_err = np.linalg.norm(whole, axis=1) - gravity
    pose_rms = float(np.sqrt(np.mean((np.linalg.norm(firsts, axis=2) - gravity) ** 2)))
    gyro_bias = gyro[:n_init].mean(0)
    directions = means / np.linalg.norm(means, axis=1, keepdims=True)
    cg, resid = fit_gyro(t, gyro, gyro_bias, ivs, directions, gyro_scale_init)
    return MultiPositionResult(
        accel_matrix=c, accel_bias=b, gyro_matrix=cg, gyro_bias=gyro_bias,
        intervals=[list(iv) for iv in ivs], threshold_multiplier=int(k),
        pose_norm_error=pose_err, pose_norm_error_first=np.linalg.norm(means, axis=1) - gravity,
        pose_rms=pose_rms, motion_residual=resid,
        accel_cost=cost, gravity=float(gravity))
