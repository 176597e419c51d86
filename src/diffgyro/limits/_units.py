"""Units a limit's bounds may be written in (datasheet units), as factors into the record's.

A record holds rates in rad/s, noise densities (ARW) in rad/s/√Hz = rad/√s,
temperature coefficients in rad/s/K. A bound may name its unit, e.g.
``unit = "deg/s"``, ``"mdps"``, ``"deg/s/sqrt(Hz)"``, ``"mdps/√Hz"``,
``"deg/sqrt(h)"``, ``"deg/s/K"``: any rate unit of ``--gyro-unit``, alone, per
√Hz, or per kelvin (°C), and the angle random walk units deg/√h and rad/√s.

On the accelerometer channel a record holds m/s² (its noise densities m/s²/√Hz, its
temperature coefficients m/s²/K): a bound names an accelerometer unit of ``--acc-unit``
(``"m/s^2"``, ``"g"``, ``"mg"``, ``"ug"``), alone, per √Hz or per kelvin, and a rate
unit is refused there (``load(path, channel)``).
"""

from __future__ import annotations

import math

from ..errors import DataError
from ..io import resolve_units

UNIT_HELP = ("a rate unit (rad/s, deg/s, dps, mdps, deg/h ...), the same per sqrt(Hz) or per "
             "K, or deg/sqrt(h)")
ACCEL_UNIT_HELP = ("on the accelerometer channel an accelerometer unit (m/s^2, g, mg, ug), the "
                   "same per sqrt(Hz) or per K")
_SQRT_HZ = ("/sqrt(hz)", "/√hz", "/rthz", "/rt(hz)", "/hz^0.5", "/hz^(1/2)")
_PER_K = ("/k", "/°c", "/degc", "/c")
_ARW = {"deg/sqrt(h)": math.pi / 180.0 / 60.0, "deg/√h": math.pi / 180.0 / 60.0,
        "°/sqrt(h)": math.pi / 180.0 / 60.0, "°/√h": math.pi / 180.0 / 60.0,
        "deg/rt(h)": math.pi / 180.0 / 60.0, "deg/rth": math.pi / 180.0 / 60.0,
        "rad/sqrt(s)": 1.0, "rad/√s": 1.0}


def _rate(text: str, signal: str = "gyro") -> float | None:

    try:
        scale, offset = resolve_units({signal: text}).get(signal, (1.0, 0.0))  # SI: none
    except DataError:
        return None
    return scale if offset == 0.0 else None


def unit_scale(unit: str, channel: str = "gyro") -> float | None:
    """The factor that turns a value in ``unit`` into the record's unit (that of
    ``channel``: the gyro's rad/s, the accelerometer's m/s²), or None."""
    text = unit.strip().replace(" ", "").lower()
    signal = "gyro" if channel == "gyro" else "accel"
    if signal == "gyro" and text in _ARW:
        return _ARW[text]
    if signal == "accel":
        text = text.replace("²", "^2").replace("µ", "u")
    for suffix in _SQRT_HZ + _PER_K:
        if text.endswith(suffix) and len(text) > len(suffix):
            return _rate(text[: -len(suffix)], signal)
    return _rate(text, signal)
