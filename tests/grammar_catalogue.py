"""Recordings with effects outside diffgyro's vocabulary, made in plain numpy.

Five kinds, each on its own test plan, each a term of the grammar in truth
(``term(...)``) on top of a base model the library already knows:

========== ============================ =================================== ==================
case       plan                         hidden effect                       base model
========== ============================ =================================== ==================
tempg      tumble over a chamber sweep  g-sensitivity along z ∝ temperature bias_poly(1)+g_sens
heater     static, heater duty logged   first-order lag (τ 300 s) of duty   bias_poly(1)
aniso      tumble through 26 directions a_y·a_z (anisoelastic)              bias_poly(0)+g_sens
cross      rate table, diagonal axes    ω_x·ω_y                             bias_poly(0)+scale_poly(0)+misalignment
supply     chamber sweep, vdd logged    temperature × supply voltage        bias_poly(1)+aux(vdd)
========== ============================ =================================== ==================

Each case has two recordings of the same unit (``profile`` 0 and 1): the same
coefficients, new noise, a new profile (other orientation order, temperature
path, heater steps, spin sequence), with ranges inside the first's so that a
calibration from the first applies to the second without clamping.
The effects are written from their physics in raw units (°C, m/s², rad/s, duty),
not from the library's centred regressors.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from diffgyro.data import Recording

G = 9.80665
DEG = math.pi / 180.0
SIGMA = 5e-4  # white gyro noise per sample (rad/s)
FS = 1.0
N = 4000


@dataclass(frozen=True)
class Case:
    name: str
    base: str
    term: str          # the hidden effect as a grammar term (the signals it names)
    signals: frozenset  # the signals the proposal must name


CASES = {
    "tempg": Case("tempg", "bias_poly(1)+g_sens", "term(temp*az)", frozenset({"temp", "az"})),
    "heater": Case("heater", "bias_poly(1)", "term(lag(heater))", frozenset({"heater"})),
    "aniso": Case("aniso", "bias_poly(0)+g_sens", "term(ay*az)", frozenset({"ay", "az"})),
    "cross": Case("cross", "bias_poly(0)+scale_poly(0)+misalignment", "term(rx*ry)",
                  frozenset({"rx", "ry"})),
    "supply": Case("supply", "bias_poly(1)+aux(vdd)", "term(temp*vdd)", frozenset({"temp", "vdd"})),
}


def _lag(x: np.ndarray, tau: float, dt: float) -> np.ndarray:
    y = np.empty_like(x)
    y[0] = x[0]
    a = -math.expm1(-dt / tau)
    for k in range(1, len(x)):
        y[k] = y[k - 1] + a * (x[k] - y[k - 1])
    return y


def _directions(kind: str) -> np.ndarray:
    """Gravity directions in the body frame: the six faces, or all 26 of a cube."""
    pts = [np.array(v, float) for v in np.ndindex(3, 3, 3)]
    pts = [p - 1.0 for p in pts if np.any(p != 1)]
    if kind == "faces":
        pts = [p for p in pts if np.abs(p).sum() == 1]
    return np.stack([p / np.linalg.norm(p) for p in pts])


def _tumble(rng, dirs: np.ndarray, n: int, hold: float = 50.0, move: float = 8.0):
    """Body-frame gravity direction and body rate: holds at ``dirs`` (shuffled, repeated),
    great-circle moves between them (sin² rate profile)."""
    u = np.zeros((n, 3))
    w = np.zeros((n, 3))
    t = np.arange(n) / FS
    order = np.concatenate([rng.permutation(len(dirs)) for _ in range(20)])
    k, now, cur = 0, 0.0, dirs[order[0]]
    while now < t[-1]:
        h = hold * rng.uniform(0.7, 1.3)
        sel = (t >= now) & (t < now + h)
        u[sel] = cur
        now += h
        k += 1
        nxt = dirs[order[k]]
        if np.allclose(nxt, cur):
            continue
        axis = np.cross(cur, nxt)
        if np.linalg.norm(axis) < 1e-9:  # opposite: turn about any perpendicular axis
            axis = np.cross(cur, [1.0, 0.0, 0.0] if abs(cur[0]) < 0.9 else [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        angle = math.acos(float(np.clip(cur @ nxt, -1, 1)))
        sel = (t >= now) & (t < now + move)
        s = (t[sel] - now) / move
        theta = angle * (s - np.sin(2 * math.pi * s) / (2 * math.pi))
        rate = angle / move * (1 - np.cos(2 * math.pi * s))
        c, sn = np.cos(theta)[:, None], np.sin(theta)[:, None]
        perp = np.cross(axis, cur)  # rotate cur about axis by theta (Rodrigues)
        u[sel] = c * cur + sn * perp + (1 - c) * (axis @ cur) * axis
        w[sel] = -rate[:, None] * axis  # dg_b/dt = −ω × g_b
        now += move
        cur = nxt
    return u * G, w


def _sweep(rng, n: int, profile: int, lo=10.0, hi=50.0) -> np.ndarray:
    """Chamber temperature: ramps and soaks inside [lo, hi]."""
    t = np.arange(n) / FS
    if profile == 0:
        knots = [(0, 30), (0.1, 30), (0.35, hi), (0.45, hi), (0.8, lo), (0.9, lo), (1.0, 25)]
    else:
        knots = [(0, 22), (0.15, 40), (0.3, 40), (0.5, 15), (0.65, 28), (0.8, 45), (1.0, 35)]
    x, y = zip(*knots)
    return np.interp(t, np.asarray(x) * t[-1], y)


def _steps(rng, n: int, lo: float, hi: float, mean_len: float) -> np.ndarray:
    """A piecewise-constant column with random levels in [lo, hi] (both ends reached)."""
    out = np.empty(n)
    k = 0
    while k < n:
        m = int(rng.uniform(0.5, 1.5) * mean_len)
        out[k:k + m] = rng.uniform(lo, hi)
        k += m
    out[:int(mean_len / 2)] = lo
    out[-int(mean_len / 2):] = hi
    return out


def _spins(rng, n: int):
    """Rate table with the device mounted so a diagonal is vertical: ± spins about
    diagonals in turn (30, 100, 200 °/s, 20 s at rate, 5 s ramps, 10 s pauses); gravity
    along the spin axis."""
    axes = np.array([[1, 1, 0], [1, -1, 0], [0, 1, 1], [1, 0, 1], [1, 1, 1], [1, -1, 1]], float)
    axes /= np.linalg.norm(axes, axis=1)[:, None]
    w = np.zeros((n, 3))
    acc = np.zeros((n, 3))
    k = 0
    while k < n:
        ax = axes[rng.integers(len(axes))]
        for r in rng.permutation([30.0, 100.0, 200.0]):
            for sign in (1.0, -1.0):
                prof = np.concatenate([np.linspace(0, 1, 6)[1:], np.ones(20), np.linspace(1, 0, 6)[1:],
                                       np.zeros(10)])
                m = min(len(prof), n - k)
                w[k:k + m] = sign * r * DEG * prof[:m, None] * ax
                acc[k:k + len(prof)] = G * ax
                k += m
                if k >= n:
                    return w, acc[:n]
    return w, acc[:n]


#: The hidden coefficients (rad/s per raw unit of the product), per axis.
COEF = {
    "tempg": np.array([1.2e-4, -1e-4, 1.5e-4]) / G,                 # per °C·(m/s²)
    "heater": np.array([4e-3, -3e-3, 3e-3]),                  # per unit duty, lagged 300 s
    "aniso": np.array([1.5e-3, -2e-3, 1.2e-3]) / G**2,           # per (m/s²)²
    "cross": np.array([5e-4, 3e-4, -4e-4]),                     # per (rad/s)²
    "supply": np.array([2.5e-3, -2e-3, 1.5e-3]),              # per °C·V
}
HEATER_TAU = 300.0


def make(case: str, profile: int = 0, device: str = "unit") -> tuple[Recording, np.ndarray]:
    """One recording of case ``case`` and its true rate (n, 3); ``profile`` 0 calibrates,
    1 is the second recording."""
    rng = np.random.default_rng(1000 * profile + sum(map(ord, case)))
    noise = np.random.default_rng(7 + 1000 * profile + sum(map(ord, case)))
    n = N
    t = np.arange(n) / FS
    bias = np.array([1e-3, -2e-3, 5e-4])
    tc = np.array([2e-4, -1e-4, 1.5e-4])  # rad/s per 10 °C
    gs = np.array([[2e-4, -1e-4, 3e-4], [1e-4, 2e-4, -2e-4], [-3e-4, 1e-4, 2e-4]]) / G
    accel = rate = temp = None
    aux = {}
    w = np.zeros((n, 3))
    if case == "tempg":
        accel, w = _tumble(rng, _directions("faces"), n)
        temp = _sweep(rng, n, profile)
        err = bias + np.outer((temp - 30) / 10, tc) + accel @ gs.T
        err = err + COEF[case] * ((temp - 30) * accel[:, 2])[:, None]
        rate = w
    elif case == "heater":
        temp = 25.0 + (0.7 if profile else 0.8) * np.sin(2 * math.pi * t / (t[-1] * (1.3 if profile else 1.0)))
        duty = _steps(rng, n, 0.0, 1.0, 450.0)
        aux["heater"] = duty
        err = bias + np.outer((temp - 30) / 10, tc)
        err = err + COEF[case] * _lag(duty, HEATER_TAU, 1 / FS)[:, None]
        accel = np.tile([0.0, 0.0, G], (n, 1))
    elif case == "aniso":
        accel, w = _tumble(rng, _directions("cube"), n)
        temp = np.full(n, 25.0)
        err = bias + accel @ gs.T + COEF[case] * (accel[:, 1] * accel[:, 2])[:, None]
        rate = w
    elif case == "cross":
        w, accel = _spins(rng, n)
        temp = np.full(n, 25.0)
        scale = np.array([3e-3, -2e-3, 1e-3])
        mis = np.array([[0, 2e-3, -1e-3], [1e-3, 0, 2e-3], [-2e-3, 1e-3, 0]])
        err = bias + w * scale + w @ mis.T + COEF[case] * (w[:, 0] * w[:, 1])[:, None]
        rate = w
    elif case == "supply":
        temp = _sweep(rng, n, profile)
        vdd = 3.3 + 0.15 * np.sin(2 * math.pi * t / rng.uniform(500, 900)) + 0.1 * _steps(
            rng, n, -1.0, 1.0, 300.0)
        vdd = np.clip(vdd, 3.05, 3.55)
        vdd[:5], vdd[-5:] = 3.05, 3.55  # both recordings span the same range
        aux["vdd"] = vdd
        err = bias + np.outer((temp - 30) / 10, tc) + np.outer(vdd - 3.3, [2e-3, 1e-3, -1.5e-3])
        err = err + COEF[case] * ((temp - 30) * (vdd - 3.3))[:, None]
        accel = np.tile([0.0, 0.0, G], (n, 1))
    else:
        raise KeyError(case)
    if temp is not None:
        temp = temp + 0.01 * noise.standard_normal(n)
    gyro = w + err + SIGMA * noise.standard_normal((n, 3))
    return Recording(t=t, gyro=gyro, temp=temp, accel=accel, rate=rate, aux=aux,
                     device=device, source=f"{case}-{profile}.csv"), w


def noise_only(n_devices: int, seed: int = 0, n: int = 2000) -> list[Recording]:
    """Devices whose base model ``NOISE_BASE`` is right, with correlated noise on top of
    white noise: first-order Gauss–Markov, random walk or flicker-like (a sum of
    Gauss–Markov processes over three decades), each at a level from barely visible to
    several times the white noise. They tumble through a temperature sweep and log an
    extra column, so the synthesis library is large."""
    out = []
    for i in range(n_devices):
        rng = np.random.default_rng(seed * 100003 + i)
        accel, w = _tumble(rng, _directions("cube"), n, hold=40.0)
        t = np.arange(n) / FS
        temp = _sweep(rng, n, i % 2) + 0.01 * rng.standard_normal(n)
        vdd = 3.3 + 0.1 * _steps(rng, n, -1.0, 1.0, 200.0)
        kind = ("gm", "rw", "flicker")[i % 3]
        level = SIGMA * float(np.exp(rng.uniform(np.log(0.3), np.log(3.0))))
        if kind == "gm":
            tau = float(np.exp(rng.uniform(np.log(30.0), np.log(600.0))))
            a = math.exp(-1.0 / (tau * FS))
            x = np.zeros((n, 3))
            e = rng.standard_normal((n, 3)) * level * math.sqrt(1 - a * a)
            for k in range(1, n):
                x[k] = a * x[k - 1] + e[k]
        elif kind == "rw":
            x = np.cumsum(rng.standard_normal((n, 3)), axis=0) * level / math.sqrt(n)
        else:
            x = np.zeros((n, 3))
            for tau in (10.0, 100.0, 1000.0):
                a = math.exp(-1.0 / (tau * FS))
                e = rng.standard_normal((n, 3)) * level / math.sqrt(3) * math.sqrt(1 - a * a)
                y = np.zeros((n, 3))
                for k in range(1, n):
                    y[k] = a * y[k - 1] + e[k]
                x += y
        bias = rng.normal(0, 1e-3, 3)
        gs = rng.normal(0, 3e-4, (3, 3)) / G
        err = bias + np.outer((temp - 30) / 10, rng.normal(0, 2e-4, 3)) + accel @ gs.T
        gyro = w + err + x + SIGMA * rng.standard_normal((n, 3))
        out.append(Recording(t=t, gyro=gyro, temp=temp, accel=accel, rate=w, aux={"vdd": vdd},
                             device=f"{kind}{i:03d}", source=f"noise-{i}.csv"))
    return out


NOISE_BASE = "bias_poly(1)+g_sens"
