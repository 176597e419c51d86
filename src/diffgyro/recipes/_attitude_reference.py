"""attitude-reference (Goertek patent, 2018): gyro scale and bias against an
accelerometer + magnetometer attitude.

The published procedure, per sample k:

1. pitch and roll from the accelerometer, heading from the tilt-compensated
   magnetometer, turned into a quaternion ``q_am(k)`` with the patent's ZYX
   formula (conventions in :mod:`diffgyro._reference`: NWU navigation frame,
   ``pitch = arcsin(−a_x/|a|)``, ``roll = atan2(a_y, a_z)``,
   ``yaw = atan2(−m_hy, m_hx)``);
2. gate: use sample k only if ``|a(k)|`` lies within ``accel_band`` of g (no
   linear acceleration, so ``q_am`` can be trusted);
3. reference rate from consecutive quaternions, compared with the measured
   rate; the per-axis affine model ``ω_ref = s·(ω_meas − b)`` is updated by
   *alternating* ("cross approximation"): one update holds ``b`` and solves
   ``s``, the next holds ``s`` and solves ``b``. Each solve is the least-squares
   solution over the trusted samples so far (running sums; ``forget`` < 1
   discounts old samples);
4. the next sample's rate is compensated with the current ``s, b``; the
   gyro-propagated quaternion is fused with ``q_am`` at a fixed ratio
   (complementary filter, normalised linear interpolation); when the gate
   fails the gyro alone propagates.

Which quaternions make the reference rate is not spelled out beyond "the
previous moment's": ``reference="am"`` (default) uses two consecutive trusted
``q_am`` (an unbiased but noisy rate), ``reference="fused"`` the fused
attitude at k−1 and ``q_am(k)`` (smoother, but it carries the fused
attitude's lag, which the feedback loop then has to work off). ``interval``
spaces the two quaternions of ``reference="am"`` by more than one sample
(less noise; the gyro is averaged over the same span).

Beside the recursive estimate, :attr:`AttitudeReferenceResult.joint_scale` /
``joint_bias`` solve the same affine per-axis model jointly by least squares
over all gated pairs.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._reference import (
    attitude_from_accel_mag,
    quat_conj,
    quat_from_rotvec,
    quat_mul,
    quat_normalize,
    rotvec_from_quat,
)
from ..errors import DataError
from ._common import RecipeResult

GRAVITY = 9.81


@dataclass(frozen=True)
class AttitudeReferenceResult(RecipeResult):
    """Recursive (published) and joint least-squares scale and bias, and the fused attitude."""

    scale: np.ndarray          # (3,) s after the last update
    bias: np.ndarray           # (3,) b after the last update (rad/s)
    scale_track: np.ndarray    # (n, 3)
    bias_track: np.ndarray     # (n, 3)
    joint_scale: np.ndarray    # (3,) least squares over every gated pair
    joint_bias: np.ndarray     # (3,)
    gate: np.ndarray           # (n,) bool
    pairs: np.ndarray          # (n,) bool: a reference rate was formed at k
    reference_rate: np.ndarray  # (n, 3) ω_ref (NaN where none)
    measured_rate: np.ndarray  # (n, 3) the gyro rate paired with it
    quat: np.ndarray           # (n, 4) fused attitude
    quat_am: np.ndarray        # (n, 4) accelerometer + magnetometer attitude
    ratio: float
    reference: str

    name = "attitude-reference"

    def compensate(self, gyro: np.ndarray, joint: bool = False) -> np.ndarray:
        s, b = (self.joint_scale, self.joint_bias) if joint else (self.scale, self.bias)
        return s * (np.asarray(gyro) - b)

    def to_dict(self) -> dict:
        keep = ("scale", "bias", "joint_scale", "joint_bias", "ratio", "reference")
        out = {k: v for k, v in super().to_dict().items() if k in keep}
        out["n_gated"] = int(np.sum(self.gate))
        out["n_pairs"] = int(np.sum(self.pairs))
        return out


def reference_pairs(t, gyro, q_am, gate, interval: int):
    """(measured, reference, ok) per sample k from trusted ``q_am(k − interval)``, ``q_am(k)``."""
    n = t.shape[0]
    x = np.full((n, 3), np.nan)
    y = np.full((n, 3), np.nan)
    ok = np.zeros(n, bool)
    if n <= interval:
        return x, y, ok
    k = np.arange(interval, n)
    dt = t[k] - t[k - interval]
    rel = quat_mul(quat_conj(jnp.asarray(q_am[k - interval])), jnp.asarray(q_am[k]))
    y[k] = np.asarray(rotvec_from_quat(rel)) / dt[:, None]
    # the gyro over the same span: samples k-interval+1 .. k (each held over its interval)
    c = np.concatenate([np.zeros((1, 3)), np.cumsum(gyro[1:] * np.diff(t)[:, None], 0)])
    x[k] = (c[k] - c[k - interval]) / dt[:, None]
    ok[k] = gate[k] & gate[k - interval]
    return x, y, ok


def joint_affine(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per axis least squares of ``y = s·(x − b)`` (linear in ``s`` and ``s·b``)."""
    s = np.zeros(3)
    b = np.zeros(3)
    for i in range(3):
        a = np.stack([x[:, i], np.ones(x.shape[0])], axis=1)
        (si, ci), *_ = np.linalg.lstsq(a, y[:, i], rcond=None)
        s[i], b[i] = si, -ci / si
    return s, b


def _alternate(sums, s, b, solve_scale):
    """One cross-approximation update from running sums (n, Σx, Σy, Σxx, Σxy)."""
    n, sx, sy, sxx, sxy = sums
    den_s = sxx - 2 * b * sx + n * b * b
    s_new = jnp.where(den_s > 1e-12, (sxy - b * sy) / jnp.where(den_s > 1e-12, den_s, 1.0), s)
    ok_b = (n > 0) & (jnp.abs(s) > 1e-6)
    b_new = jnp.where(ok_b, (sx - sy / jnp.where(ok_b, s, 1.0)) / jnp.maximum(n, 1.0), b)
    return jnp.where(solve_scale, s_new, s), jnp.where(solve_scale, b, b_new)


@jax.jit
def _run(t, gyro, q_am, gate, xk, yk, pair, ratio, forget, fused_reference):
    dt = jnp.diff(t)

    def step(carry, inp):
        q, s, b, sums, solve_scale = carry
        w, d, qa, g, x, y, pok = inp
        # 4. compensate with the current s, b and propagate
        q_gyro = quat_normalize(quat_mul(q, quat_from_rotvec(s * (w - b) * d)))
        # 3. the reference rate and the measured rate paired with it
        y_fused = rotvec_from_quat(quat_mul(quat_conj(q), qa)) / d
        y = jnp.where(fused_reference, y_fused, y)
        x = jnp.where(fused_reference, w, x)
        use = jnp.where(fused_reference, g, pok)
        x0, y0 = jnp.where(use, x, 0.0), jnp.where(use, y, 0.0)
        decay = jnp.where(use, forget, 1.0)
        n, sx, sy, sxx, sxy = sums
        sums = (decay * n + use, decay * sx + x0, decay * sy + y0, decay * sxx + x0 * x0,
                decay * sxy + x0 * y0)
        s_new, b_new = _alternate(sums, s, b, solve_scale)
        s = jnp.where(use, s_new, s)
        b = jnp.where(use, b_new, b)
        solve_scale = jnp.where(use, ~solve_scale, solve_scale)
        # complementary fusion at a fixed ratio (sign-aligned normalised interpolation)
        qa = jnp.where(jnp.dot(qa, q_gyro) < 0, -qa, qa)
        q_fused = quat_normalize((1 - ratio) * q_gyro + ratio * qa)
        q = jnp.where(g, q_fused, q_gyro)
        return (q, s, b, sums, solve_scale), (q, s, b, use, y)

    zeros = jnp.zeros(3, gyro.dtype)
    carry = (q_am[0], jnp.ones(3, gyro.dtype), zeros, (zeros, zeros, zeros, zeros, zeros),
             jnp.asarray(True))
    inputs = (gyro[1:], dt, q_am[1:], gate[1:], xk[1:], yk[1:], pair[1:])
    _, (qs, ss, bs, used, ys) = jax.lax.scan(step, carry, inputs)
    first = lambda a, v: jnp.concatenate([v[None], a])  # noqa: E731
    return (first(qs, q_am[0]), first(ss, jnp.ones(3)), first(bs, zeros),
            first(used, jnp.asarray(False)), first(ys, jnp.full(3, jnp.nan)))


def attitude_reference(
    gyro: np.ndarray,
    accel: np.ndarray,
    mag: np.ndarray,
    t: np.ndarray,
    *,
    gravity: float = GRAVITY,
    accel_band: float = 0.02,
    ratio: float = 0.02,
    reference: str = "am",
    interval: int = 1,
    forget: float = 1.0,
) -> AttitudeReferenceResult:
    """Run attitude-reference on one recording (gyro rad/s, accel m/s², mag any unit, t s).

    ``accel_band``: the gate ``| |a| − g | ≤ accel_band·g``; ``ratio``: weight of
    ``q_am`` in the complementary fusion.

    **Arguments:**

    - ``gyro``: the measured rate (n, 3), rad/s.
    - ``accel``: the specific force (n, 3), m/s².
    - ``mag``: the magnetic field (n, 3), any unit.
    - ``t``: sample times (n,), s.
    - ``gravity``: the magnitude of gravity, m/s².
    - ``accel_band``: the gate's half-width, a fraction of ``gravity``.
    - ``ratio``: the weight of ``q_am`` in the complementary fusion.
    - ``reference``: ``"am"`` (two trusted ``q_am``) or ``"fused"`` (the fused attitude and
      ``q_am``): the quaternions the reference rate comes from.
    - ``interval``: samples between the two quaternions of ``reference="am"``.
    - ``forget``: the running sums' forgetting factor (1: none).
    """
    gyro = np.asarray(gyro, float)
    accel = np.asarray(accel, float)
    mag = np.asarray(mag, float)
    t = np.asarray(t, float)
    if reference not in ("am", "fused"):
        raise DataError(f"reference must be 'am' or 'fused', not {reference!r}")
    if not 0.0 <= ratio <= 1.0:
        raise DataError("the fusion ratio must lie in [0, 1]")
    *_, q_am = attitude_from_accel_mag(jnp.asarray(accel), jnp.asarray(mag))
    q_am = np.asarray(q_am)
    gate = np.abs(np.linalg.norm(accel, axis=1) - gravity) <= accel_band * gravity
    if gate.sum() < 10:
        raise DataError(f"only {int(gate.sum())} samples have |a| within {accel_band:.0%} of g",
                        hint="widen the gate (--accel-band) or check the accelerometer unit")
    x, y, ok = reference_pairs(t, gyro, q_am, gate, int(interval) if reference == "am" else 1)
    qs, ss, bs, used, ys = _run(jnp.asarray(t), jnp.asarray(gyro), jnp.asarray(q_am),
                                jnp.asarray(gate), jnp.asarray(np.nan_to_num(x)),
                                jnp.asarray(np.nan_to_num(y)), jnp.asarray(ok),
                                float(ratio), float(forget), reference == "fused")
    used = np.asarray(used)
    if reference == "fused":
        x = np.where(used[:, None], gyro, np.nan)
        y = np.where(used[:, None], np.asarray(ys), np.nan)
    if used.sum() < 10:
        raise DataError(f"only {int(used.sum())} trusted reference rates",
                        hint="the device must move while the accelerometer gate holds")
    js, jb = joint_affine(x[used], y[used])
    ss, bs = np.asarray(ss), np.asarray(bs)
    return AttitudeReferenceResult(
        scale=ss[-1], bias=bs[-1], scale_track=ss, bias_track=bs, joint_scale=js, joint_bias=jb,
        gate=gate, pairs=used, reference_rate=np.where(used[:, None], y, np.nan),
        measured_rate=np.where(used[:, None], x, np.nan), quat=np.asarray(qs), quat_am=q_am,
        ratio=float(ratio), reference=reference)
