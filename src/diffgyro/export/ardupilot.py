"""ArduPilot temperature calibration: ``INS_TCAL{n}_*`` in a ``NAME,VALUE`` file.

ArduPilot (libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp,
``TCal::correct_sensor``, the same for ``correct_gyro`` and ``correct_accel``;
AP_InertialSensor_Backend.cpp ``_rotate_and_correct_gyro`` / ``_accel``) corrects
each sensor, per axis, in float32::

    P(d)      = (C1 + (C2 + C3·d)·d)·d · 1e-6       (no constant term)
    T', Tc'   = clamp(T, TMIN, TMAX), clamp(CALTEMP, TMIN, TMAX)
    corrected = raw − P(T' − 35) + P(Tc' − 35) − OFFS

with the fixed reference TEMP_REFERENCE = 35 °C; ``C`` is ``GYRk`` or ``ACCk``, CALTEMP
``INS_GYRn_CALTEMP`` or ``INS_ACCn_CALTEMP`` and OFFS the offset measured at it. One
TMIN/TMAX serves both sensors of IMU n. With ``a`` a bias polynomial about 35 °C, the
export writes ``C_k = a_k · 1e6``. For the gyro it also writes INS_GYROFFS = b(Tc) at
Tc = clamp(35, TMIN, TMAX), so that ``OFFS − P(Tc − 35) = a_0`` and the correction is
b(T) exactly (ArduPilot measures it again at each boot when INS_GYR_CAL = 1). For the
accelerometer the offset and CALTEMP are the accelerometer calibration's (a soak in one
orientation does not determine them), and the ``+ P(Tc' − 35)`` term makes the
correction ``b(T) − b(Tc) + OFFS`` exact whenever that calibration is made.
"""

from __future__ import annotations

import numpy as np

from ..calibration import Calibration
from ._thermal import ThermalPoly, error_line, f32, float32_error, fmt_f32, thermal_poly

__all__ = ["write", "parameters", "accel_parameters", "evaluate", "evaluate_accel", "SLOTS",
           "NAME"]

NAME = "ardupilot"
#: INS_TCAL1 .. INS_TCAL3 (ArduPilot's three IMUs).
SLOTS = range(1, 4)
TEMP_REFERENCE = 35.0
SCALE_FACTOR = 1.0e6
AXES = "XYZ"


def _offset_names(n: int) -> list[str]:
    stem = "INS_GYROFFS" if n == 1 else f"INS_GYR{n}OFFS"
    return [f"{stem}_{a}" for a in AXES]


def _range(poly: ThermalPoly, n: int) -> list[tuple[str, float]]:
    p = f"INS_TCAL{n}_"
    return [(p + "ENABLE", 1.0), (p + "TMIN", poly.t_lo), (p + "TMAX", poly.t_hi)]


def _coefficients(poly: ThermalPoly, n: int, letters: str) -> list[tuple[str, float]]:
    a = poly.about(TEMP_REFERENCE)
    return [(f"INS_TCAL{n}_{letters}{k}_{AXES[i]}", a[i, k] * SCALE_FACTOR)
            for k in range(1, 4) for i in range(3)]


def parameters(poly: ThermalPoly, n: int, shared: bool = False) -> list[tuple[str, float]]:
    """(name, value) of IMU ``n``'s gyro temperature calibration and offset (float64);
    ``shared``: leave out ENABLE/TMIN/TMAX (written with the accelerometer's).

    **Arguments:**

    - ``poly``: the device's temperature polynomial.
    - ``n``: the IMU instance.
    - ``shared``: leave out ENABLE/TMIN/TMAX.
    """
    t_cal = float(np.clip(TEMP_REFERENCE, poly.t_lo, poly.t_hi))
    offs = poly.bias(np.array([t_cal]))[0]
    rows = ([] if shared else _range(poly, n)) + _coefficients(poly, n, "GYR")
    rows += list(zip(_offset_names(n), offs))
    rows.append((f"INS_GYR{n}_CALTEMP", t_cal))
    return rows


def accel_parameters(poly: ThermalPoly, n: int) -> list[tuple[str, float]]:
    """(name, value) of IMU ``n``'s accelerometer temperature calibration (float64).

    **Arguments:**

    - ``poly``: the device's temperature polynomial.
    - ``n``: the IMU instance.
    """
    return _range(poly, n) + _coefficients(poly, n, "ACC")


def _correct(values: dict, n: int, temp: np.ndarray, letters: str, cal_temp, offs) -> np.ndarray:
    """raw − corrected (n, 3) of ``TCal::correct_sensor`` and the offset, in float32."""
    p = f"INS_TCAL{n}_"
    lo, hi = f32(values[p + "TMIN"]), f32(values[p + "TMAX"])
    ref, inv = f32(TEMP_REFERENCE), f32(1.0 / SCALE_FACTOR)
    t = np.clip(temp.astype(np.float32), lo, hi)
    tc = np.clip(f32(cal_temp), lo, hi)
    out = []
    for i, axis in enumerate(AXES):
        c = [f32(values[f"{p}{letters}{k}_{axis}"]) for k in range(1, 4)]

        def poly(d, c=c):
            return (c[0] + (c[1] + c[2] * d) * d) * d * inv

        out.append(poly((t - ref).astype(np.float32)) - poly(f32(tc - ref)) + f32(offs[i]))
    return np.stack(out, axis=-1)


def evaluate(values: dict[str, float], n: int, temp: np.ndarray) -> np.ndarray:
    """ArduPilot's total gyro correction raw − corrected (n, 3), in float32 as the firmware.

    **Arguments:**

    - ``values``: the parameters by name.
    - ``n``: the IMU instance.
    - ``temp``: temperatures (n,), °C.
    """
    return _correct(values, n, temp, "GYR", values[f"INS_GYR{n}_CALTEMP"],
                    [values[k] for k in _offset_names(n)])


def evaluate_accel(values: dict[str, float], n: int, temp: np.ndarray, cal_temp: float = 35.0,
                   offsets=(0.0, 0.0, 0.0)) -> np.ndarray:
    """ArduPilot's accelerometer correction raw − corrected (n, 3) with an accelerometer
    calibration made at ``cal_temp`` (INS_ACCn_CALTEMP) that measured ``offsets``.

    **Arguments:**

    - ``values``: the parameters by name.
    - ``n``: the IMU instance.
    - ``temp``: temperatures (n,), °C.
    - ``cal_temp``: the accelerometer calibration's temperature, °C.
    - ``offsets``: the offsets it measured, m/s².
    """
    return _correct(values, n, temp, "ACC", cal_temp, offsets)


def _pairs(cal, devices, accel) -> list[tuple[ThermalPoly | None, ThermalPoly | None]]:
    """Per IMU, its gyro and accelerometer polynomials on their shared TMIN/TMAX (the
    overlap of the two calibrated ranges); the accelerometer's relative to 35 °C."""
    gyros = [thermal_poly(cal, cal.device(d), NAME) for d in devices] if cal is not None else []
    accs = ([thermal_poly(accel[0], accel[0].device(d), NAME) for d in accel[1]]
            if accel is not None else [])
    out = []
    for k in range(max(len(gyros), len(accs))):
        g = gyros[k] if k < len(gyros) else None
        a = accs[k] if k < len(accs) else None
        if g is not None and a is not None:
            lo, hi = max(g.t_lo, a.t_lo), min(g.t_hi, a.t_hi)
            lo, hi = (lo, hi) if lo <= hi else (g.t_lo, g.t_hi)
            g, a = g.narrowed(lo, hi), a.narrowed(lo, hi)
        if a is not None:
            a = a.relative(float(np.clip(TEMP_REFERENCE, a.t_lo, a.t_hi)))
        out.append((g, a))
    return out


def _shared_range(cal, g_name, acc_cal, a_name, shared: ThermalPoly, n: int) -> list[str]:
    """A line where IMU n's shared TMIN/TMAX is narrower than either sensor's own range."""
    own = {"gyro": cal.device(g_name).temp_range, "accelerometer": acc_cal.device(a_name).temp_range}
    cut = [f"the {what}'s {lo:.2f}..{hi:.2f} °C" for what, (lo, hi) in
           ((w, r) for w, r in own.items() if r is not None)
           if lo < shared.t_lo - 0.01 or hi > shared.t_hi + 0.01]
    if not cut:
        return []
    return [f"INS_TCAL{n} TMIN/TMAX {shared.t_lo:.2f}..{shared.t_hi:.2f} °C is the overlap of the "
            f"two sensors' calibrated ranges (narrower than {' and '.join(cut)}): each is "
            "clamped to it"]


def _id(cal: Calibration, name: str) -> str:
    """`` (device_id N)`` where the calibration knows the sensor's id (from the log)."""
    dev_id = cal.device(name).device_id
    return "" if dev_id is None else f" (device_id {dev_id})"


def write(cal: Calibration | None, devices: list[str], first_slot: int,
          accel: tuple[Calibration, list[str]] | None = None) -> tuple[str, list[str]]:
    """The .param file's text and its report lines (float32 error per device): the gyros
    of ``cal`` (None: none) and the accelerometers of ``accel``, IMU by IMU.

    **Arguments:**

    - ``cal``: the gyro calibration, or None.
    - ``devices``: the devices written, IMU by IMU.
    - ``first_slot``: the first IMU instance.
    - ``accel``: (accelerometer calibration, its devices), or None.
    """
    lines = ["# Temperature calibration written by diffgyro export --format ardupilot",
             "# corrected = raw - P(T - 35) + P(CALTEMP - 35) - OFFS, P(d) = (C1 + (C2 + C3*d)*d)*d*1e-6,",
             "# T clamped to [TMIN, TMAX]; C = GYRk (rad/s) or ACCk (m/s^2)"]
    if cal is not None:
        lines.append(f"# gyro model {cal.model}; INS_GYR_CAL = 1 (boot-time gyro calibration) "
                     "replaces GYROFFS and CALTEMP at boot")
    if accel is not None:
        lines.append(f"# accelerometer model {accel[0].model}; INS_ACCOFFS and INS_ACCn_CALTEMP "
                     "are the accelerometer calibration's (left as they are)")
    else:
        lines.append("# accelerometer INS_TCALn_ACC* parameters are left as they are")
    rows, report = [], []
    names = [(devices[k] if cal is not None and k < len(devices) else None,
              accel[1][k] if accel is not None and k < len(accel[1]) else None)
             for k in range(max(len(devices) if cal is not None else 0,
                                len(accel[1]) if accel is not None else 0))]
    for k, ((g, a), (g_name, a_name)) in enumerate(zip(_pairs(cal, devices, accel), names)):
        n = first_slot + k
        if g is not None and a is not None:
            report += _shared_range(cal, g_name, accel[0], a_name, g, n)
        if a is not None:
            params = accel_parameters(a, n)
            values = {key: float(f32(v)) for key, v in params}
            err = float32_error(a, lambda temp, v=values, s=n: evaluate_accel(v, s, temp))
            report.append(f"device {a_name} -> INS_TCAL{n} ACC{_id(accel[0], a_name)}: "
                          + error_line(err, a))
            rows += params
        if g is not None:
            params = parameters(g, n, shared=a is not None)
            values = {key: float(f32(v)) for key, v in (params + _range(g, n))}
            err = float32_error(g, lambda temp, v=values, s=n: evaluate(v, s, temp))
            report.append(f"device {g_name} -> INS_TCAL{n}{_id(cal, g_name)}: "
                          + error_line(err, g))
            rows += params
    lines += ["# " + msg for msg in report]
    lines += [f"{key},{fmt_f32(v)}" for key, v in rows]
    return "\n".join(lines) + "\n", report
