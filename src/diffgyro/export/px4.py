"""PX4 gyro temperature compensation: ``TC_G{N}_*`` in QGroundControl's parameter file.

PX4 (src/modules/temperature_compensation/TemperatureCompensation.cpp,
``calc_thermal_offsets_3D``) computes per axis i::

    dT       = clamp(T, TC_Gn_TMIN, TC_Gn_TMAX) − TC_Gn_TREF
    offset_i = X0_i + X1_i·dT + X2_i·dT² + X3_i·dT³           (float32)

and src/lib/sensor_calibration/Gyroscope.hpp ``Correct`` subtracts it from the
raw rate: ``corrected = R · (raw − offset − CAL_GYROn offset)``. diffgyro's
``gyro = Ω + b(T)`` has the same sign, so ``offset = b(T)``. TREF is the centre
of the calibrated range, as PX4's own Tools/process_sensor_caldata.py sets it;
TMIN/TMAX are the calibrated range. PX4 finds the slot N whose ``TC_Gn_ID``
equals the sensor's device_id, so the ID must be the sensor's.
"""

from __future__ import annotations

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

__all__ = ["write", "parameters", "evaluate", "as_int32", "SLOTS", "NAME"]

NAME = "px4"
#: PX4 has TC_G0 .. TC_G3.
SLOTS = range(0, 4)
TYPE_INT32, TYPE_FLOAT32 = 6, 9


def parameters(poly: ThermalPoly, slot: int, device_id: int) -> list[tuple[str, float | int, int]]:
    """(name, value, MAVLink type) of one gyro slot, values before float32 rounding."""
    t_ref = 0.5 * (poly.t_lo + poly.t_hi)
    a = poly.about(t_ref)
    p = f"TC_G{slot}_"
    rows: list[tuple[str, float | int, int]] = [(p + "ID", as_int32(device_id), TYPE_INT32)]
    rows += [(p + "TMAX", poly.t_hi, TYPE_FLOAT32), (p + "TMIN", poly.t_lo, TYPE_FLOAT32),
             (p + "TREF", t_ref, TYPE_FLOAT32)]
    rows += [(f"{p}X{k}_{axis}", a[axis, k], TYPE_FLOAT32) for k in range(4) for axis in range(3)]
    return rows


def as_int32(device_id: int) -> int:
    """PX4's uint32 device_id as the int32 parameter that holds it (same bits)."""
    v = int(device_id) & 0xFFFFFFFF
    return v - (1 << 32) if v >= (1 << 31) else v


def evaluate(values: dict[str, float], slot: int, temp: np.ndarray) -> np.ndarray:
    """PX4's offset (n, 3) from parameter values, in float32 as the firmware computes it."""
    p = f"TC_G{slot}_"
    t = np.clip(temp.astype(np.float32), f32(values[p + "TMIN"]), f32(values[p + "TMAX"]))
    d = (t - f32(values[p + "TREF"])).astype(np.float32)
    d2 = d * d
    d3 = d2 * d
    return np.stack([f32(values[f"{p}X0_{i}"]) + f32(values[f"{p}X1_{i}"]) * d
                     + f32(values[f"{p}X2_{i}"]) * d2 + f32(values[f"{p}X3_{i}"]) * d3
                     for i in range(3)], axis=-1)


def write(cal: Calibration, devices: list[str], first_slot: int, device_ids: list[int],
          vehicle_id: int = 1, component_id: int = 1) -> tuple[str, list[str]]:
    """The parameter file's text and its report lines (float32 error per device)."""
    lines = ["# Onboard parameters for Vehicle 1", "#",
             "# Gyro temperature compensation written by diffgyro export --format px4",
             f"# model {cal.model}; offset = X0 + X1*dT + X2*dT^2 + X3*dT^3, "
             "dT = clamp(T, TMIN, TMAX) - TREF, subtracted from the raw rate (rad/s)"]
    rows, report = [("TC_G_ENABLE", 1, TYPE_INT32)], []
    for k, (name, dev_id) in enumerate(zip(devices, device_ids)):
        slot = first_slot + k
        poly = thermal_poly(cal, cal.device(name), NAME)
        params = parameters(poly, slot, dev_id)
        values = {n: (float(f32(v)) if t == TYPE_FLOAT32 else v) for n, v, t in params}
        err = float32_error(poly, lambda temp, v=values, s=slot: evaluate(v, s, temp))
        msg = f"device {name} -> TC_G{slot}: " + error_line(err, poly)
        lines.append("# " + msg)
        report.append(msg)
        rows += params
    lines.append("#")
    lines.append("# Vehicle-Id Component-Id Name Value Type")
    for name, value, typ in rows:
        text = str(int(value)) if typ == TYPE_INT32 else fmt_f32(value)
        lines.append(f"{vehicle_id}\t{component_id}\t{name}\t{text}\t{typ}")
    return "\n".join(lines) + "\n", report
