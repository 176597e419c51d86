"""Gyro and sensor noise with stated conventions (IEEE Std 952 / 1554).

* White rate noise from angle random walk ``N`` (rad/s/√Hz): σ per sample
  ``N·√fs``; Allan deviation ``N/√τ``.
* Bias random walk from rate random walk ``K`` (rad/s²/√Hz): increments of
  σ ``K·√dt`` per sample; Allan deviation ``K·√(τ/3)``.
* Bias instability ``B`` (rad/s): flicker rate noise with IEEE 952's
  two-sided PSD ``B²/(2π|f|)`` (one-sided ``B²/(π f)``), approximated by a
  sum of first-order Gauss–Markov processes with correlation times two per
  decade (ratio ``r = √10``) between half a sample and the record length, each
  of variance ``B²·ln r/π`` (the sum of their one-sided Lorentzian spectra
  ``4σ²τ/(1 + (2πfτ)²)`` is then ``B²/(π f)`` between the ends). The Allan
  deviation is flat at ``√(2 ln 2/π)·B ≈ 0.664·B`` there.
* Output quantisation: the final rate is rounded to multiples of ``quantum``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from scipy.signal import lfilter

from ..errors import SpecError
from ._population import Preset, stream

#: Correlation-time ratio between neighbouring Gauss–Markov processes (two per decade).
GM_RATIO = math.sqrt(10.0)

_AXES3 = ("arw", "rrw", "bias_instability")
_PER_DEVICE = ("quantum", "accel_noise")
_SCALARS = ("temp_noise", "temp_quantum", "mag_noise")


@dataclass(frozen=True)
class NoiseLevels:
    """Noise levels of every device (units in the module docstring).

    ``arw``, ``rrw``, ``bias_instability`` are (devices, 3); ``quantum``
    (output LSB, 0 = none) and ``accel_noise`` (m/s²/√Hz) are (devices,);
    ``temp_noise`` (°C σ per reading), ``temp_quantum`` (°C read-out step,
    0 = none) and ``mag_noise`` (µT σ per sample) are shared.
    """

    arw: np.ndarray
    rrw: np.ndarray
    bias_instability: np.ndarray
    quantum: np.ndarray
    accel_noise: np.ndarray
    temp_noise: float = 0.0
    temp_quantum: float = 0.0
    mag_noise: float = 0.0

    @property
    def n_devices(self) -> int:
        return int(self.arw.shape[0])

    def device(self, i: int) -> dict:
        """Device ``i``'s levels as plain values (per-axis lists for the gyro terms)."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = (np.asarray(v)[i].tolist() if f.name in _AXES3 + _PER_DEVICE else float(v))
        return out

    @classmethod
    def zero(cls, n_devices: int) -> NoiseLevels:
        z3, z1 = np.zeros((n_devices, 3)), np.zeros(n_devices)
        return cls(arw=z3, rrw=z3, bias_instability=z3, quantum=z1, accel_noise=z1)


def noise_levels(preset: Preset, n_devices: int, seed: int, noise=None,
                 temp_quantum: float | None = None) -> NoiseLevels:
    """Levels from a preset with device-to-device spread, then user overrides.

    ``noise`` is ``None`` (preset), ``"none"``/``False`` (all zero), a
    :class:`NoiseLevels`, or a dict overriding some levels: a scalar applies
    to every device and axis exactly, an array broadcasts to the level's shape.
    """
    d = n_devices
    if isinstance(noise, NoiseLevels):
        levels = noise
    elif noise is False or (isinstance(noise, str) and noise.lower() in ("none", "off", "0")):
        levels = NoiseLevels.zero(d)
    else:
        rng = stream(seed, "noise_levels")

        def spread(shape):
            return np.exp(preset.noise_spread * rng.standard_normal(shape))

        levels = NoiseLevels(
            arw=preset.arw * spread((d, 3)),
            rrw=preset.rrw * spread((d, 3)),
            bias_instability=preset.bias_instability * spread((d, 3)),
            quantum=np.full(d, preset.quantum),
            accel_noise=np.full(d, preset.accel_noise),
            temp_noise=preset.temp_noise,
            temp_quantum=0.0,
            mag_noise=preset.mag_noise,
        )
        if noise is not None:
            if not isinstance(noise, dict):
                raise SpecError(f"cannot read noise setting {noise!r}",
                                hint="use None, 'none' or a dict such as {'arw': 1e-4}")
            kw = {}
            for key, value in noise.items():
                if key in _AXES3:
                    kw[key] = np.broadcast_to(np.asarray(value, float), (d, 3)).copy()
                elif key in _PER_DEVICE:
                    kw[key] = np.broadcast_to(np.asarray(value, float), (d,)).copy()
                elif key in _SCALARS:
                    kw[key] = float(value or 0.0)
                else:
                    valid = ", ".join(_AXES3 + _PER_DEVICE + _SCALARS)
                    raise SpecError(f"unknown noise level {key!r}", hint=f"valid: {valid}")
            levels = replace(levels, **kw)
    if levels.n_devices != d:
        raise SpecError(f"noise levels are for {levels.n_devices} devices, not {d}")
    if temp_quantum is not None:
        levels = replace(levels, temp_quantum=float(temp_quantum or 0.0))
    for f in fields(levels):
        v = np.asarray(getattr(levels, f.name), float)
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise SpecError(f"noise level {f.name} must be finite and non-negative")
    return levels


def gauss_markov_times(dt: float, duration: float) -> np.ndarray:
    """Correlation times of the flicker approximation: dt/2 .. duration, two per decade."""
    lo = 0.5 * dt
    hi = max(duration, 10.0 * lo)
    k = int(math.ceil(math.log(hi / lo) / math.log(GM_RATIO)))
    return lo * GM_RATIO ** np.arange(k + 1)


def _gauss_markov(n: int, dt: float, tau: float, var: float, shape, rng) -> np.ndarray:
    """Stationary first-order Gauss–Markov process (variance ``var``, correlation time
    ``tau``) on ``n`` samples; slow ones (τ ≥ 128·dt) are drawn on a grid of τ/32
    and interpolated linearly (their spectrum above 1/(2π·τ/32) is negligible)."""
    m = max(1, int(tau / (32.0 * dt)))
    if m < 4:
        m = 1
    k = (n - 1) // m + 2 if m > 1 else n
    h = m * dt
    a = math.exp(-h / tau)
    b = math.sqrt(var * (1.0 - a * a))
    x0 = rng.standard_normal((*shape, 1)) * math.sqrt(var)
    y = lfilter([b], [1.0, -a], rng.standard_normal((*shape, k)), axis=-1, zi=a * x0)[0]
    if m == 1:
        return y
    frac = np.arange(m) / m
    fine = y[..., :-1, None] + (y[..., 1:, None] - y[..., :-1, None]) * frac
    return fine.reshape(*shape, -1)[..., :n]


def flicker(n: int, dt: float, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    """Unit bias-instability noise (B = 1) of ``shape + (n,)``: sum of stationary
    Gauss–Markov processes (see the module docstring)."""
    var = math.log(GM_RATIO) / math.pi
    out = np.zeros((*shape, n))
    for tau in gauss_markov_times(dt, n * dt):
        out += _gauss_markov(n, dt, float(tau), var, shape, rng)
    return out


def gyro_noise(levels: NoiseLevels, n: int, dt: float, seed: int, keep: bool = False):
    """Additive gyro noise (devices, n, 3) and, if ``keep``, its parts by name."""
    rng = stream(seed, "gyro_noise")
    d = levels.n_devices
    parts = {}
    parts["white"] = rng.standard_normal((d, n, 3)) * (levels.arw / math.sqrt(dt))[:, None, :]
    steps = rng.standard_normal((d, n, 3)) * (levels.rrw * math.sqrt(dt))[:, None, :]
    steps[:, 0] = 0.0  # the walk starts at zero at the first sample
    parts["random_walk"] = np.cumsum(steps, axis=1)
    if np.any(levels.bias_instability > 0):
        fl = flicker(n, dt, (d, 3), rng)
        parts["flicker"] = np.moveaxis(fl, -1, 1) * levels.bias_instability[:, None, :]
    else:
        parts["flicker"] = np.zeros((d, n, 3))
    total = parts["white"] + parts["random_walk"] + parts["flicker"]
    return total, (parts if keep else {})


def quantise(x: np.ndarray, quantum) -> np.ndarray:
    """Round to multiples of ``quantum`` (broadcast over the leading axis); 0 keeps ``x``."""
    q = np.asarray(quantum, float)
    if q.ndim:
        q = q.reshape(q.shape + (1,) * (x.ndim - q.ndim))
    safe = np.where(q > 0, q, 1.0)
    return np.where(q > 0, np.round(x / safe) * safe, x)
