"""Data-loading options shared by the commands that read recordings.

Use in a command module (``fit``, ``diagnose``, ``allan``, ``recipe`` ...)::

    from ._options import (AccUnit, Columns, DataFiles, DropInvalid, GyroUnit,
                           SamplingRate, TempUnit, TimeUnit, load_from_cli)

    @app.command("fit")
    def fit_command(data: DataFiles, columns: Columns = None, gyro_unit: GyroUnit = None,
                    acc_unit: AccUnit = None, temp_unit: TempUnit = None,
                    time_unit: TimeUnit = None, sampling_rate: SamplingRate = None,
                    drop_invalid: DropInvalid = False, ...):
        batch = load_from_cli(data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                              sampling_rate, drop_invalid, min_samples=model_needs)

``load_from_cli`` returns a padded :class:`~diffgyro.data.Batch`, prints
"dropped N rows ... in file F device D" lines to stderr when
``--drop-invalid`` skipped rows, and lets :class:`~diffgyro.errors.DataError`
propagate (the CLI turns it into one line on stderr and exit code 2).
Pass ``batch=False`` to get the list of recordings instead.
This module starts with ``_`` so it is not imported as a command.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

_UNITS_HELP = "Unit of {what} in the files: {units} (converted to {si})."

DataFiles = Annotated[
    list[Path],
    typer.Argument(help="Data files (CSV, TSV, Parquet, NPZ) in the standard schema; "
                        "one or many devices per file (a 'device' column); or logs: "
                        "PX4 .ulg, ROS .bag / .mcap / rosbag2 folder, ArduPilot .bin / .log.",
                   show_default=False),
]
Columns = Annotated[
    str | None,
    typer.Option("--columns", help="Map standard columns to the names in the files, "
                                   "e.g. 'gx=gyr_x,gy=gyr_y,gz=gyr_z,t=time'; another "
                                   "left-hand name renames an extra column for aux(NAME), "
                                   "e.g. 'vdd=Supply V'."),
]
GyroUnit = Annotated[
    str | None,
    typer.Option("--gyro-unit", help=_UNITS_HELP.format(
        what="gyro and reference rates", units="rad/s, deg/s, mdps, deg/h, rpm, ...",
        si="rad/s")),
]
AccUnit = Annotated[
    str | None,
    typer.Option("--acc-unit", help=_UNITS_HELP.format(
        what="accelerometer specific force", units="m/s^2, g, mg", si="m/s²")),
]
TempUnit = Annotated[
    str | None,
    typer.Option("--temp-unit", help=_UNITS_HELP.format(
        what="temperatures", units="C, K, F", si="°C")),
]
TimeUnit = Annotated[
    str | None,
    typer.Option("--time-unit", help=_UNITS_HELP.format(
        what="time t", units="s, ms, us, ns, min, h", si="s")),
]
SamplingRate = Annotated[
    float | None,
    typer.Option("--sampling-rate", help="Sampling rate in Hz for files without a 't' "
                                         "column (t = sample index / rate)."),
]
DropInvalid = Annotated[
    bool,
    typer.Option("--drop-invalid", help="Skip rows with empty, NaN, inf or non-physical cells "
                                        "(the count is reported) instead of stopping."),
]
Topic = Annotated[
    str | None,
    typer.Option("--topic", help="ROS bags: the sensor_msgs/msg/Imu topic(s) to read, "
                                 "comma-separated (default: every Imu topic)."),
]
TempTopic = Annotated[
    str | None,
    typer.Option("--temp-topic", help="ROS bags: the sensor_msgs/msg/Temperature topic joined "
                                      "to the Imu samples (default: the only one, if any)."),
]
StaticOnly = Annotated[
    bool,
    typer.Option("--static-only", help="Use only the samples where the device was at rest "
                                       "(the motion check's static intervals; moving samples "
                                       "and a window either side are left out)."),
]


def longest_static(batch, motion, min_samples: int):
    """Each device's longest run of static samples, as a batch (a DataError naming the
    device when that run is shorter than ``min_samples``)."""
    import numpy as np

    from diffgyro.data import Batch
    from diffgyro.errors import DataError

    recs = []
    for i, rec in enumerate(batch.recordings()):
        st = np.asarray(motion.static[i])[:rec.n]
        edges = np.flatnonzero(np.diff(np.concatenate([[0], st.astype(np.int8), [0]])))
        starts, stops = edges[::2], edges[1::2]
        if not len(starts) or (stops - starts).max() < min_samples:
            raise DataError(f"no static interval of at least {min_samples} samples for "
                            "--static-only", device=batch.devices[i],
                            file=batch.sources[i] if i < len(batch.sources) else None,
                            hint="record the device at rest")
        k = int(np.argmax(stops - starts))
        recs.append(rec.slice(int(starts[k]), int(stops[k])))
    return Batch.from_recordings(recs)


def motion_notes(records: list[dict]) -> list[str]:
    """One line per device that is not ok: its name and why (the text output's notes)."""
    return [f"{r['device']}: {r['status_detail']}" for r in records if r.get("status") != "ok"]


def streamed_dir(path: Path) -> bool:
    """A folder of Parquet files (streamed); a rosbag2 folder is a log, read whole."""
    from diffgyro.logs import is_rosbag_dir

    return path.is_dir() and not is_rosbag_dir(path)


def units_from_cli(gyro_unit: str | None = None, acc_unit: str | None = None,
                   temp_unit: str | None = None, time_unit: str | None = None) -> dict[str, str]:
    """The ``units=`` mapping of :func:`diffgyro.io.load` from the unit options."""
    given = {"gyro": gyro_unit, "accel": acc_unit, "temp": temp_unit, "t": time_unit}
    return {sig: unit for sig, unit in given.items() if unit is not None}


def load_from_cli(
    paths: list[Path],
    columns: str | None = None,
    gyro_unit: str | None = None,
    acc_unit: str | None = None,
    temp_unit: str | None = None,
    time_unit: str | None = None,
    sampling_rate: float | None = None,
    drop_invalid: bool = False,
    *,
    min_samples: int = 2,
    batch: bool = True,
    topic: str | None = None,
    temp_topic: str | None = None,
    report=None,
):
    """Load data files from command-line options; report dropped rows, warnings and the
    units read from headers on stderr (and in ``report``, a :class:`LoadReport`, if given).

    Returns a :class:`~diffgyro.data.Batch` (or a list of recordings with
    ``batch=False``). Raises :class:`~diffgyro.errors.DataError` on bad input.
    """
    from diffgyro.data import Batch
    from diffgyro.io import LoadReport, load, parse_columns

    report = LoadReport() if report is None else report
    recordings = load(paths, parse_columns(columns),
                      units_from_cli(gyro_unit, acc_unit, temp_unit, time_unit),
                      drop_invalid=drop_invalid, sampling_rate=sampling_rate,
                      min_samples=min_samples, report=report, topic=topic,
                      temp_topic=temp_topic)
    for line in report.lines():
        print(f"diffgyro: {line}", file=sys.stderr)
    return Batch.from_recordings(recordings) if batch else recordings


def units_json(report) -> list[dict]:
    """The ``"units"`` field of ``--json`` output: the load's unit lines (read from
    headers, or warned), each ``{"file", "signal", "kind", "text"}``."""
    from dataclasses import asdict

    return [asdict(u) for u in report.units]
