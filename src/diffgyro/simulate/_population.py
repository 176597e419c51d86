"""Device populations: true coefficients for every effect term, drawn from realistic spreads.

Coefficients are drawn in the error model's own basis (normalised temperature, :class:`~diffgyro.signals.TempNorm`), so a
fit given the same :class:`~diffgyro.signals.TempNorm` recovers them
directly. Temperature polynomials are specified physically: ``*_edges[j]`` is
the 1-σ contribution of order ``j`` at ``REF_HALF_RANGE`` °C from the centre,
so for a normalisation of half-range ``s`` the coefficient of ``T_s^j`` has
σ ``edges[j]·(s / REF_HALF_RANGE)^j`` (the same device physics whatever the
plan's range). Every coefficient is zero-mean Gaussian unless a range is
given (time constants: log-uniform; thermal constants: uniform).

Random streams are keyed by the seed and the term name, so adding an effect
to a spec does not change the coefficients drawn for the others, and orders
are nested (``bias_poly(3)`` extends ``bias_poly(2)``'s draws).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, fields

import numpy as np

from ..effects import (
    MAX_ORDER,
    AbstractEffect,
    Aux,
    BiasPoly,
    Gradient,
    GSens,
    Hysteresis,
    Misalignment,
    ScaleAsym,
    ScaleNonlin,
    ScalePoly,
    TempDiff,
    Term,
    ThermalLag,
    Warmup,
)
from ..errors import SpecError
from ..model import ErrorModel, Params
from ._motion import DEG, G0

#: Temperature half-range (°C) at which the preset polynomial contributions are stated.
REF_HALF_RANGE = 50.0
DPH = DEG / 3600.0  # one degree per hour in rad/s


@dataclass(frozen=True)
class Preset:
    """Typical 1-σ spreads of a sensor class (rad/s unless stated)."""

    name: str
    bias_edges: tuple[float, ...]          # rad/s at ±50 °C per order (order 0: constant)
    scale_edges: tuple[float, ...]         # dimensionless at ±50 °C per order
    scale_asym: float                      # dimensionless
    scale_nonlin: float                    # (rad/s)^-2
    misalignment: float                    # rad
    g_sens: float                          # rad/s per m/s²
    gradient: float                        # rad/s per °C/s
    temp_diff: float                       # rad/s per °C
    hysteresis: float                      # rad/s
    warmup: float                          # rad/s
    warmup_tau: tuple[float, float]        # s, log-uniform
    lag_tau: tuple[float, float]           # s, log-uniform (thermal_lag)
    tau_sensor: tuple[float, float]        # s, sensor vs chamber lag (uniform)
    self_heating: tuple[float, float]      # °C above chamber at nominal power (uniform)
    tau_heating: tuple[float, float]       # s, self-heating time constant (uniform)
    arw: float                             # rad/s/√Hz
    rrw: float                             # rad/s²/√Hz
    bias_instability: float                # rad/s (IEEE B; ADEV floor 0.664·B)
    quantum: float                         # rad/s (output LSB)
    temp_noise: float                      # °C, read-out white noise σ
    accel_noise: float                     # m/s²/√Hz
    mag_noise: float                       # µT per sample
    noise_spread: float                    # log-normal σ of device-to-device noise levels
    accel_bias: float                      # m/s²
    accel_scale: float                     # dimensionless
    accel_misalignment: float              # rad


MEMS = Preset(
    name="mems",
    bias_edges=(0.5 * DEG, 0.01 * DEG * REF_HALF_RANGE, 0.1 * DEG, 0.05 * DEG),
    scale_edges=(1000e-6, 100e-6 * REF_HALF_RANGE, 1000e-6, 500e-6),
    scale_asym=200e-6,
    scale_nonlin=1e-3 / (300 * DEG) ** 2,       # 0.1 % at 300 °/s
    misalignment=1e-3,
    g_sens=0.05 * DEG / G0,                       # 0.05 °/s/g
    gradient=0.02 * DEG * 60.0,                   # 0.02 °/s per °C/min
    temp_diff=0.005 * DEG,                        # 0.005 °/s/°C
    hysteresis=0.02 * DEG,
    warmup=0.1 * DEG,
    warmup_tau=(60.0, 600.0),
    lag_tau=(120.0, 600.0),
    tau_sensor=(300.0, 900.0),
    self_heating=(2.0, 5.0),
    tau_heating=(600.0, 1200.0),
    arw=0.01 * DEG,                               # 0.6 °/√h
    rrw=10.0 * DPH / 60.0,                        # 10 °/h/√h
    bias_instability=5.0 * DPH,
    quantum=DEG / 131.0,                          # 16-bit, ±250 °/s
    temp_noise=0.01,
    accel_noise=1e-3,                             # ≈ 100 µg/√Hz
    mag_noise=0.3,
    noise_spread=0.15,
    accel_bias=0.05,
    accel_scale=1e-3,
    accel_misalignment=1e-3,
)

FOG = Preset(
    name="fog",
    bias_edges=(1.0 * DPH, 0.02 * DPH * REF_HALF_RANGE, 0.3 * DPH, 0.1 * DPH),
    scale_edges=(50e-6, 2e-6 * REF_HALF_RANGE, 30e-6, 10e-6),
    scale_asym=10e-6,
    scale_nonlin=10e-6 / (300 * DEG) ** 2,      # 10 ppm at 300 °/s
    misalignment=1e-4,
    g_sens=0.2 * DPH / G0,
    gradient=0.5 * DPH * 60.0,                    # Shupe: 0.5 °/h per °C/min
    temp_diff=0.05 * DPH,
    hysteresis=0.05 * DPH,
    warmup=3.0 * DPH,
    warmup_tau=(300.0, 1800.0),
    lag_tau=(600.0, 1800.0),
    tau_sensor=(600.0, 1200.0),
    self_heating=(3.0, 8.0),
    tau_heating=(1200.0, 2400.0),
    arw=0.005 * DEG / 60.0,                       # 0.005 °/√h
    rrw=0.005 * DPH / 60.0,
    bias_instability=0.01 * DPH,
    quantum=1e-4 * DPH,
    temp_noise=0.005,
    accel_noise=5e-5,
    mag_noise=0.1,
    noise_spread=0.1,
    accel_bias=2e-3,
    accel_scale=1e-4,
    accel_misalignment=1e-4,
)

PRESETS: dict[str, Preset] = {"mems": MEMS, "fog": FOG}


def get_preset(name: str | Preset) -> Preset:
    if isinstance(name, Preset):
        return name
    try:
        return PRESETS[str(name).lower()]
    except KeyError:
        raise SpecError(f"unknown preset {name!r}", hint=f"use one of {', '.join(PRESETS)}") from None


def stream(seed: int, key: str) -> np.random.Generator:
    """Independent random stream for one purpose (``key``) of a seeded simulation."""
    return np.random.default_rng([int(seed), zlib.crc32(key.encode())])


def _edges(edges: tuple[float, ...], order: int) -> np.ndarray:
    out = list(edges)
    while len(out) <= order:
        out.append(out[-1] * 0.5)
    return np.asarray(out[: order + 1])


def _poly(seed: int, key: str, d: int, edges, order: int, scale: float) -> np.ndarray:
    """(d, 3, order+1) polynomial coefficients in T_s with half-range ``scale``."""
    z = stream(seed, key).standard_normal((d, 3, MAX_ORDER + 1))[..., : order + 1]
    j = np.arange(order + 1)
    return z * _edges(edges, order) * (scale / REF_HALF_RANGE) ** j


def _normal(seed: int, key: str, d: int, width: int, sigma: float) -> np.ndarray:
    return stream(seed, key).standard_normal((d, 3, width)) * sigma


def _log_uniform(seed: int, key: str, d: int, lo_hi: tuple[float, float]) -> np.ndarray:
    lo, hi = lo_hi
    return np.exp(stream(seed, key).uniform(math.log(lo), math.log(hi), d))


def draw_params(model: ErrorModel, preset: Preset, n_devices: int, seed: int, temp_scale: float) -> Params:
    """True parameters of ``n_devices`` devices for every deterministic term of ``model``.

    ``temp_scale`` is the half-range of the TempNorm the coefficients refer to.
    Returns Params with beta (d, 3, P) and theta (d, Q) (theta = log τ).
    """
    d = n_devices
    bias_order = max((t.order for t in model.terms if isinstance(t, BiasPoly)), default=-1)
    betas, thetas = [], []
    for term in model.terms:
        beta, theta = _draw_term(term, preset, d, seed, temp_scale, bias_order)
        betas.append(beta)
        thetas.append(theta)
    beta = np.concatenate(betas, axis=-1) if betas else np.zeros((d, 3, 0))
    theta = np.concatenate(thetas, axis=-1) if thetas else np.zeros((d, 0))
    return Params(beta=beta, theta=theta)


def _draw_term(term: AbstractEffect, p: Preset, d: int, seed: int, scale: float, bias_order: int):
    none = np.zeros((d, 0))
    if isinstance(term, BiasPoly):
        return _poly(seed, "bias_poly", d, p.bias_edges, term.order, scale), none
    if isinstance(term, ScalePoly):
        return _poly(seed, "scale_poly", d, p.scale_edges, term.order, scale), none
    if isinstance(term, ThermalLag):
        # The bias polynomial sees the lagged temperature: l_j = c_j where bias_poly has order j.
        own = _poly(seed, "thermal_lag", d, p.bias_edges, term.order, scale)[..., 1:]
        shared = _poly(seed, "bias_poly", d, p.bias_edges, term.order, scale)[..., 1:]
        j = np.arange(1, term.order + 1)
        beta = np.where(j <= bias_order, shared, own)
        return beta, np.log(_log_uniform(seed, "thermal_lag.tau", d, p.lag_tau))[:, None]
    if isinstance(term, Warmup):
        return (_normal(seed, "warmup", d, 1, p.warmup),
                np.log(_log_uniform(seed, "warmup.tau", d, p.warmup_tau))[:, None])
    simple = {
        ScaleAsym: p.scale_asym, ScaleNonlin: p.scale_nonlin, Misalignment: p.misalignment,
        GSens: p.g_sens, Gradient: p.gradient, TempDiff: p.temp_diff, Hysteresis: p.hysteresis,
    }
    for cls, sigma in simple.items():
        if isinstance(term, cls):
            return _normal(seed, term.name, d, term.n_params, sigma), none
    if isinstance(term, Aux):  # about the linear temperature term's size over the range
        return _normal(seed, term.spec, d, term.n_params, p.bias_edges[1] / 3.0), none
    if isinstance(term, Term):  # a product of centred signals: sized like aux(NAME)
        theta = (np.log(_log_uniform(seed, f"{term.spec}.tau", d, p.lag_tau))[:, None]
                 if term.n_nonlinear else none)
        return _normal(seed, term.spec, d, term.n_params, p.bias_edges[1] / 3.0), theta
    raise SpecError(f"the simulator has no population for effect {term.spec!r}",
                    hint="pass params=Params(beta, theta) to simulate() to set its coefficients")


def draw_thermal(preset: Preset, n_devices: int, seed: int) -> dict[str, np.ndarray]:
    """Per-device thermal constants: sensor lag τ_s, self-heating H and its τ_h."""
    rng = stream(seed, "thermal")
    u = rng.uniform(size=(3, n_devices))

    def pick(lo_hi, x):
        return lo_hi[0] + (lo_hi[1] - lo_hi[0]) * x

    return {"tau_sensor": pick(preset.tau_sensor, u[0]),
            "self_heating": pick(preset.self_heating, u[1]),
            "tau_heating": pick(preset.tau_heating, u[2])}


def draw_accel_errors(preset: Preset, n_devices: int, seed: int, enabled: bool) -> dict[str, np.ndarray]:
    """Accelerometer bias and matrix: ``a_raw = (I + K)·f + bias``.

    Returned in imucal's convention as well: ``accel_matrix = (I + K)⁻¹`` so
    that ``f = accel_matrix · (a_raw − accel_bias)``.
    """
    d = n_devices
    eye = np.broadcast_to(np.eye(3), (d, 3, 3))
    if not enabled:
        return {"bias": np.zeros((d, 3)), "error_matrix": np.zeros((d, 3, 3)),
                "matrix": eye.copy()}
    rng = stream(seed, "accel")
    bias = rng.standard_normal((d, 3)) * preset.accel_bias
    k = rng.standard_normal((d, 3, 3)) * preset.accel_misalignment
    diag = rng.standard_normal((d, 3)) * preset.accel_scale
    k[:, np.arange(3), np.arange(3)] = diag
    return {"bias": bias, "error_matrix": k, "matrix": np.linalg.inv(eye + k)}


def preset_dict(preset: Preset) -> dict:
    return {f.name: getattr(preset, f.name) for f in fields(preset)}
