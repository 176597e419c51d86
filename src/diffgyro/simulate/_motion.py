"""Scripted motion for test plans: poses, smooth moves, table spins, Earth rate, gravity.

Conventions are those of :mod:`diffgyro._reference`: quaternions ``(w, x, y,
z)`` rotate body vectors into the navigation frame, which is NWU (x north, y
west, z up). A resting accelerometer reads ``+g`` on the axis pointing up.

Every motion segment is closed form, so the true body rate, the attitude and
the specific force agree exactly at every sample:

* ``hold``: the pose is fixed, the body rate is zero;
* ``move``: ``q(t) = q_a ⊗ exp(u(t)·Δ)`` with ``Δ`` the body-frame rotation
  vector from ``q_a`` to ``q_b`` and ``u`` a raised-cosine 0 → 1, so the body
  rate is ``u'(t)·Δ``;
* ``spin``: a table turn about a fixed navigation axis ``k`` with a
  trapezoidal rate profile ``φ'(t)``: ``q(t) = exp(φ(t)·k) ⊗ q_a``, body rate
  ``φ'(t)·R_aᵀk`` (constant direction in the body).

Earth rate is added as ``R(t)ᵀ·Ω_E·(cos lat, 0, sin lat)`` when a latitude is
given; the centripetal acceleration of a spinning table is ignored (the
device sits on the axis).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Earth's rotation rate (rad/s, WGS-84).
EARTH_RATE = 7.292115e-5
#: Standard gravity (m/s²).
G0 = 9.80665
DEG = math.pi / 180.0


# ----------------------------------------------------------------------------- quaternions (numpy)


def qmul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` (broadcasting over leading axes)."""
    pw, px, py, pz = np.moveaxis(p, -1, 0)
    qw, qx, qy, qz = np.moveaxis(q, -1, 0)
    return np.stack([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ], axis=-1)


def qconj(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def qexp(v: np.ndarray) -> np.ndarray:
    """Rotation by ``|v|`` about ``v/|v|`` as a unit quaternion."""
    v = np.asarray(v, dtype=float)
    angle = np.linalg.norm(v, axis=-1, keepdims=True)
    half = 0.5 * angle
    k = np.where(angle > 1e-12, np.sin(half) / np.where(angle > 1e-12, angle, 1.0),
                 0.5 - angle**2 / 48.0)
    return np.concatenate([np.cos(half), k * v], axis=-1)


def qlog(q: np.ndarray) -> np.ndarray:
    """Rotation vector of ``q`` (shortest rotation)."""
    q = np.where(q[..., :1] < 0, -q, q)
    vn = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vn, q[..., :1])
    k = np.where(vn > 1e-12, angle / np.where(vn > 1e-12, vn, 1.0), 2.0)
    return k * q[..., 1:]


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``q ⊗ v ⊗ q*``: a body vector in the navigation frame."""
    w, x, y, z = np.moveaxis(q, -1, 0)
    vx, vy, vz = np.moveaxis(np.asarray(v, dtype=float), -1, 0)
    # v + 2w (u × v) + 2 u × (u × v), u = (x, y, z)
    cx, cy, cz = y * vz - z * vy, z * vx - x * vz, x * vy - y * vx
    return np.stack([
        vx + 2 * (w * cx + y * cz - z * cy),
        vy + 2 * (w * cy + z * cx - x * cz),
        vz + 2 * (w * cz + x * cy - y * cx),
    ], axis=-1)


def to_body(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A navigation-frame vector seen in the body frame: ``q* ⊗ v ⊗ q``."""
    return rotate(qconj(q), v)


def face_quat(face: str) -> np.ndarray:
    """Pose with body axis ``face`` (``+x``, ``-x``, ``+y``, ``-y``, ``+z``, ``-z``) pointing up."""
    table = {
        "+z": (0.0, 0.0, 0.0), "-z": (math.pi, 0.0, 0.0),
        "+y": (math.pi / 2, 0.0, 0.0), "-y": (-math.pi / 2, 0.0, 0.0),
        "+x": (0.0, -math.pi / 2, 0.0), "-x": (0.0, math.pi / 2, 0.0),
    }
    try:
        rv = table[face]
    except KeyError:
        raise ValueError(f"unknown face {face!r}; use one of {', '.join(table)}") from None
    return qexp(np.array(rv))


def earth_rate_nav(latitude_deg: float) -> np.ndarray:
    """Earth's rotation in the NWU frame at ``latitude_deg`` (rad/s)."""
    lat = latitude_deg * DEG
    return EARTH_RATE * np.array([math.cos(lat), 0.0, math.sin(lat)])


# ----------------------------------------------------------------------------- rate profiles


def trapezoid(tau: np.ndarray, duration: float, rate: float, accel: float):
    """Angle ``φ`` and rate ``φ'`` of a table turn: accelerate at ``accel`` to
    ``rate``, hold, decelerate, all within ``duration`` (triangular if too short)."""
    t_r = abs(rate) / accel if accel > 0 else 0.0
    peak = rate
    if 2 * t_r > duration:
        t_r = duration / 2
        peak = math.copysign(accel * t_r, rate)
    if t_r <= 0:
        return peak * tau, np.full_like(tau, peak)
    up = tau < t_r
    down = tau > duration - t_r
    rate_t = peak * np.where(up, tau / t_r, np.where(down, (duration - tau) / t_r, 1.0))
    phi = np.where(up, peak * tau**2 / (2 * t_r),
                   np.where(down, peak * (duration - t_r) - peak * (duration - tau) ** 2 / (2 * t_r),
                            peak * (tau - t_r / 2)))
    return phi, rate_t


def turn_duration(angle: float, rate: float, accel: float) -> float:
    """Duration of a trapezoidal turn by ``angle`` at plateau ``|rate|``."""
    t_r = abs(rate) / accel
    return abs(angle) / abs(rate) + t_r


# ----------------------------------------------------------------------------- timeline


@dataclass
class Timeline:
    """A test plan's script: chamber temperature, dissipated power and motion over time.

    Methods append segments at the current time and advance it. ``segment``
    records a labelled window (e.g. a static face or a table turn) for the
    truth. ``render`` evaluates everything on a uniform time grid.
    """

    start_temp: float = 25.0
    pose: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    now: float = 0.0
    chamber: list = field(default_factory=list)  # (t, °C) breakpoints, linear between
    power: list = field(default_factory=list)    # (t, level) steps
    motion: list = field(default_factory=list)   # (t0, t1, kind, data)
    segments: list = field(default_factory=list)  # (label, t0, t1, meta)

    def __post_init__(self):
        self.pose = np.asarray(self.pose, dtype=float)
        self.chamber = [(0.0, float(self.start_temp))]
        self.power = [(0.0, 1.0)]

    @property
    def temp(self) -> float:
        return self.chamber[-1][1]

    def _advance(self, duration: float, kind: str, data) -> tuple[float, float]:
        t0, t1 = self.now, self.now + float(duration)
        if duration > 0:
            self.motion.append((t0, t1, kind, data))
        self.now = t1
        return t0, t1

    def hold(self, duration: float, label: str | None = None, **meta) -> tuple[float, float]:
        """Keep pose and chamber temperature for ``duration`` seconds."""
        t0, t1 = self._advance(duration, "hold", self.pose.copy())
        if label:
            self.segment(label, t0, t1, **meta)
        return t0, t1

    def ramp(self, target: float, rate_per_min: float, label: str | None = None, **meta):
        """Chamber ramps to ``target`` °C at ``rate_per_min`` °C/min (pose held)."""
        span = abs(float(target) - self.temp)
        if span == 0:
            return self.now, self.now
        duration = span / (abs(rate_per_min) / 60.0)
        self.chamber.append((self.now, self.temp))
        t0, t1 = self.hold(duration)
        self.chamber.append((t1, float(target)))
        if label:
            self.segment(label, t0, t1, **meta)
        return t0, t1

    def set_power(self, level: float) -> None:
        """Dissipated power (self-heating) level from now on (1 = nominal)."""
        self.power.append((self.now, float(level)))

    def move(self, duration: float, to: np.ndarray, label: str | None = None, **meta):
        """Smooth rotation to pose ``to`` (raised-cosine profile)."""
        to = np.asarray(to, dtype=float)
        delta = qlog(qmul(qconj(self.pose), to))
        t0, t1 = self._advance(duration, "move", (self.pose.copy(), delta))
        self.pose = qmul(self.pose, qexp(delta))
        if label:
            self.segment(label, t0, t1, **meta)
        return t0, t1

    def spin(self, duration: float, rate: float, accel: float, axis=(0.0, 0.0, 1.0),
             label: str | None = None, **meta):
        """Table turn about navigation ``axis`` with plateau ``rate`` (rad/s) and
        angular acceleration ``accel`` (rad/s²)."""
        axis = np.asarray(axis, dtype=float)
        axis = axis / np.linalg.norm(axis)
        t0, t1 = self._advance(duration, "spin", (self.pose.copy(), axis, float(rate), float(accel)))
        phi, _ = trapezoid(np.array([float(duration)]), float(duration), rate, accel)
        self.pose = qmul(qexp(phi[0] * axis), self.pose)
        if label:
            self.segment(label, t0, t1, rate=float(rate), **meta)
        return t0, t1

    def turn(self, angle: float, rate: float, accel: float, axis=(0.0, 0.0, 1.0),
             label: str | None = None, **meta):
        """Table turn by ``angle`` (rad, sign gives the direction) at plateau ``|rate|``."""
        duration = turn_duration(angle, rate, accel)
        return self.spin(duration, math.copysign(abs(rate), angle), accel, axis, label,
                         angle=float(angle), **meta)

    def segment(self, label: str, t0: float, t1: float, **meta) -> None:
        self.segments.append((label, float(t0), float(t1), meta))

    # ------------------------------------------------------------------ evaluation

    def render(self, dt: float, latitude: float | None = None, g: float = G0) -> dict:
        """Uniform samples ``t = k·dt`` over the script: chamber, power, attitude,
        body rate and specific force (numpy arrays)."""
        total = self.now
        n = max(int(math.ceil(total / dt - 1e-9)), 2)
        t = np.arange(n) * dt
        bt, bv = zip(*self.chamber)
        chamber = np.interp(t, np.array(bt + (max(total, bt[-1]),)), np.array(bv + (bv[-1],)))
        pt, pv = zip(*self.power)
        power = np.asarray(pv)[np.searchsorted(np.asarray(pt), t, side="right") - 1]
        quat = np.tile(self.pose, (n, 1))
        rate = np.zeros((n, 3))
        for t0, t1, kind, data in self.motion:
            sel = (t >= t0) & (t < t1)
            if not sel.any():
                continue
            tau = t[sel] - t0
            dur = t1 - t0
            if kind == "hold":
                quat[sel] = data
            elif kind == "move":
                qa, delta = data
                s = tau / dur
                u = 0.5 * (1 - np.cos(math.pi * s))
                du = 0.5 * math.pi / dur * np.sin(math.pi * s)
                quat[sel] = qmul(qa, qexp(u[:, None] * delta))
                rate[sel] = du[:, None] * delta
            else:  # spin
                qa, axis, r, acc = data
                phi, dphi = trapezoid(tau, dur, r, acc)
                quat[sel] = qmul(qexp(phi[:, None] * axis), qa)
                rate[sel] = dphi[:, None] * to_body(qa, axis)
        if latitude is not None:
            rate = rate + to_body(quat, earth_rate_nav(latitude))
        force = to_body(quat, np.array([0.0, 0.0, g]))
        return {"t": t, "chamber": chamber, "power": power, "quat": quat, "rate": rate,
                "specific_force": force}

    def windows(self, dt: float) -> list[dict]:
        """Labelled segments with sample ranges ``[start, end)`` on the grid ``k·dt``."""
        out = []
        for label, t0, t1, meta in self.segments:
            start = int(math.ceil(t0 / dt - 1e-9))
            end = int(math.ceil(t1 / dt - 1e-9))
            out.append({"label": label, "t0": t0, "t1": t1, "start": start, "end": end, **meta})
        return out
