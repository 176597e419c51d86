"""``diffgyro compensate``: apply a calibration file to recordings."""

from __future__ import annotations

import dataclasses
import sys
import warnings
from pathlib import Path
from typing import Annotated

import typer

from diffgyro.errors import DataError

from . import app
from ._load import load_from_cli
from ._options import (
    AccUnit,
    Columns,
    DropInvalid,
    GyroUnit,
    SamplingRate,
    TempTopic,
    TempUnit,
    TimeUnit,
    Topic,
)


@app.command("compensate")
def compensate_command(
    data: Annotated[Path, typer.Argument(help="Recordings to correct (standard schema).")],
    cal: Annotated[Path, typer.Option("--cal", help="Calibration file from 'diffgyro fit --out'.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="File to write (CSV, Parquet or NPZ).")],
    columns: Columns = None, gyro_unit: GyroUnit = None, acc_unit: AccUnit = None,
    temp_unit: TempUnit = None, time_unit: TimeUnit = None, sampling_rate: SamplingRate = None,
    drop_invalid: DropInvalid = False, topic: Topic = None, temp_topic: TempTopic = None,
    as_json: Annotated[bool, typer.Option("--json", help="Print what was written as JSON: the "
                                          "file, and per device its samples, how many were "
                                          "clamped to the calibrated range, and the residual "
                                          "(corrected − reference rate, or − 0 without one) "
                                          "against the recording's noise floor.")] = False,
) -> None:
    """Write DATA with gyro rates corrected by CAL (rad/s). Temperatures outside the
    calibrated range are clamped to it, with a warning.

    An accelerometer calibration ('fit --channel accel') corrects the accelerometer's
    columns instead (m/s², numpy only: diffgyro.apply.compensate_accel): to the reading
    at the calibration's centre temperature where it was fitted in one orientation, to
    the calibrated specific force where in several (docs/imu.md)."""

    from diffgyro import calibration, io

    calib = calibration.load(cal)
    batch = load_from_cli([data], columns, gyro_unit, acc_unit, temp_unit, time_unit,
                          sampling_rate, drop_invalid, topic=topic, temp_topic=temp_topic,
                          channel=calib.channel)
    if calib.channel == "accel":
        _accel(calib, cal, batch, data, out, as_json)
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            corrected, clamped = calibration.compensate(calib, batch, engine="numpy")
        except DataError as err:  # the calibration's problem: name its file
            if err.file is not None:
                raise
            raise type(err)(err.problem, file=str(cal), device=err.device, column=err.column,
                            row=err.row, hint=err.hint) from None
    _warn_clamped(clamped)
    _refuse_overwrite(data, out)
    io.save(corrected, out)
    if as_json:
        from diffgyro._jsonio import dumps
        from diffgyro.carry import residuals

        counts = [int(v) for v in corrected.mask.sum(axis=1)]
        carried = residuals(corrected, batch)
        typer.echo(dumps({"out": str(out), "model": calib.model, "devices": [
            {"device": d, "n_samples": n, "clamped": int(clamped.get(d, 0)),
             **{k: v for k, v in r.items() if k != "device"}}
            for d, n, r in zip(corrected.devices, counts, carried, strict=True)]}))
    else:
        n_clamped = sum(int(v) for v in clamped.values())
        typer.echo(f"wrote {out}: {len(corrected.devices)} device(s), "
                   f"{int(corrected.mask.sum())} samples corrected by {calib.model} (rad/s)"
                   + (f", {n_clamped} clamped to the calibrated temperature range"
                      if n_clamped else ""))


def _accel(calib, cal: Path, batch, data: Path, out: Path, as_json: bool) -> None:
    """``compensate`` with an accelerometer calibration: every device's accelerometer
    corrected with :func:`diffgyro.apply.compensate_accel`, the rest written as read."""
    import numpy as np

    from diffgyro import apply, io

    if batch.accel is None:
        raise DataError("an accelerometer calibration corrects ax, ay, az, which the data "
                        "lack", file=str(data), hint="load a file or log with the "
                        "accelerometer's readings")
    doc = calib.to_json()
    acc = np.array(batch.accel, dtype=float)
    clamped: dict[str, int] = {}
    for i, name in enumerate(batch.devices):
        dev = calib.device(name)
        if dev.status != "ok":
            why = dev.status_detail if dev.status_detail not in ("", dev.status) else dev.status
            raise DataError(f"calibration of device {name!r} is not ok ({why}); refusing to "
                            "apply it", file=str(cal), device=name)
        n = int(batch.n_valid[i])
        temp = None if batch.temp is None else np.asarray(batch.temp[i, :n], float)
        if temp is None and "temp" in calib.error_model.requires():
            raise DataError("the calibration's model needs temperature, which the data lack",
                            file=str(data), device=name, column="temp")
        if temp is not None and dev.temp_range is not None:
            outside = int(((temp < dev.temp_range[0]) | (temp > dev.temp_range[1])).sum())
            if outside:
                clamped[name] = outside
        ext = None if batch.temp_ext is None else np.asarray(batch.temp_ext[i, :n], float)
        aux = {k: np.asarray(v[i, :n], float) for k, v in (batch.aux or {}).items()}
        try:
            acc[i, :n] = apply.compensate_accel(doc, name, np.asarray(batch.t[i, :n], float),
                                                acc[i, :n], temp, ext, aux=aux or None)
        except ValueError as err:
            raise DataError(str(err), file=str(cal), device=name) from None
    _warn_clamped(clamped)
    _refuse_overwrite(data, out)
    corrected = dataclasses.replace(batch, accel=acc)
    io.save(corrected, out)
    counts = [int(v) for v in np.asarray(batch.mask).sum(axis=1)]
    if as_json:
        from diffgyro._jsonio import dumps

        typer.echo(dumps({"out": str(out), "model": calib.model, "channel": "accel",
                          "devices": [{"device": d, "n_samples": n, "clamped": clamped.get(d, 0)}
                                      for d, n in zip(batch.devices, counts, strict=True)]}))
        return
    what = ("specific force, offset and scale removed" if apply.reads_input(calib.model) else
            "offset's thermal change removed, as read at the centre temperature")
    n_clamped = sum(clamped.values())
    typer.echo(f"wrote {out}: {len(batch.devices)} device(s), {sum(counts)} accelerometer "
               f"samples corrected by {calib.model} (m/s², {what})"
               + (f", {n_clamped} clamped to the calibrated temperature range"
                  if n_clamped else ""))


def _warn_clamped(clamped: dict[str, int]) -> None:
    """One warning line per device whose temperature was clamped to its calibrated range."""
    for dev, n in clamped.items():
        print(f"diffgyro: warning: device {dev}: {n} samples outside the calibrated temperature "
              f"range were clamped to it", file=sys.stderr)


def _refuse_overwrite(data: Path, out: Path) -> None:
    """A DataError where ``out`` is the input file itself (nothing the user gave is altered)."""
    if Path(out).resolve() == Path(data).resolve():
        raise DataError("refusing to overwrite the input file", file=str(out),
                        hint="choose another --out")
