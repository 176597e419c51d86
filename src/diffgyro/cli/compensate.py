"""``diffgyro compensate``: apply a calibration file to recordings."""

from __future__ import annotations

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
    calibrated range are clamped to it, with a warning."""

    from diffgyro import calibration, io

    calib = calibration.load(cal)
    batch = load_from_cli([data], columns, gyro_unit, acc_unit, temp_unit, time_unit,
                          sampling_rate, drop_invalid, topic=topic, temp_topic=temp_topic)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            corrected, clamped = calibration.compensate(calib, batch, engine="numpy")
        except DataError as err:  # the calibration's problem: name its file
            if err.file is not None:
                raise
            raise type(err)(err.problem, file=str(cal), device=err.device, column=err.column,
                            row=err.row, hint=err.hint) from None
    for dev, n in clamped.items():
        print(f"diffgyro: warning: device {dev}: {n} samples outside the calibrated temperature "
              f"range were clamped to it", file=sys.stderr)
    if Path(out).resolve() == Path(data).resolve():
        raise DataError("refusing to overwrite the input file", file=str(out),
                        hint="choose another --out")
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
