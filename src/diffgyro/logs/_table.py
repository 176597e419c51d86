"""The table every log reader returns, and the helpers the readers share."""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..errors import DataError

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["LogTable", "cut_at", "interp_join", "require", "table", "truncated"]


@dataclass
class LogTable:
    """A log read as a standard-schema frame, with what the reader noticed."""

    frame: pd.DataFrame
    warnings: list[str] = field(default_factory=list)
    # per device: metadata the schema has no column for (e.g. PX4's device_id)
    metadata: dict[str, dict[str, object]] = field(default_factory=dict)


def require(module: str, package: str, file: str):
    """Import ``module`` or raise a DataError telling how to install it."""
    try:
        return importlib.import_module(module)
    except ImportError:
        raise DataError(f"reading this log needs {package}", file=file,
                        hint='pip install "diffgyro[logs]"') from None


def interp_join(t: np.ndarray, t_other: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` sampled at ``t_other`` linearly interpolated at ``t``.

    Beyond the ends of ``t_other`` the first / last value is held. Columns of
    a 2-D ``values`` are interpolated separately.
    """
    values = np.asarray(values, dtype=np.float64)
    if values.ndim == 1:
        return np.interp(t, t_other, values)
    return np.stack([np.interp(t, t_other, values[:, k]) for k in range(values.shape[1])],
                    axis=1)


def table(devices: list[dict[str, np.ndarray | str]], file: str,
          warnings: list[str] | None = None) -> LogTable:
    """Stack per-device dicts (``device, t, gyro`` [, ``temp``, ``accel``]) in one frame.

    An optional group (temperature, accelerometer) that some devices lack is
    left out for all of them, with a warning (a table has one set of columns).
    """
    import pandas as pd  # a log's frame (a CSV is read without pandas)

    warnings = list(warnings or [])
    if not devices:
        raise DataError("no gyro data in the log", file=file)
    groups = []
    for sig, what in (("temp", "temperature"), ("accel", "accelerometer")):
        have = [d["device"] for d in devices if d.get(sig) is not None]
        if have and len(have) < len(devices):
            lacking = next(d["device"] for d in devices if d.get(sig) is None)
            warnings.append(f"warning: file {file}: device {lacking} has no {what}; "
                            f"the {what} of the other devices is left out too")
        elif have:
            groups.append(sig)
    parts = []
    for d in devices:
        n = len(d["t"])
        cols: dict[str, object] = {"device": np.full(n, d["device"], dtype=object),
                                   "t": np.asarray(d["t"], dtype=np.float64)}
        gyro = np.asarray(d["gyro"], dtype=np.float64)
        cols.update(gx=gyro[:, 0], gy=gyro[:, 1], gz=gyro[:, 2])
        if "temp" in groups:
            cols["temp"] = np.asarray(d["temp"], dtype=np.float64)
        if "accel" in groups:
            acc = np.asarray(d["accel"], dtype=np.float64)
            cols.update(ax=acc[:, 0], ay=acc[:, 1], az=acc[:, 2])
        parts.append(pd.DataFrame(cols))
    frame = pd.concat(parts, ignore_index=True)
    return LogTable(frame, warnings)


def truncated(file: str, cut: int, size: int, devices: list[dict]) -> str:
    """The warning line for a log cut off at byte ``cut`` of ``size`` (the bytes from there
    are not a whole message): how much gyro data was read, and that only it is used."""
    n = sum(len(d["t"]) for d in devices)
    t = np.concatenate([np.asarray(d["t"], dtype=np.float64) for d in devices])
    span = float(t.max() - t.min()) if t.size else 0.0
    of = f" of {len(devices)} devices" if len(devices) > 1 else ""
    when = f"{span:.1f}" if span >= 1 else f"{span:.3g}"
    return (f"warning: file {file}: truncated after {when} s of gyro data "
            f"({cut_at(cut, size)}); using the {n} complete samples{of}")


def cut_at(cut: int, size: int) -> str:
    """Where a log is cut off, in words."""
    return f"its last {size - cut} bytes, from byte {cut}, are not a whole message"
