"""``diffgyro recipe NAME DATA``: run a published calibration method as published.

Every recipe reads the standard columns (mapped with ``--columns`` and the
unit options) and works in SI units; results are printed in SI (rates in
rad/s) except ``six-position``, whose ``--json`` object is in the input units.
Options that a recipe does not take are an error.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from diffgyro.errors import DataError

from . import app
from ._load import load_from_cli
from ._options import (
    AccUnit,
    Columns,
    DropInvalid,
    GyroUnit,
    JsonOut,
    SamplingRate,
    StaticOnly,
    TempTopic,
    TempUnit,
    TimeUnit,
    Topic,
)


def _opt(name: str, help_text: str, **kw):
    return typer.Option(name, help=help_text, show_default=False, **kw)


Sections = Annotated[Path | None, _opt(
    "--sections", "six-position: JSON of sample ranges (x_p, x_a, y_p, y_a, z_p, z_a, x_rot, "
    "y_rot, z_rot), default DATA's stem + '_list.json'; cube-bias: JSON of the static sets "
    "(z_up_1 ... y_down_4).")]


@app.command("recipe")
def recipe_command(
    name: Annotated[str, typer.Argument(help="Recipe: binned-thermal, static-kalman, fog-one-run, "
                                             "attitude-reference, cube-bias, six-position, "
                                             "multi-position.", show_default=False)],
    data: Annotated[Path, typer.Argument(help="Data file (CSV, TSV, Parquet, NPZ) or log (PX4 "
                                              ".ulg, ROS .bag / .mcap / rosbag2 folder, "
                                              "ArduPilot .bin / .log).",
                                         show_default=False)],
    as_json: JsonOut = False,
    out: Annotated[Path | None, _opt("--out", "Also write the JSON result to this file.")] = None,
    device: Annotated[str | None, _opt("--device", "Run on this device only (files with "
                                                   "several devices).")] = None,
    sections: Sections = None,
    rotation_angle: Annotated[float | None, _opt(
        "--rotation-angle", "six-position: angle of each turn in degrees (default -360, "
                            "clockwise).")] = None,
    gravity: Annotated[float | None, _opt("--gravity", "Local gravity in m/s² (default 9.81).")] = None,
    bin_width: Annotated[float | None, _opt("--bin-width", "binned-thermal: bin width in °C "
                                                           "(default 0.1).")] = None,
    edge: Annotated[str | None, _opt("--edge", "binned-thermal: bin temperature at its low, "
                                               "centre or high edge (default low).")] = None,
    per_bin: Annotated[int | None, _opt("--per-bin", "binned-thermal: samples kept per bin.")] = None,
    r_min: Annotated[float | None, _opt("--r-min", "binned-thermal: |r| needed to accept a line "
                                                   "(default 0.999).")] = None,
    init: Annotated[int | None, _opt("--init", "static-kalman: samples of the initial rest "
                                               "(default 1000).")] = None,
    window: Annotated[int | None, _opt("--window", "static-kalman: samples per window (default "
                                                   "100); multi-position: variance window "
                                                   "(default 101).")] = None,
    margin: Annotated[float | None, _opt("--margin", "static-kalman: threshold margin M "
                                                     "(default 1.5).")] = None,
    q: Annotated[float | None, _opt("--q", "static-kalman: Kalman Q in (--q-unit)² "
                                           "(default 1e-4).")] = None,
    q_unit: Annotated[str | None, _opt("--q-unit", "static-kalman: unit of Q's square root, "
                                                   "deg/s or rad/s (default deg/s).")] = None,
    axis: Annotated[str | None, _opt("--axis", "fog-one-run: the table axis x, y or z "
                                               "(default z).")] = None,
    k0: Annotated[float | None, _opt("--k0", "fog-one-run: room-temperature scale factor "
                                             "(default 1).")] = None,
    n: Annotated[int | None, _opt("--n", "fog-one-run: dT over 2^n samples (default 6).")] = None,
    m: Annotated[int | None, _opt("--m", "fog-one-run: samples removed each side of a sign "
                                         "change (default 3).")] = None,
    signs_from: Annotated[str | None, _opt("--signs-from", "fog-one-run: sign changes of the "
                                                           "'rate' (default) or the 'gyro'.")] = None,
    accel_band: Annotated[float | None, _opt("--accel-band", "attitude-reference: |a| gate as a "
                                                             "fraction of g (default 0.02).")] = None,
    ratio: Annotated[float | None, _opt("--ratio", "attitude-reference: fusion weight of the "
                                                   "accel/mag attitude (default 0.02).")] = None,
    reference: Annotated[str | None, _opt("--reference", "attitude-reference: 'am' or "
                                                         "'fused' reference rate.")] = None,
    interval: Annotated[int | None, _opt("--interval", "attitude-reference: samples between "
                                                       "the two quaternions (default 1).")] = None,
    all_faces: Annotated[bool | None, _opt("--all-faces/--published-faces",
                                           "cube-bias: average every perpendicular face pair "
                                           "instead of the patent's assignment.")] = None,
    init_seconds: Annotated[float | None, _opt("--init-seconds", "multi-position: initial rest "
                                                                 "in s (default 50).")] = None,
    pose_means: Annotated[bool | None, _opt("--pose-means/--pose-samples",
                                            "multi-position: fit whole-pose means (diffgyro) or "
                                            "the first 100 samples (IMU-TK).")] = None,
    columns: Columns = None, gyro_unit: GyroUnit = None, acc_unit: AccUnit = None,
    temp_unit: TempUnit = None, time_unit: TimeUnit = None, sampling_rate: SamplingRate = None,
    drop_invalid: DropInvalid = False, topic: Topic = None, temp_topic: TempTopic = None,
    static_only: StaticOnly = False,
) -> None:
    """Run recipe NAME on DATA exactly as published; print its numbers (--json: one object).

    Recipes that assume the device at rest (binned-thermal) check each recording for
    motion: the result carries the motion check and, where the device moved, status
    in_motion and a warning; --static-only runs them on the static samples only."""
    # Over 80 lines only through its signature: typer reads each recipe option from a
    # parameter of this function; the work is in the helpers below.
    from diffgyro._jsonio import atomic_write_text, dumps
    from diffgyro.io import resolve_units
    from diffgyro.recipes import get

    recipe = get(name)
    given = {
        "rotation_angle": rotation_angle, "gravity": gravity, "bin_width": bin_width,
        "edge": edge, "per_bin": per_bin, "r_min": r_min, "init": init, "window": window,
        "margin": margin, "q": q, "q_unit": q_unit, "axis": axis, "k0": k0, "n": n, "m": m,
        "signs_from": signs_from, "accel_band": accel_band, "ratio": ratio,
        "reference": reference, "interval": interval, "all_faces": all_faces,
        "init_seconds": init_seconds, "pose_means": pose_means,
    }
    given = _recipe_options(recipe, name, data, given, sections, sampling_rate)
    recordings = load_from_cli([data], columns, gyro_unit, acc_unit, temp_unit, time_unit,
                               sampling_rate, drop_invalid, batch=False,
                               topic=topic, temp_topic=temp_topic)
    if device is not None:
        recordings = [r for r in recordings if r.device == device]
        if not recordings:

            raise DataError(f"device {device!r} is not in the data", file=str(data))
    conv = resolve_units({"gyro": gyro_unit, "accel": acc_unit})
    recordings, rest = _rest_check(name, recordings, static_only)
    results, failed = _run_devices(recipe, name, recordings, given, conv, str(data))
    payload = _payload(results, failed, rest)
    results = [(d, r) for d, r in results if r is not None]
    if out is not None:
        atomic_write_text(out, dumps(payload, indent=2) + "\n")
    if as_json:
        typer.echo(dumps(payload))
        return
    for err in failed.values():
        typer.echo(f"diffgyro: warning: {err}", err=True)
    for dev, extra in (rest or {}).items():
        if extra["status"] != "ok":
            typer.echo(f"diffgyro: warning: device {dev}: {extra['status_detail']}", err=True)
    _print_human(name, recipe, results, gyro_unit or "rad/s", acc_unit or "m/s²")


#: Recipes whose method assumes the device at rest throughout.
REST_RECIPES = ("binned-thermal",)


def _rest_check(name: str, recordings, static_only: bool):
    """For a recipe that assumes rest: the recordings (their static samples only with
    ``static_only``) and per device the motion check, status and samples kept."""
    import numpy as np

    from diffgyro.data import Batch, Recording
    from diffgyro.motion import motion_check, rest_kept

    if name not in REST_RECIPES:
        if static_only:
            raise DataError(f"option --static-only does not apply to recipe {name}",
                            hint="it applies to the recipes that assume rest: "
                                 + ", ".join(REST_RECIPES))
        return recordings, None
    motion = motion_check(Batch.from_recordings(recordings))
    out, rest = [], {}
    for i, rec in enumerate(recordings):
        extra = {"motion": motion.record(i), "status": "ok", "status_detail": "ok"}
        if static_only:
            keep = np.asarray(motion.static[i])[:rec.n]
            rec = Recording(**{s: (None if getattr(rec, s) is None else np.asarray(getattr(rec, s))[keep])
                               for s in rec.signals}, device=rec.device, source=rec.source,
                            aux={k: np.asarray(v)[keep] for k, v in rec.aux.items()})
            extra.update(static_only=True, n_samples=int(keep.sum()), n_recorded=int(keep.size))
        if static_only:
            kept = rest_kept(motion)
            extra.update(motion=kept.record(i), status=kept.status(i), status_detail=kept.status_detail(
                i, f"recipe {name} assumes the device at rest"))
        elif not motion.at_rest(i):
            extra.update(status=motion.status(i), status_detail=motion.status_detail(
                i, f"recipe {name} assumes the device at rest: record at rest, or run it on "
                   "the static intervals only with --static-only"))
        out.append(rec)
        rest[rec.device] = extra
    return out, rest


def _recipe_options(recipe, name: str, data: Path, given: dict, sections: Path | None,
                    sampling_rate: float | None) -> dict:
    """The options given on the command line that recipe ``name`` takes; an option it
    does not take is an error naming its options. Its sections file defaults to
    ``DATA_list.json`` beside the data."""

    given = {k: v for k, v in given.items() if v is not None}
    accepted = set(recipe.options())
    for key in given:
        if key not in accepted:
            raise DataError(f"option --{key.replace('_', '-')} does not apply to recipe {name}",
                            hint="its options: " + ", ".join(
                                "--" + o.replace("_", "-") for o in recipe.options()))
    if "sections" in accepted:
        if sections is None:
            sections = data.with_name(data.stem + "_list.json")
            if not sections.exists():
                raise DataError(f"recipe {name} needs the sample ranges of its sections",
                                file=str(data), hint=f"give --sections FILE (looked for {sections})")
        given["sections"] = sections
    elif sections is not None:
        raise DataError(f"option --sections does not apply to recipe {name}")
    if "sampling_rate" in accepted and sampling_rate is not None:
        given["sampling_rate"] = sampling_rate
    return given


def _run_devices(recipe, name: str, recordings, given: dict, conv: dict, file: str):
    """(device, result or None) per recording and the errors of the failed ones; with one
    device its error is raised, and so is the first when every device failed."""

    results, failed = [], {}
    for rec in recordings:
        try:
            res = recipe.run(rec, **given)
        except DataError as err:  # name the file; with several devices, one failure is a record
            err = _naming_file(err, file, rec.device)
            if len(recordings) == 1:
                raise err from None
            failed[rec.device] = err
            results.append((rec.device, None))
            continue
        if name == "six-position":  # the contract: input units
            res = res.scaled(1.0 / conv.get("gyro", (1.0, 0.0))[0],
                             1.0 / conv.get("accel", (1.0, 0.0))[0])
        results.append((rec.device, res))
    if len(failed) == len(results):
        raise next(iter(failed.values()))
    return results, failed


def _payload(results, failed, rest=None) -> dict:
    """The JSON result: the recipe's own object for one device, else a record per device;
    ``rest``: per device the motion check of a recipe that assumes rest."""
    from diffgyro._jsonio import to_json_safe

    rest = rest or {}
    if len(results) == 1:
        return to_json_safe(results[0][1].to_dict() | rest.get(results[0][0], {}))
    return {"devices": [
        {"device": d, "status": "ok", **to_json_safe(r.to_dict()), **rest.get(d, {})}
        if r is not None else
        {"device": d, "status": "failed", "status_detail": f"failed: {failed[d].problem}"}
        for d, r in results]}


def _naming_file(err, file: str, device: str):
    """``err`` with the file and device filled in where it names neither."""

    if err.file is not None:
        return err
    return DataError(err.problem, file=file, device=err.device or device, column=err.column,
                     row=err.row, hint=err.hint)


#: Units of the numbers each recipe prints (the recording is in SI: rad/s, m/s², °C, s;
#: six-position answers in DATA's own units). A field not listed has none.
UNITS = {
    "binned-thermal": {"offset": "rad/s", "slope": "rad/s per °C", "bin_width": "°C",
                       "per_bin": "samples"},
    "static-kalman": {"thresholds": "m/s² (ax, ay, az), rad/s (gx, gy, gz)",
                      "initial_offset": "rad/s", "window": "samples", "q": "(rad/s)²",
                      "n_static_windows": "windows", "duration": "s", "yaw_end": "rad",
                      "heading_error": "rad"},
    "fog-one-run": {"k0": "output per rad/s", "n_avg": "samples", "m": "samples",
                    "rms": "output units", "n_kept": "samples", "n_removed": "samples"},
    "attitude-reference": {"scale": "gyro / reference", "bias": "rad/s",
                           "joint_scale": "gyro / reference", "joint_bias": "rad/s",
                           "n_gated": "samples", "n_pairs": "samples"},
    "cube-bias": {"gyro_bias": "rad/s", "accel_bias": "m/s²", "face_gyro": "rad/s",
                  "face_accel": "m/s²"},
    "six-position": {"gyro_bias": "{gyro}", "g_sens": "{gyro} per {acc}",
                     "accel_bias": "{acc}"},
    "multi-position": {"gyro_bias": "rad/s", "accel_bias": "m/s²", "pose_norm_error": "m/s²",
                       "pose_norm_error_first": "m/s²", "pose_rms": "m/s²",
                       "motion_residual": "rad", "gravity": "m/s²",
                       "gyro_scale_counts": "raw units per rad/s"},
}


def _accepted_reasons(d: dict) -> str:
    """binned-thermal's verdict per axis with its reason (|r| against r_min)."""
    parts = []
    r_min = f"{d['r_min']!r}"  # as given: 0.9999999, not rounded to 1
    digits = max(6, len(r_min.lstrip("0.").replace(".", "")) + 1)
    for axis, ok, r in zip("xyz", d["accepted"], d["r"], strict=True):
        if r is None:
            parts.append(f"{axis} no (r undefined: the bin means or temperatures do not vary)")
        else:
            parts.append(f"{axis} {'yes' if ok else 'no'} (|r| {abs(r):.{digits}g} "
                         f"{'>' if ok else '≤'} r_min {r_min})")
    return "; ".join(parts) + ("" if all(d["accepted"]) else
                               ": a rejected axis' bias does not follow a straight line in "
                               "temperature closely enough (--r-min to relax)")


def _print_human(name, recipe, results, gyro_unit: str = "rad/s", acc_unit: str = "m/s²") -> None:
    """Short, readable summary: scalars and small arrays of each result, with units."""
    import numpy as np

    from diffgyro._jsonio import dumps, to_json_safe

    units = {k: u.format(gyro=gyro_unit, acc=acc_unit) for k, u in UNITS.get(name, {}).items()}
    con = Console(width=120)
    con.print(f"[bold]{name}[/bold] — {recipe.source}")
    for dev, res in results:
        con.print("device ", end="")
        con.print(dev, style="bold", markup=False)
        d = to_json_safe(res.to_dict())
        for key, val in d.items():
            arr = np.asarray(val, dtype=object) if isinstance(val, list) else None
            if arr is not None and arr.size > 12:
                continue
            if isinstance(val, dict) and len(dumps(val)) > 200:
                continue
            text = f"  {key}: {_fmt(val)}" + (f" {units[key]}" if key in units else "")
            if name == "binned-thermal" and key == "accepted":
                text = f"  accepted: {_accepted_reasons(d)}"
            con.print(text, markup=False, highlight=False, soft_wrap=True)


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{k}: {_fmt(x)}" for k, x in v.items()) + "}"
    return str(v)
