"""``diffgyro export``: a calibration as PX4 or ArduPilot parameters, a C header, or Kalibr's imu.yaml."""

from __future__ import annotations

import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from diffgyro.errors import DataError

from . import app
from ._load import MIN_SAMPLES, load_from_cli
from ._options import (
    AccUnit,
    Columns,
    DropInvalid,
    GyroUnit,
    SamplingRate,
    TempUnit,
    TimeUnit,
)


@app.command("export")
def export_command(
    source: Annotated[Path, typer.Argument(
        help="Calibration file from 'diffgyro fit --out' (px4, ardupilot, c-header); for kalibr "
             "an 'allan --json' output or a static recording.", show_default=False)],
    fmt: Annotated[str, typer.Option("--format", "-f", help="px4, ardupilot, kalibr, c-header; "
                                     "px4-ekf, ardupilot-ekf (from 'noise --json').",
                                     show_default=False)],
    device: Annotated[str | None, typer.Option("--device", help="The device to export "
                                               "(default: every device, where the format holds several).")] = None,
    instance: Annotated[int | None, typer.Option("--instance", help="First sensor slot: TC_G<N> "
                                                 "(px4, 0-3, default 0), INS_TCAL<N> (ardupilot, 1-3, default 1).")] = None,
    out: Annotated[str | None, typer.Option("--out", "-o", help="File to write; '-' or none: stdout.")] = None,
    device_id: Annotated[str | None, typer.Option("--device-id", help="px4: the sensors' device_id "
                                                  "(TC_G<N>_ID), comma-separated for several devices "
                                                  "(default: the ids the log gave, kept in the "
                                                  "calibration file).")] = None,
    accel: Annotated[Path | None, typer.Option("--accel", help="px4, ardupilot: an accelerometer "
                                               "calibration ('fit --channel accel --out') written "
                                               "beside the gyro's: TC_A<N>_* or "
                                               "INS_TCAL<N>_ACC*.")] = None,
    accel_device_id: Annotated[str | None, typer.Option(
        "--accel-device-id", help="px4: the accelerometers' device_id (TC_A<N>_ID), "
                                  "comma-separated (default: from the calibration file).")] = None,
    rate: Annotated[float | None, typer.Option("--rate", help="kalibr: update_rate in Hz "
                                               "(default: the recording's).")] = None,
    topic: Annotated[str, typer.Option("--topic", help="kalibr: rostopic.")] = "/imu0",
    accel_noise_density: Annotated[float | None, typer.Option(
        "--accel-noise-density", help="kalibr: accelerometer noise density, m/s²/√Hz.")] = None,
    accel_random_walk: Annotated[float | None, typer.Option(
        "--accel-random-walk", help="kalibr: accelerometer random walk, m/s³/√Hz.")] = None,
    ekf_dt: Annotated[float | None, typer.Option(
        "--ekf-dt", min=1e-6, max=10.0, help="px4-ekf, ardupilot-ekf: the filter's step in s (default: "
                         "EKF2_PREDICT_US 0.010, EKF3 0.012).", show_default=False)] = None,
    columns: Columns = None, gyro_unit: GyroUnit = None, acc_unit: AccUnit = None,
    temp_unit: TempUnit = None, time_unit: TimeUnit = None, sampling_rate: SamplingRate = None,
    drop_invalid: DropInvalid = False,
    force: Annotated[bool, typer.Option("--force", help="Write a device whose status is not ok "
                                        "(in_motion, insufficient_range, ...), or noise parameters "
                                        "the model does not identify, anyway; the file says so in "
                                        "a comment.")] = False,
) -> None:
    """Write SOURCE in an autopilot's or estimator's format (docs/export.md: formulas, units).

    A model the format cannot hold exactly (px4, ardupilot: anything but bias_poly(k ≤ 3))
    is refused, never truncated; the float32 error of autopilot parameters is reported.
    A device that is not ok (a fit's status, or Allan read-outs of a recording that
    moved), or a noise parameter the model does not identify (px4-ekf, ardupilot-ekf,
    kalibr from 'noise --json'), is refused with the reason, unless --force.
    """
    from diffgyro.export import FORMATS

    fmt = fmt.lower()
    _check_format(fmt, FORMATS, accel)
    if fmt in ("px4-ekf", "ardupilot-ekf"):
        from diffgyro.export import ekf_noise

        name, n, k, report = ekf_noise.device_densities(_read_json(source, "noise models"), device,
                                                        force=force)
        forced = [ln for ln in report if ln.startswith("WARNING: written")]
        if fmt == "px4-ekf":
            dt = ekf_noise.PX4_DT if ekf_dt is None else ekf_dt
            text = ekf_noise.write_px4(ekf_noise.px4_parameters(n, k, dt), name, dt, forced)
        else:
            dt = ekf_noise.ARDUPILOT_DT if ekf_dt is None else ekf_dt
            text = ekf_noise.write_ardupilot(ekf_noise.ardupilot_parameters(n, k, dt), name, dt,
                                             forced)
        for line in report:
            print(f"diffgyro: {line}", file=sys.stderr)
        _emit(text, out, source, f"{fmt} noise parameters of device {name}")
        return
    if fmt == "kalibr":
        from diffgyro.export import kalibr

        noise, report = _kalibr_noise(source, device, rate, (columns, gyro_unit, acc_unit, temp_unit,
                                      time_unit, sampling_rate, drop_invalid), force)
        if accel_noise_density is not None:
            noise = replace(noise, accel_noise_density=accel_noise_density)
        if accel_random_walk is not None:
            noise = replace(noise, accel_random_walk=accel_random_walk)
        text = kalibr.write(noise, topic, [ln for ln in report if ln.startswith("WARNING: written")])
        what = f"kalibr IMU noise of device {noise.device}"
    else:
        text, report, what = _calibration(source, accel, fmt, device, instance, device_id,
                                          accel_device_id, force)
    for line in report:
        print(f"diffgyro: {line}", file=sys.stderr)
    _emit(text, out, source, what)


def _check_format(fmt: str, formats, accel: Path | None) -> None:
    """One line (exit 2) for an unknown format, or --accel where the format has no
    accelerometer table."""
    if fmt not in formats:
        raise DataError(f"unknown export format {fmt!r}", hint=f"one of {', '.join(formats)}")
    if accel is not None and fmt not in ("px4", "ardupilot"):
        raise DataError(f"--accel is for px4 and ardupilot (their accelerometer tables), not {fmt}")


def _calibration(source: Path, accel: Path | None, fmt: str, device, instance, device_id,
                 accel_device_id, force: bool) -> tuple[str, list[str], str]:
    """The file of a calibration (and an accelerometer's beside it), its report lines, and
    what it holds."""
    from diffgyro import calibration
    from diffgyro.export import render

    cal = calibration.load(source)
    acc = None if accel is None else calibration.load(accel)
    ids = None if device_id is None else _ids(device_id)
    acc_ids = None if accel_device_id is None else _ids(accel_device_id)
    text, report = render(cal, fmt, device=device, instance=instance, device_ids=ids,
                          force=force, accel=acc, accel_ids=acc_ids)
    what = f"{fmt} calibration of {_devices_of(cal, fmt, device)}" + (
        "" if acc is None else f" and the accelerometers of {_devices_of(acc, fmt, None)}")
    return text, report, what


def _devices_of(cal, fmt: str, device: str | None) -> str:
    """'device NAME' or 'N devices (A, B)': what an autopilot file holds."""
    from diffgyro.export import ardupilot, px4, select_devices

    names = select_devices(cal, device, fmt, {"px4": len(px4.SLOTS),
                                              "ardupilot": len(ardupilot.SLOTS)}.get(fmt, 1))
    return f"device {names[0]}" if len(names) == 1 else f"{len(names)} devices ({', '.join(names)})"


def _ids(text: str) -> list[int]:

    try:
        return [int(x, 0) for x in text.split(",")]
    except ValueError:
        raise DataError(f"--device-id {text!r} must be integers (comma-separated)") from None


def _read_json(source: Path, what: str):

    try:
        return json.loads(source.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise DataError(f"cannot read {what}: {err}".splitlines()[0], file=str(source)) from None


def _is_noise_doc(doc) -> bool:
    """A ``noise --json`` object (axes holding components), not an ``allan --json`` one."""
    try:
        return any(isinstance(d.get("axes"), dict) and any(
            isinstance(a, dict) and "components" in a for a in d["axes"].values())
            for d in doc["devices"])
    except (AttributeError, KeyError, TypeError):
        return False


def _is_json_object(path: Path) -> bool:
    """Whether the file holds a JSON object (by its content: a name need not end in .json)."""
    try:
        with open(path, "rb") as f:
            head = f.read(4096).lstrip(b"\xef\xbb\xbf \t\r\n")
    except OSError:
        return path.suffix.lower() == ".json"  # let the reader name the problem
    return head.startswith(b"{")


def _kalibr_noise(source: Path, device, rate, load_opts, force: bool = False):
    """Noise densities from an 'allan --json' file, or from Allan curves of a recording."""
    from diffgyro.export import kalibr

    if _is_json_object(source):
        try:
            doc = json.loads(source.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, ValueError) as err:
            raise DataError(f"cannot read Allan read-outs: {err}".splitlines()[0],
                            file=str(source)) from None
        if _is_noise_doc(doc):
            from diffgyro.export import ekf_noise

            name, n, k, report = ekf_noise.device_densities(doc, device, force=force)
            dt = next((d.get("sample_interval") for d in doc["devices"] if str(d.get("device")) == name),
                      None)
            if rate is None and not (isinstance(dt, (int, float)) and dt > 0):
                raise DataError("the noise models give no sampling interval", file=str(source),
                                hint="pass --rate HZ")
            return kalibr.ImuNoise(name, n, k, float(rate) if rate is not None else 1.0 / dt), report
        try:
            return kalibr.from_allan(doc, device, rate, force=force)
        except DataError as err:
            raise DataError(err.problem, file=str(source), device=err.device,
                            hint=err.hint) from None
    from diffgyro.motion import motion_check


    batch = load_from_cli([source], *load_opts, min_samples=MIN_SAMPLES)
    gyro_doc = kalibr.allan_of(batch, "gyro", motion_check(batch))
    acc_doc = kalibr.allan_of(batch, "accel") if batch.accel is not None else None
    return kalibr.from_allan(gyro_doc, device, rate, acc_doc, force=force)


def _emit(text: str, out: str | None, source: Path, what: str) -> None:
    """``text`` to stdout, or to ``out`` with one line saying what was written."""
    from diffgyro._jsonio import atomic_write_text

    if out is None or out == "-":
        sys.stdout.write(text)
        return
    if Path(out).resolve() == Path(source).resolve():
        raise DataError("refusing to overwrite the input file", file=out, hint="choose another --out")
    atomic_write_text(out, text)
    typer.echo(f"wrote {out}: {what}, {len(text.splitlines())} lines")
