"""Extra logged columns as model inputs: checks, centring and scaling, ranges.

An ``aux(NAME)`` term reads the extra column ``NAME`` of a batch (supply
voltage, a second board temperature, heater duty ...), centred and scaled
like temperature: ``x_s = (x - centre) / scale`` with centre and half-range
of the device's valid samples, so a polynomial of ``x_s`` is well
conditioned. A calibration stores centre, scale and the calibrated range per
column; compensation clamps the column to that range, as it does
temperature. A column a model uses must be finite on every valid sample and
must vary; otherwise :class:`~diffgyro.errors.DataError` names file, device
and column.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

import numpy as np

from ._vocabulary import aux_names  # noqa: F401  (its users read it here)
from .data import Batch
from .errors import DataError
from .signals import TempNorm

#: Relative half-range below which a column counts as constant.
MIN_RELATIVE_SPAN = 1e-9


def missing_message(batch: Batch, name: str) -> tuple[str, str]:
    """Problem and hint for a model that needs extra column ``name`` the data lacks."""
    have = ", ".join(batch.aux) or "none"
    return (f"needs extra column {name!r}, not in the data",
            f"extra columns in the data: {have}; columns holding text are ignored at load; "
            f"rename one with --columns {name}=name_in_file")


def column_problem(x: np.ndarray, vary: bool = True) -> str | None:
    """Why the valid samples ``x`` of one device's extra column cannot feed a term, or None:
    no numbers, a missing or non-finite value, or (``vary``) a constant."""
    bad = ~np.isfinite(x)
    if bad.all():
        return "extra column holds no numbers (all NaN)"
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        return f"extra column has a missing or non-finite value at sample {k + 1} of the device"
    lo, hi = float(x.min()), float(x.max())
    if vary and hi - lo <= MIN_RELATIVE_SPAN * max(abs(lo), abs(hi), 1e-300):
        return f"extra column is constant ({lo!r}): a term in it cannot be told from the bias"
    return None


def device_problems(batch: Batch, name: str, vary: bool = True) -> list[str | None]:
    """:func:`column_problem` of column ``name`` for every device of ``batch``."""
    values = np.asarray(batch.aux[name])
    return [column_problem(values[i, :int(batch.n_valid[i])], vary)
            for i in range(batch.n_devices)]


def check_columns(batch: Batch, names: Iterable[str], vary: bool = True) -> None:
    """DataError naming file, device and column for a missing, non-finite or (``vary``:
    a fit's data) constant column."""
    for name in names:
        if name not in batch.aux:
            problem, hint = missing_message(batch, name)
            raise DataError(problem, file=batch.sources[0] if batch.sources else None,
                            column=name, hint=hint)
        for i, problem in enumerate(device_problems(batch, name, vary)):
            if problem is None:
                continue
            where = dict(file=batch.sources[i] if batch.sources else None,
                         device=batch.devices[i], column=name)
            hint = ("a model term reading it needs a value on every sample"
                    if "missing or non-finite" in problem else None)
            raise DataError(problem, **where, hint=hint)


def ranges(batch: Batch, names: Iterable[str]) -> dict[str, np.ndarray]:
    """Per column, the (devices, 2) smallest and largest valid value."""
    out = {}
    for name in names:
        x = np.where(batch.mask, np.asarray(batch.aux[name], np.float64), np.nan)
        out[name] = np.stack([np.nanmin(x, axis=1), np.nanmax(x, axis=1)], axis=1)
    return out


def norms(batch: Batch, names: Iterable[str],
          given: Mapping[str, TempNorm] | None = None) -> dict[str, TempNorm]:
    """Centre and half-range of every column per device (numpy (d,) arrays), or the given
    ones broadcast to the devices."""
    given = dict(given or {})
    out = {}
    d = batch.n_devices
    for name, r in ranges(batch, names).items():
        if name in given:
            g = given[name]
            out[name] = TempNorm(centre=np.broadcast_to(np.asarray(g.centre, np.float64), (d,)),
                                 scale=np.broadcast_to(np.asarray(g.scale, np.float64), (d,)))
        else:
            half = 0.5 * (r[:, 1] - r[:, 0])
            out[name] = TempNorm(centre=0.5 * (r[:, 0] + r[:, 1]),
                                 scale=np.where(half > 0, half, 1.0))
    return out


def scaled(batch: Batch, norm: Mapping[str, TempNorm],
           clamp: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Every normalised column as a (devices, n) float64 array; ``clamp`` (per column,
    (devices, 2) ranges) clips the raw values first."""
    out = {}
    for name, nm in norm.items():
        x = np.asarray(batch.aux[name], np.float64)
        if clamp is not None and name in clamp:
            r = np.asarray(clamp[name], np.float64)
            x = np.clip(x, r[:, :1], r[:, 1:])
        out[name] = (x - np.asarray(nm.centre)[:, None]) / np.asarray(nm.scale)[:, None]
    return out
