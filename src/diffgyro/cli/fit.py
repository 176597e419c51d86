"""``diffgyro fit``: calibrate devices with an error model; write a calibration file."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from . import _progress, app
from . import _tables as tables
from ._limits import LimitsOpt, attach, judge, load_limits, print_lines
from ._load import load_for_model, streamed_dir, units_json
from ._options import (
    AccUnit,
    Channel,
    Columns,
    DataFiles,
    DropInvalid,
    Gravity,
    GyroUnit,
    JsonOut,
    SamplingRate,
    StaticOnly,
    TempTopic,
    TempUnit,
    TimeUnit,
    Topic,
    motion_notes,
    refuse_on_accel,
)
from ._stream import ChunkDevices, DaskOpt, ResultsOpt, Resume, WorkDirOpt, stream_fit
from ._tables import NUMBER, TEXT

Model = Annotated[str, typer.Option("--model", "-m", help="Model spec, e.g. 'bias_poly(2)+gradient' "
                                                         "(see 'diffgyro effects').")]
DtempWindow = Annotated[float | None, typer.Option(
    "--dtemp-window", help="Seconds of the centred slope that gives dT/dt (default: 60 s, wider "
                           "when the temperature read-out is noisy or coarsely quantised, as "
                           "'diffgyro diagnose' chooses; streamed runs: 60 s).")]


@app.command("fit")
def fit_command(
    data: DataFiles,
    model: Model,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Calibration file to write (JSON).")] = None,
    as_json: JsonOut = False,
    dtemp_window: DtempWindow = None,
    columns: Columns = None, gyro_unit: GyroUnit = None, acc_unit: AccUnit = None,
    temp_unit: TempUnit = None, time_unit: TimeUnit = None, sampling_rate: SamplingRate = None,
    drop_invalid: DropInvalid = False, topic: Topic = None, temp_topic: TempTopic = None,
    chunk_devices: ChunkDevices = None, work_dir: WorkDirOpt = None, resume: Resume = True,
    dask: DaskOpt = None, results: ResultsOpt = None, limits: LimitsOpt = None,
    static_only: StaticOnly = False,
    channel: Channel = None,
    gravity: Gravity = None,
) -> None:
    """Fit MODEL to every device in DATA; per-device status, RMS and held-out RMS.

    --channel accel (or a spec 'accel: ...') fits the accelerometer's thermal offset
    relative to its gravity reference: one device per accelerometer, the motion check
    still the IMU's (docs/imu.md).

    --limits FILE.toml: each device passes or fails the limits, with the limits it
    broke and by how much; the batch gets its yield and the rejected units (in the
    text, --json, the calibration file).

    A directory of Parquet files, --chunk-devices or --dask streams the data in
    chunks of devices with resumable state in --work-dir (see docs/dask.md).
    """
    from diffgyro import calibration
    from diffgyro._jsonio import dumps
    from diffgyro._term_info import model_info
    from diffgyro.channel import resolve
    from diffgyro.io import LoadReport

    channel, model = resolve(model, channel)
    refuse_on_accel(channel, static_only=static_only,
                     streamed=chunk_devices is not None or dask is not None
                     or any(streamed_dir(p) for p in data), **{"--gravity": gravity is not None})
    if chunk_devices is not None or dask is not None or any(streamed_dir(p) for p in data):

        if static_only:
            raise typer.BadParameter("is not available for streamed runs (a folder of Parquet "
                                     "files, --chunk-devices, --dask); fit the files directly",
                                     param_hint="--static-only")

        stream_fit(data, model, out, as_json, dtemp_window, columns, gyro_unit, acc_unit,
                   temp_unit, time_unit, sampling_rate, drop_invalid, chunk_devices, work_dir,
                   resume, dask, results, limits=limits)
        return

    info = model_info(model)  # the spec checked, and the data read, before JAX starts
    lim = None if limits is None else load_limits(limits, _error_model(model), channel)
    report = LoadReport()
    with _progress.steps(f"loading {len(data)} file(s)") as step:
        batch = load_for_model(info, data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                               sampling_rate, drop_invalid, topic=topic, temp_topic=temp_topic,
                               report=report, channel=channel)
        from diffgyro.fit import fit

        em = _error_model(model)
        if dtemp_window is None:
            from diffgyro._temperature import suggest_dtemp_window

            dtemp_window = suggest_dtemp_window(batch)
        step(f"fitting {em.spec} on {batch.n_devices} device(s)")
        result = fit(em, batch, dtemp_window=float(dtemp_window), static_only=static_only,
                     channel=channel, **({} if gravity is None else {"gravity": gravity}))
    records = result.records()
    summary = None
    if lim is not None:
        from diffgyro.channel import fitted_batch

        records, summary = judge(lim, records, result, fitted_batch(result, batch))
    if out is not None:
        cal = calibration.from_fit(result, batch, device_ids=report.device_ids)
        calibration.save(cal if summary is None else attach(cal, records, summary), out)
    if as_json:
        print(dumps({"model": em.spec, "devices": records, "units": units_json(report)}
                    | ({} if summary is None else {"limits": summary})
                    | ({} if channel == "gyro" else {"channel": channel})))
        return

    _print_table(records, em.spec, channel, summary)
    for line in motion_notes(records):
        print(line)
    if summary is not None:
        print_lines(records, summary)
    if out is not None:
        print(f"calibration written to {out}", file=sys.stderr)


def _error_model(spec: str):
    """The spec's :class:`~diffgyro.model.ErrorModel` (JAX starts here)."""
    from diffgyro.model import ErrorModel

    return ErrorModel.from_spec(spec)


def _print_table(records: list[dict], spec: str, channel: str, summary) -> None:
    """The devices' table (``summary``: the --limits result, a column of pass/fail)."""
    from diffgyro.channel import UNITS

    static = any(r.get("static_only") for r in records)
    rows = []
    for r in records:
        mo = (r.get("motion") or {}).get("moving_fraction")
        n = str(r["n_samples"]) + (f" of {r['n_recorded']}" if r.get("static_only") else "")
        rows.append([r["device"], r["status"], _fmt(r["rms"]), _fmt(r["heldout_rms"]),
                     _fmt(r["noise_floor"]), "—" if mo is None else f"{100 * mo:.1f} %", n,
                     *((r["limits"]["result"],) if summary else ())])
    from diffgyro.channel import reads_gravity
    from diffgyro.model import ErrorModel

    what = "rates in rad/s" if channel == "gyro" else (
        f"accelerometer on its faces: absolute offset and scale, in {UNITS[channel]}"
        if reads_gravity(ErrorModel.from_spec(spec)) else
        f"accelerometer, relative to its gravity reference, in {UNITS[channel]}")
    table = tables.table(f"fit {spec}  ({what})", [
        ("device", TEXT), ("status", TEXT), ("rms", NUMBER), ("held-out rms", NUMBER),
        ("noise floor", NUMBER), ("moving", NUMBER),
        ("samples (static only)" if static else "samples", NUMBER),
        *((("limits", TEXT),) if summary else ())], rows, (con := Console()).width)
    con.print(table)


def _fmt(x) -> str:
    return "—" if x is None else f"{x:.3e}"
