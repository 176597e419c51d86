"""The thermal bias polynomial of a calibration, re-expanded about an autopilot's reference.

diffgyro's ``bias_poly(k)`` is, per axis i (:mod:`diffgyro.effects._bias_poly`)::

    b_i(T) = Σ_j c_ij · T_s^j,     T_s = (clip(T, T_lo, T_hi) − centre) / scale

PX4 and ArduPilot evaluate ``Σ_m a_im · (T − T_ref)^m``. With ``δ = T_ref − centre``
the binomial expansion ``((u + δ) / s)^j = s^-j · Σ_m C(j, m) u^m δ^(j−m)`` gives
the exact coefficients ``a_im = Σ_{j≥m} c_ij · C(j, m) · δ^(j−m) / s^j``.
Both autopilots clamp T to their TMIN/TMAX as diffgyro clamps to the calibrated
range, so the two forms agree everywhere, up to the float32 rounding measured
by :func:`float32_error`.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .._vocabulary import UNITS
from ..calibration import Calibration, DeviceCalibration
from ..errors import DataError

#: Highest polynomial order PX4's TC_* and ArduPilot's INS_TCAL* parameters hold.
MAX_ORDER = 3


@dataclass(frozen=True)
class ThermalPoly:
    """One device's bias polynomial: ``coef`` (3, k+1) in the centred, scaled basis."""

    device: str
    coef: np.ndarray
    centre: float
    scale: float
    t_lo: float
    t_hi: float
    noise_floor: float   # rad/s per sample (fit quality), NaN if unknown
    unit: str = "rad/s"  # the measurement's (m/s² for the accelerometer)

    def about(self, t_ref: float) -> np.ndarray:
        """Coefficients (3, 4) of powers 0..3 of ``T − t_ref`` (exact binomial expansion)."""
        k = self.coef.shape[1] - 1
        delta = float(t_ref) - self.centre
        out = np.zeros((3, MAX_ORDER + 1))
        for j in range(k + 1):
            for m in range(j + 1):
                out[:, m] += self.coef[:, j] * math.comb(j, m) * delta ** (j - m) / self.scale**j
        return out

    def narrowed(self, t_lo: float, t_hi: float) -> ThermalPoly:
        """The same polynomial clamped to ``[t_lo, t_hi]`` (a range shared with another sensor)."""
        return dataclasses.replace(self, t_lo=float(t_lo), t_hi=float(t_hi))

    def relative(self, t_ref: float) -> ThermalPoly:
        """``b(T) − b(t_ref)``: the change from the reference temperature, what an
        accelerometer's thermal parameters hold (its constant is the offset calibration's)."""
        coef = np.array(self.coef, float)
        coef[:, 0] -= self.bias(np.array([t_ref]))[0]
        return dataclasses.replace(self, coef=coef)

    def bias(self, temp: np.ndarray) -> np.ndarray:
        """b(T) (n, 3) in float64, T clamped to the calibrated range (the reference)."""
        ts = (np.clip(np.asarray(temp, float), self.t_lo, self.t_hi) - self.centre) / self.scale
        return np.stack([np.polyval(self.coef[i, ::-1], ts) for i in range(3)], axis=-1)


def thermal_poly(cal: Calibration, dev: DeviceCalibration, fmt: str) -> ThermalPoly:
    """The device's ``bias_poly(k ≤ 3)``; any other term or a higher order is refused."""
    terms = cal.model_info.terms
    for t in terms:
        if t.name != "bias_poly":
            raise DataError(f"term {t.spec} cannot be written as {fmt} parameters: {fmt} holds "
                            f"a bias polynomial of temperature only (bias_poly(k), k ≤ {MAX_ORDER})",
                            device=dev.device, hint="refit with --model 'bias_poly(3)' to export")
        if t.order > MAX_ORDER:
            raise DataError(f"term {t.spec} cannot be written as {fmt} parameters: {fmt} holds "
                            f"polynomials up to order {MAX_ORDER}", device=dev.device,
                            hint=f"refit with --model 'bias_poly({MAX_ORDER})' to export")
    if len(terms) != 1:
        raise DataError(f"model {cal.model!r} cannot be written as {fmt} parameters: it needs "
                        "exactly one bias_poly term", device=dev.device)
    if dev.status != "ok":
        raise DataError(f"calibration has status {dev.status}; refusing to export it",
                        device=dev.device)
    order = terms[0].order
    if dev.temp_range is None:
        if order > 0:
            raise DataError("calibration has no calibrated temperature range", device=dev.device)
        lo = hi = dev.temp_centre   # a constant: any range gives the same offset
    else:
        lo, hi = (float(x) for x in dev.temp_range)
    floor = dev.quality.get("noise_floor")
    return ThermalPoly(device=dev.device, coef=np.asarray(dev.beta, float), centre=dev.temp_centre,
                       scale=dev.temp_scale, t_lo=lo, t_hi=hi,
                       noise_floor=float("nan") if floor is None else float(floor),
                       unit=UNITS[cal.channel])


def float32_error(poly: ThermalPoly, evaluate, n: int = 2001) -> float:
    """Largest |b_autopilot(T) − b(T)| (rad/s) over the calibrated range and a margin.

    ``evaluate(temp)`` is the autopilot's own formula on its float32 parameters,
    computed in float32 as the firmware does; the reference is the float64 fit.
    """
    span = max(poly.t_hi - poly.t_lo, 1.0)
    temp = np.linspace(poly.t_lo - 0.1 * span, poly.t_hi + 0.1 * span, n)
    return float(np.max(np.abs(np.asarray(evaluate(temp), float) - poly.bias(temp))))


def f32(x) -> np.float32:
    return np.float32(x)


def fmt_f32(x) -> str:
    """A float32 value written so that it reads back to the same float32 (9 digits)."""
    return format(float(np.float32(x)), ".9g")


def error_line(err: float, poly: ThermalPoly) -> str:
    """One sentence: the float32 error against the device's noise floor."""
    u = poly.unit
    if math.isfinite(poly.noise_floor) and poly.noise_floor > 0:
        return (f"float32 rounding of these parameters changes the bias by at most {err:.3g} {u} "
                f"over the calibrated range, {err / poly.noise_floor:.2g} × the noise floor "
                f"{poly.noise_floor:.3g} {u}")
    return f"float32 rounding of these parameters changes the bias by at most {err:.3g} {u}"
