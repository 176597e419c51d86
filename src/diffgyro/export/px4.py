"""PX4 temperature compensation: ``TC_G{N}_*`` and ``TC_A{N}_*`` in QGroundControl's file.

PX4 (src/modules/temperature_compensation/TemperatureCompensation.cpp,
``calc_thermal_offsets_3D``, the same for the gyro's TC_G and the accelerometer's TC_A
slots) computes per axis i::

    dT       = clamp(T, TC_Xn_TMIN, TC_Xn_TMAX) − TC_Xn_TREF
    offset_i = X0_i + X1_i·dT + X2_i·dT² + X3_i·dT³           (float32)

and src/lib/sensor_calibration (``Gyroscope::Correct``, ``Accelerometer::Correct``)
subtracts it from the raw reading before the offset calibration and the board rotation:
``corrected = R · ((raw − offset − CAL offset) ⊙ CAL scale)`` (the gyro has no scale).
diffgyro's ``measured = true + b(T)`` has the same sign, so ``offset = b(T)``. TREF is the
centre of the calibrated range, as PX4's own Tools/process_sensor_caldata.py sets it;
TMIN/TMAX are the calibrated range. PX4 finds the slot N whose ``TC_Xn_ID`` equals the
sensor's device_id, so the ID must be the sensor's.

The accelerometer's offset is written relative to TREF (``X0 = 0``: the change
``b(T) − b(TREF)``): a soak in one orientation determines nothing more, and the
absolute offset is the accelerometer calibration's (``CAL_ACCn_*OFF``), made with the
compensation on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..calibration import Calibration
from ._thermal import (
    ThermalPoly,
    error_line,
    f32,
    float32_error,
    fmt_f32,
    thermal_poly,
)

__all__ = ["write", "parameters", "evaluate", "as_int32", "SLOTS", "NAME", "Sensors"]

NAME = "px4"
#: PX4 has TC_G0 .. TC_G3 and TC_A0 .. TC_A3.
SLOTS = range(0, 4)
TYPE_INT32, TYPE_FLOAT32 = 6, 9
#: The parameter letter of each channel.
LETTER = {"gyro": "G", "accel": "A"}


@dataclass(frozen=True)
class Sensors:
    """One channel's devices to write: their calibration, names, first slot and ids."""

    cal: Calibration
    devices: list[str]
    first_slot: int
    device_ids: list[int]


def _poly(cal: Calibration, name: str) -> ThermalPoly:
    """The device's polynomial as PX4 holds it (an accelerometer's relative to TREF)."""
    poly = thermal_poly(cal, cal.device(name), NAME)
    return poly if cal.channel == "gyro" else poly.relative(0.5 * (poly.t_lo + poly.t_hi))


def parameters(poly: ThermalPoly, slot: int, device_id: int,
               channel: str = "gyro") -> list[tuple[str, float | int, int]]:
    """(name, value, MAVLink type) of one slot, values before float32 rounding.

    **Arguments:**

    - ``poly``: the device's temperature polynomial.
    - ``slot``: the slot.
    - ``device_id``: the sensor's device id.
    - ``channel``: ``"gyro"`` (TC_G) or ``"accel"`` (TC_A).
    """
    t_ref = 0.5 * (poly.t_lo + poly.t_hi)
    a = poly.about(t_ref)
    p = f"TC_{LETTER[channel]}{slot}_"
    rows: list[tuple[str, float | int, int]] = [(p + "ID", as_int32(device_id), TYPE_INT32)]
    rows += [(p + "TMAX", poly.t_hi, TYPE_FLOAT32), (p + "TMIN", poly.t_lo, TYPE_FLOAT32),
             (p + "TREF", t_ref, TYPE_FLOAT32)]
    rows += [(f"{p}X{k}_{axis}", a[axis, k], TYPE_FLOAT32) for k in range(4) for axis in range(3)]
    return rows


def as_int32(device_id: int) -> int:
    """PX4's uint32 device_id as the int32 parameter that holds it (same bits).

    **Arguments:**

    - ``device_id``: the uint32 device id.
    """
    v = int(device_id) & 0xFFFFFFFF
    return v - (1 << 32) if v >= (1 << 31) else v


def evaluate(values: dict[str, float], slot: int, temp: np.ndarray,
             channel: str = "gyro") -> np.ndarray:
    """PX4's offset (n, 3) from parameter values, in float32 as the firmware computes it.

    **Arguments:**

    - ``values``: the parameters by name.
    - ``slot``: the slot.
    - ``temp``: temperatures (n,), °C.
    - ``channel``: ``"gyro"`` or ``"accel"``.
    """
    p = f"TC_{LETTER[channel]}{slot}_"
    t = np.clip(temp.astype(np.float32), f32(values[p + "TMIN"]), f32(values[p + "TMAX"]))
    d = (t - f32(values[p + "TREF"])).astype(np.float32)
    d2 = d * d
    d3 = d2 * d
    return np.stack([f32(values[f"{p}X0_{i}"]) + f32(values[f"{p}X1_{i}"]) * d
                     + f32(values[f"{p}X2_{i}"]) * d2 + f32(values[f"{p}X3_{i}"]) * d3
                     for i in range(3)], axis=-1)


def _block(s: Sensors) -> tuple[list, list[str]]:
    """One channel's parameter rows (its ENABLE first) and report lines."""
    channel = s.cal.channel
    letter = LETTER[channel]
    rows, report = [(f"TC_{letter}_ENABLE", 1, TYPE_INT32)], []
    for k, (name, dev_id) in enumerate(zip(s.devices, s.device_ids)):
        slot = s.first_slot + k
        poly = _poly(s.cal, name)
        params = parameters(poly, slot, dev_id, channel)
        values = {n: (float(f32(v)) if t == TYPE_FLOAT32 else v) for n, v, t in params}
        err = float32_error(poly, lambda temp, v=values, n=slot: evaluate(v, n, temp, channel))
        report.append(f"device {name} -> TC_{letter}{slot}: " + error_line(err, poly))
        rows += params
    return rows, report


def write(cal: Calibration | None, devices: list[str], first_slot: int, device_ids: list[int],
          vehicle_id: int = 1, component_id: int = 1,
          accel: Sensors | None = None) -> tuple[str, list[str]]:
    """The parameter file's text and its report lines (float32 error per device): the gyro
    slots of ``cal`` (None: none), then the accelerometer slots of ``accel``.

    **Arguments:**

    - ``cal``: the gyro calibration, or None.
    - ``devices``: the devices written, slot by slot.
    - ``first_slot``: the first slot.
    - ``device_ids``: the sensors' device ids.
    - ``vehicle_id``: the MAVLink system id.
    - ``component_id``: the MAVLink component id.
    - ``accel``: the accelerometers written after the gyros, or None.
    """
    blocks = ([Sensors(cal, devices, first_slot, device_ids)] if cal is not None else []) \
        + ([accel] if accel is not None else [])
    what = " and ".join({"gyro": "Gyro", "accel": "accelerometer"}[b.cal.channel] for b in blocks)
    lines = ["# Onboard parameters for Vehicle 1", "#",
             f"# {what} temperature compensation written by diffgyro export --format px4"]
    for b in blocks:
        unit = "rad/s" if b.cal.channel == "gyro" else "m/s^2, X0 = 0: relative to TREF"
        lines.append(f"# TC_{LETTER[b.cal.channel]}: model {b.cal.model}; offset = X0 + X1*dT + "
                     f"X2*dT^2 + X3*dT^3, dT = clamp(T, TMIN, TMAX) - TREF, subtracted from the "
                     f"raw reading ({unit})")
    rows, report = [], []
    for b in blocks:
        r, rep = _block(b)
        rows += r
        report += rep
    lines += ["# " + msg for msg in report]
    lines.append("#")
    lines.append("# Vehicle-Id Component-Id Name Value Type")
    for name, value, typ in rows:
        text = str(int(value)) if typ == TYPE_INT32 else fmt_f32(value)
        lines.append(f"{vehicle_id}\t{component_id}\t{name}\t{text}\t{typ}")
    return "\n".join(lines) + "\n", report
