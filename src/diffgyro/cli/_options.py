"""The typer options shared by the commands that read recordings.

Use in a command module (``fit``, ``diagnose``, ``allan``, ``recipe`` ...)::

    from ._load import load_from_cli
    from ._options import (AccUnit, Columns, DataFiles, DropInvalid, GyroUnit,
                           SamplingRate, TempUnit, TimeUnit)

    @app.command("fit")
    def fit_command(data: DataFiles, columns: Columns = None, gyro_unit: GyroUnit = None,
                    acc_unit: AccUnit = None, temp_unit: TempUnit = None,
                    time_unit: TimeUnit = None, sampling_rate: SamplingRate = None,
                    drop_invalid: DropInvalid = False, ...):
        batch = load_from_cli(data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                              sampling_rate, drop_invalid, min_samples=model_needs)

Loading itself is :mod:`diffgyro.cli._load`.
This module starts with ``_`` so it is not imported as a command.
"""

from __future__ import annotations

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
Channel = Annotated[
    str | None,
    typer.Option("--channel", help="The sensor to calibrate: gyro (default) or accel, the "
                                   "accelerometer's thermal offset relative to its gravity "
                                   "reference (one orientation at rest; docs/imu.md). A spec "
                                   "may name it instead: 'accel: bias_poly(3)'."),
]
Gravity = Annotated[
    float | None,
    typer.Option("--gravity", help="Local gravity, m/s², of an accelerometer fit in several "
                                   "orientations (a model with scale_poly or misalignment on "
                                   "--channel accel): the scale is relative to it (default: "
                                   "standard gravity, 9.80665)."),
]
JsonOut = Annotated[bool, typer.Option("--json", help="Print one JSON object on stdout.")]
FigureReport = Annotated[
    Path | None,
    typer.Option("--report", help="Write PNG figures and an HTML page here."),
]


def motion_notes(records: list[dict]) -> list[str]:
    """One line per device that is not ok (its name and why), and per device whose held-out
    RMS stands above its noise floor (:func:`diffgyro.status.residual_note`): the text
    output's notes."""
    from diffgyro.status import residual_note

    lines = [f"{r['device']}: {r['status_detail']}" for r in records if r.get("status") != "ok"]
    notes = (residual_note(r["device"], r.get("heldout_rms"), r.get("noise_floor"))
             for r in records if r.get("status") == "ok")
    return lines + [n for n in notes if n]


def refuse_on_accel(channel: str, static_only: bool = False, streamed: bool = False,
                    **others) -> None:
    """One line (exit 2) for the options the accelerometer channel does not take
    (``others``: option name -> whether it was given, e.g. ``{"--limits": True}``)."""
    if channel == "gyro":
        if others.get("--gravity"):
            raise typer.BadParameter("is for the accelerometer channel (gravity is its input "
                                     "in several orientations)", param_hint="--gravity")
        return
    for name, given in others.items():
        if name == "--gravity":
            continue
        if given:
            raise typer.BadParameter("is not available on the accelerometer channel yet "
                                     "(it reads the gyro's columns)", param_hint=name)
    if static_only:
        raise typer.BadParameter("is not available on the accelerometer channel: each stretch "
                                 "of rest may hold another orientation, so another gravity "
                                 "reference; record the soak in one orientation",
                                 param_hint="--static-only")
    if streamed:
        raise typer.BadParameter("is not available for streamed runs (a folder of Parquet "
                                 "files, --chunk-devices, --dask) yet: the pipeline reads, "
                                 "fits and merges the gyro's columns, and carries no gravity "
                                 "reference or faces from chunk to merge; fit the files "
                                 "directly (a chunk holds whole devices, so the result is "
                                 "the same)", param_hint="--channel accel")
