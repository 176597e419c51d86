"""Attitude references: quaternion algebra, attitude from accelerometer and
magnetometer, reference rates from consecutive quaternions, gyro integration.

Conventions (used everywhere in diffgyro):

* quaternions are ``(w, x, y, z)``, Hamilton product, and rotate body-frame
  vectors into the navigation frame: ``v_nav = q ⊗ v_body ⊗ q*``;
* the navigation frame is **NWU**: x towards magnetic north (horizontal), y
  west, z up. A resting accelerometer reads ``+g`` on the axis pointing up
  (specific force);
* Euler angles are ZYX: ``q = q_z(yaw) ⊗ q_y(pitch) ⊗ q_x(roll)``. Roll turns
  about body x, pitch about body y, yaw about the vertical, counter-clockwise
  seen from above; yaw 0 means body x points to magnetic north.

At rest the specific force in the body frame is ``g·(−sin θ, sin φ cos θ,
cos φ cos θ)``, so ``pitch = arcsin(−a_x/|a|)`` and ``roll = atan2(a_y, a_z)``.
The magnetometer, rotated back to level by pitch and roll, points to
magnetic north in the horizontal plane: ``yaw = atan2(−m_hy, m_hx)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def quat_mul(p: Float[Array, "... 4"], q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """Hamilton product ``p ⊗ q``."""
    pw, px, py, pz = jnp.moveaxis(p, -1, 0)
    qw, qx, qy, qz = jnp.moveaxis(q, -1, 0)
    return jnp.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ], axis=-1)


def quat_conj(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_normalize(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def quat_positive(q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    """The representative with ``w ≥ 0`` (q and −q are the same rotation)."""
    return jnp.where(q[..., :1] < 0, -q, q)


def quat_from_rotvec(v: Float[Array, "... 3"]) -> Float[Array, "... 4"]:
    """Exponential map: rotation by ``|v|`` about ``v / |v|`` (exact near zero,
    with finite gradients at zero)."""
    a2 = jnp.sum(v * v, axis=-1, keepdims=True)
    small = a2 < 1e-20
    angle = jnp.sqrt(jnp.where(small, 1.0, a2))
    k = jnp.where(small, 0.5 - a2 / 48.0, jnp.sin(0.5 * angle) / angle)
    w = jnp.where(small, 1.0 - a2 / 8.0, jnp.cos(0.5 * angle))
    return jnp.concatenate([w, k * v], axis=-1)


def rotvec_from_quat(q: Float[Array, "... 4"]) -> Float[Array, "... 3"]:
    """Logarithm map (shortest rotation): the rotation vector of ``q`` (finite
    gradients at the identity)."""
    q = quat_positive(q)
    v2 = jnp.sum(q[..., 1:] ** 2, axis=-1, keepdims=True)
    small = v2 < 1e-20
    vn = jnp.sqrt(jnp.where(small, 1.0, v2))
    w = q[..., :1]
    k = jnp.where(small, 2.0 / jnp.where(small, jnp.maximum(w, 1e-12), 1.0),
                  2.0 * jnp.arctan2(vn, w) / vn)
    return k * q[..., 1:]


def rotate(q: Float[Array, "... 4"], v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """``q ⊗ v ⊗ q*``: a body vector expressed in the navigation frame."""
    vq = jnp.concatenate([jnp.zeros_like(v[..., :1]), v], axis=-1)
    return quat_mul(quat_mul(q, vq), quat_conj(q))[..., 1:]


def quat_from_euler(roll, pitch, yaw) -> Float[Array, "... 4"]:
    """ZYX Euler angles to a quaternion (the formula of the attitude-reference patent, same order)."""
    cr, sr = jnp.cos(roll / 2), jnp.sin(roll / 2)
    cp, sp = jnp.cos(pitch / 2), jnp.sin(pitch / 2)
    cy, sy = jnp.cos(yaw / 2), jnp.sin(yaw / 2)
    return jnp.stack([
        cp * cr * cy + sp * sr * sy,
        cp * sr * cy - sp * cr * sy,
        sp * cr * cy + cp * sr * sy,
        cp * cr * sy - sp * sr * cy,
    ], axis=-1)


def euler_from_quat(q: Float[Array, "... 4"]):
    """ZYX Euler angles ``(roll, pitch, yaw)`` of ``q``."""
    w, x, y, z = jnp.moveaxis(q, -1, 0)
    roll = jnp.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = jnp.arcsin(jnp.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = jnp.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def attitude_from_accel_mag(accel: Float[Array, "n 3"], mag: Float[Array, "n 3"]):
    """Per sample: roll and pitch from the accelerometer, yaw from the
    tilt-compensated magnetometer; returns ``(roll, pitch, yaw, quaternion)``."""
    an = jnp.linalg.norm(accel, axis=-1)
    pitch = jnp.arcsin(jnp.clip(-accel[..., 0] / an, -1.0, 1.0))
    roll = jnp.arctan2(accel[..., 1], accel[..., 2])
    # Level the magnetometer: m_h = R_y(pitch) R_x(roll) m_body.
    cr, sr = jnp.cos(roll), jnp.sin(roll)
    cp, sp = jnp.cos(pitch), jnp.sin(pitch)
    mx, my, mz = mag[..., 0], mag[..., 1], mag[..., 2]
    my_r = cr * my - sr * mz
    mz_r = sr * my + cr * mz
    mhx = cp * mx + sp * mz_r
    mhy = my_r
    yaw = jnp.arctan2(-mhy, mhx)
    return roll, pitch, yaw, quat_from_euler(roll, pitch, yaw)


def relative_rate(q0: Float[Array, "... 4"], q1: Float[Array, "... 4"], dt) -> Float[Array, "... 3"]:
    """Constant body rate that turns ``q0`` into ``q1`` in ``dt``: ``log(q0* ⊗ q1) / dt``."""
    return rotvec_from_quat(quat_mul(quat_conj(q0), q1)) / dt[..., None]


def rates_from_quaternions(t: Float[Array, " n"], q: Float[Array, "n 4"], interval: int = 1):
    """Body rates from a quaternion sequence over ``interval`` samples.

    Returns ``(t_mid, rate)`` with ``n − interval`` rows: the rate that turns
    ``q[k]`` into ``q[k + interval]`` and the time at the middle of that span.
    NaN quaternions give NaN rates.
    """
    dt = t[interval:] - t[:-interval]
    return 0.5 * (t[interval:] + t[:-interval]), relative_rate(q[:-interval], q[interval:], dt)


def integrate_gyro(q0: Float[Array, " 4"], gyro: Float[Array, "n 3"], t: Float[Array, " n"]):
    """Attitude from body rates: ``q[k+1] = q[k] ⊗ exp(ω_k · Δt_k)`` (``q[0] = q0``).

    ``ω_k`` is held over ``[t_k, t_{k+1})``; the result has ``n`` rows.
    """
    dt = jnp.diff(t)

    def step(q, wd):
        w, d = wd
        q = quat_normalize(quat_mul(q, quat_from_rotvec(w * d)))
        return q, q

    _, qs = jax.lax.scan(step, q0, (gyro[:-1], dt))
    return jnp.concatenate([q0[None], qs], axis=0)


def heading_error(q_est: Float[Array, "... 4"], q_ref: Float[Array, "... 4"]) -> Float[Array, "..."]:
    """Heading (yaw) part of the navigation-frame error ``q_ref ⊗ q_est*`` (rad, wrapped).

    The twist of the error rotation about the vertical: zero for pure tilt errors.
    """
    e = quat_mul(q_ref, quat_conj(q_est))
    return wrap_angle(2.0 * jnp.arctan2(e[..., 3], e[..., 0]))


def wrap_angle(a):
    """Angles wrapped to ``[-π, π)``."""
    return (a + jnp.pi) % (2 * jnp.pi) - jnp.pi
