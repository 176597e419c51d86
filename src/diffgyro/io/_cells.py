"""Physical limits and the check of every numeric cell (NaN, overflow, beyond a limit)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ..data import COLUMN_TO_SIGNAL

#: Closed interval of physically possible values (SI units) per signal; a value
#: outside is refused at load like NaN (see the module notes).
LIMITS: dict[str, tuple[float, float]] = {
    "gyro": (-1e8, 1e8), "rate": (-1e8, 1e8),          # rad/s (or raw counts)
    "accel": (-1e8, 1e8),                              # m/s² (or raw counts)
    "temp": (-273.15, 500.0), "temp_ext": (-273.15, 500.0),  # °C
}
_SI_UNIT = {"gyro": "rad/s", "rate": "rad/s", "accel": "m/s²", "temp": "°C",
            "temp_ext": "°C", "t": "s"}
_WHAT = {"gyro": "gyro", "rate": "reference rate", "accel": "accelerometer",
         "temp": "temperature", "temp_ext": "external temperature"}
NAN, INF, OVERFLOW, BEYOND = 1, 2, 3, 4


def check_cells(raw: Sequence[np.ndarray], numeric: Sequence[str],
                conv: Mapping[str, tuple[float, float]]) -> tuple[np.ndarray, np.ndarray]:
    """Values of the standard columns ``numeric`` (one 1-D array each) in SI units, as
    rows × columns (each column contiguous), and a code per cell: 0 valid, else
    :data:`NAN`, :data:`INF`, :data:`OVERFLOW` (in the unit conversion) or :data:`BEYOND`
    (outside :data:`LIMITS`).

    **Arguments:**

    - ``raw``: the columns as read, one 1-D array each.
    - ``numeric``: their standard names.
    - ``conv``: the unit conversion of each, ``{column: (scale, offset)}`` into SI.
    """
    si = np.empty((raw[0].shape[0], len(raw)), np.float64, order="F")
    for j, column in enumerate(raw):
        si[:, j] = column
    code = np.zeros(si.shape, np.int8, order="F")
    code[np.isnan(si)] = NAN
    code[np.isinf(si)] = INF
    for j, std in enumerate(numeric):
        sig = "t" if std == "t" else COLUMN_TO_SIGNAL[std]
        if sig in conv:
            scale, offset = conv[sig]
            with np.errstate(over="ignore", invalid="ignore"):
                si[:, j] = si[:, j] * scale + offset
            code[(code[:, j] == 0) & ~np.isfinite(si[:, j]), j] = OVERFLOW
        if sig in LIMITS:
            lo, hi = LIMITS[sig]
            with np.errstate(invalid="ignore"):
                out = (si[:, j] < lo) | (si[:, j] > hi)
            code[(code[:, j] == 0) & out, j] = BEYOND
    return si, code


def cell_problem(code: int, raw: float, std: str, conv: Mapping) -> tuple[str, str]:
    """The problem and the hint of an invalid cell (a :func:`check_cells` code).

    **Arguments:**

    - ``code``: the cell's code from :func:`check_cells`.
    - ``raw``: the cell's value as read.
    - ``std``: its standard column's name.
    - ``conv``: the unit conversion of each column, ``{column: (scale, offset)}``.
    """
    drop = "use --drop-invalid (drop_invalid=True) to skip such rows; the count is reported"
    if code == NAN:
        return "missing or NaN value", drop
    if code == INF:
        return "infinite value", drop
    if code == OVERFLOW:
        return "value overflows in unit conversion", drop
    sig = COLUMN_TO_SIGNAL[std]
    lo, hi = LIMITS[sig]
    scale, offset = conv.get(sig, (1.0, 0.0))
    unit = _SI_UNIT[sig]
    value = f"{raw * scale + offset:.6g} {unit}" + ("" if sig not in conv else f" (read {raw:.6g})")
    if sig.startswith("temp"):
        bound = f"below absolute zero, {lo} {unit}" if raw * scale + offset < lo else \
            f"above {hi:g} {unit}"
    else:
        bound = f"beyond ±{hi:g} {unit}"
    option = {"gyro": "--gyro-unit", "rate": "--gyro-unit", "accel": "--acc-unit"}.get(
        sig, "--temp-unit")
    return (f"{_WHAT[sig]} value {value} is not physical ({bound})",
            f"check the unit ({option}) and the column mapping; or {drop}")


