"""ArduPilot gyro temperature calibration: ``INS_TCAL{n}_*`` in a ``NAME,VALUE`` file.

ArduPilot (libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp,
``TCal::correct_sensor``; AP_InertialSensor_Backend.cpp
``_rotate_and_correct_gyro``) corrects the gyro, per axis, in float32::

    P(d)      = (GYR1 + (GYR2 + GYR3·d)·d)·d · 1e-6       (no constant term)
    T', Tc'   = clamp(T, TMIN, TMAX), clamp(INS_GYRn_CALTEMP, TMIN, TMAX)
    corrected = raw − P(T' − 35) + P(Tc' − 35) − INS_GYROFFS

with the fixed reference TEMP_REFERENCE = 35 °C. The polynomial has no
constant: the constant is the gyro offset, measured at INS_GYRn_CALTEMP. With
``a`` the bias polynomial about 35 °C, the export writes GYRk = a_k · 1e6 and
INS_GYROFFS = b(Tc) at Tc = clamp(35, TMIN, TMAX), so that
``OFFS − P(Tc − 35) = a_0`` and the correction is b(T) exactly. ArduPilot
measures the offset again at each boot when INS_GYR_CAL = 1 (its default):
that replaces INS_GYROFFS and CALTEMP by the boot-time b(T_boot) (the device
must be still), which the polynomial form accounts for.
"""

from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from ._thermal import ThermalPoly, error_line, f32, float32_error, fmt_f32, thermal_poly

__all__ = ["write", "parameters", "evaluate", "SLOTS", "NAME"]

NAME = "ardupilot"
#: INS_TCAL1 .. INS_TCAL3 (ArduPilot's three IMUs).
SLOTS = range(1, 4)
TEMP_REFERENCE = 35.0
SCALE_FACTOR = 1.0e6
AXES = "XYZ"


def _offset_names(n: int) -> list[str]:
    stem = "INS_GYROFFS" if n == 1 else f"INS_GYR{n}OFFS"
    return [f"{stem}_{a}" for a in AXES]


def parameters(poly: ThermalPoly, n: int) -> list[tuple[str, float]]:
    """(name, value) of IMU ``n``'s temperature calibration and gyro offset (float64)."""
    a = poly.about(TEMP_REFERENCE)
    t_cal = float(np.clip(TEMP_REFERENCE, poly.t_lo, poly.t_hi))
    offs = poly.bias(np.array([t_cal]))[0]
    p = f"INS_TCAL{n}_"
    rows = [(p + "ENABLE", 1.0), (p + "TMIN", poly.t_lo), (p + "TMAX", poly.t_hi)]
    rows += [(f"{p}GYR{k}_{AXES[i]}", a[i, k] * SCALE_FACTOR) for k in range(1, 4) for i in range(3)]
    rows += list(zip(_offset_names(n), offs))
    rows.append((f"INS_GYR{n}_CALTEMP", t_cal))
    return rows


def evaluate(values: dict[str, float], n: int, temp: np.ndarray) -> np.ndarray:
    """ArduPilot's total correction raw − corrected (n, 3), in float32 as the firmware does."""
    p = f"INS_TCAL{n}_"
    lo, hi = f32(values[p + "TMIN"]), f32(values[p + "TMAX"])
    ref, inv = f32(TEMP_REFERENCE), f32(1.0 / SCALE_FACTOR)
    t = np.clip(temp.astype(np.float32), lo, hi)
    tc = np.clip(f32(values[f"INS_GYR{n}_CALTEMP"]), lo, hi)
    out = []
    for i, axis in enumerate(AXES):
        c = [f32(values[f"{p}GYR{k}_{axis}"]) for k in range(1, 4)]

        def poly(d, c=c):
            return (c[0] + (c[1] + c[2] * d) * d) * d * inv

        offs = f32(values[_offset_names(n)[i]])
        out.append(poly((t - ref).astype(np.float32)) - poly(f32(tc - ref)) + offs)
    return np.stack(out, axis=-1)


def write(cal: Calibration, devices: list[str], first_slot: int) -> tuple[str, list[str]]:
    """The .param file's text and its report lines (float32 error per device)."""
    lines = ["# Gyro temperature calibration written by diffgyro export --format ardupilot",
             f"# model {cal.model}; corrected = raw - P(T - 35) + P(CALTEMP - 35) - GYROFFS,",
             "# P(d) = (GYR1 + (GYR2 + GYR3*d)*d)*d*1e-6, T clamped to [TMIN, TMAX] (rad/s)",
             "# INS_GYR_CAL = 1 (boot-time gyro calibration) replaces GYROFFS and CALTEMP at boot;",
             "# accelerometer INS_TCALn_ACC* parameters are left as they are"]
    rows, report = [], []
    for k, name in enumerate(devices):
        n = first_slot + k
        poly = thermal_poly(cal, cal.device(name), NAME)
        params = parameters(poly, n)
        values = {key: float(f32(v)) for key, v in params}
        err = float32_error(poly, lambda temp, v=values, s=n: evaluate(v, s, temp))
        msg = f"device {name} -> INS_TCAL{n}: " + error_line(err, poly)
        lines.append("# " + msg)
        report.append(msg)
        rows += params
    lines += [f"{key},{fmt_f32(v)}" for key, v in rows]
    return "\n".join(lines) + "\n", report
