"""Units of the input columns: the names users write and their SI factors."""

from __future__ import annotations

import math
from collections.abc import Mapping

from ..errors import DataError

_DEG = math.pi / 180.0
_G0 = 9.80665  # standard gravity, m/s²

# kind -> canonical unit -> (scale, offset): SI = scale * value + offset
UNITS: dict[str, dict[str, tuple[float, float]]] = {
    "time": {"s": (1.0, 0.0), "ms": (1e-3, 0.0), "us": (1e-6, 0.0), "ns": (1e-9, 0.0),
             "min": (60.0, 0.0), "h": (3600.0, 0.0)},
    "rate": {"rad/s": (1.0, 0.0), "mrad/s": (1e-3, 0.0), "urad/s": (1e-6, 0.0),
             "deg/s": (_DEG, 0.0), "mdeg/s": (_DEG * 1e-3, 0.0),
             "deg/min": (_DEG / 60.0, 0.0), "deg/h": (_DEG / 3600.0, 0.0),
             "rad/h": (1.0 / 3600.0, 0.0), "rpm": (2.0 * math.pi / 60.0, 0.0),
             "rev/s": (2.0 * math.pi, 0.0)},
    "accel": {"m/s^2": (1.0, 0.0), "g": (_G0, 0.0), "mg": (_G0 * 1e-3, 0.0),
              "ug": (_G0 * 1e-6, 0.0)},
    "temp": {"C": (1.0, 0.0), "K": (1.0, -273.15), "F": (5.0 / 9.0, -32.0 * 5.0 / 9.0)},
}
_ALIASES = {
    "sec": "s", "second": "s", "seconds": "s", "msec": "ms", "µs": "us", "μs": "us",
    "usec": "us", "hour": "h", "hr": "h", "minute": "min",
    "rad/sec": "rad/s", "dps": "deg/s", "°/s": "deg/s", "deg/sec": "deg/s",
    "mdps": "mdeg/s", "m°/s": "mdeg/s", "°/h": "deg/h", "deg/hr": "deg/h", "dph": "deg/h",
    "°/min": "deg/min", "µrad/s": "urad/s", "μrad/s": "urad/s", "r/min": "rpm",
    "m/s2": "m/s^2", "m/s²": "m/s^2", "m/s/s": "m/s^2", "µg": "ug", "μg": "ug",
    "c": "C", "°c": "C", "degc": "C", "celsius": "C", "k": "K", "kelvin": "K",
    "f": "F", "°f": "F", "degf": "F", "fahrenheit": "F",
}
#: Which unit table each signal uses (None: any unit, no conversion).
SIGNAL_KIND: dict[str, str | None] = {"t": "time", "gyro": "rate", "rate": "rate",
                                      "accel": "accel", "temp": "temp", "temp_ext": "temp",
                                      "mag": None}
#: How a user sets each unit (for messages).
UNIT_OPTION = {"t": "--time-unit", "gyro": "--gyro-unit", "accel": "--acc-unit",
               "temp": "--temp-unit"}


def canonical_unit(kind: str, text: str) -> str | None:
    """The name in :data:`UNITS` of unit ``text`` of ``kind`` (aliases such as ``dps``,
    ``°/s``, ``m/s²``, ``degC``, ``µs`` included); None if it is not one."""
    table = UNITS[kind]
    raw = str(text).strip()
    if raw in table:
        return raw
    key = raw.replace(" ", "").lower()
    key = _ALIASES.get(key, key).lower()
    for name in table:
        if name.lower() == key:
            return name
    return None


def resolve_units(units: Mapping[str, str] | None) -> dict[str, tuple[float, float]]:
    """Map ``{"gyro": "deg/s", ...}`` to ``{signal: (scale, offset)}`` into SI.

    Keys are signal names: ``t, gyro, rate, accel, temp, temp_ext, mag``.
    ``rate`` (reference rate) follows ``gyro`` and ``temp_ext`` follows
    ``temp`` unless given. ``mag`` accepts any unit and is not converted.
    Unknown signals or units raise :class:`DataError` listing valid ones.

    **Arguments:**

    - ``units``: signal -> unit name (None: all SI).
    """
    units = dict(units or {})
    for key in units:
        if key not in SIGNAL_KIND:
            raise DataError(f"unknown signal {key!r} in units",
                            hint="valid: " + ", ".join(SIGNAL_KIND))
    if "gyro" in units and "rate" not in units:
        units["rate"] = units["gyro"]
    if "temp" in units and "temp_ext" not in units:
        units["temp_ext"] = units["temp"]
    out: dict[str, tuple[float, float]] = {}
    for sig, text in units.items():
        kind = SIGNAL_KIND[sig]
        if kind is None or text is None:
            continue
        name = canonical_unit(kind, text)
        if name is None:
            how = UNIT_OPTION.get(sig, f"units[{sig!r}]")
            if sig in UNIT_OPTION:
                how += f" / units[{sig!r}]"
            raise DataError(f"unknown {sig} unit {str(text)!r} (option {how})",
                            hint="valid: " + ", ".join(UNITS[kind]))
        scale, offset = UNITS[kind][name]
        if scale != 1.0 or offset != 0.0:
            out[sig] = (scale, offset)
    return out


