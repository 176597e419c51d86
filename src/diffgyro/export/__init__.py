"""Calibrations out to the tools that fly and fuse: PX4, ArduPilot, Kalibr, C firmware.

One module per target format; :func:`render` picks the devices and returns the
file's text with report lines (the float32 error of autopilot parameters,
warnings). The formulas, signs, clamping and units are in docs/export.md.
"""

from __future__ import annotations

import dataclasses

from .._vocabulary import residual_note, residual_verdict
from ..calibration import Calibration
from ..errors import DataError
from . import ardupilot, c_header, px4

__all__ = ["render", "FORMATS", "select_devices", "refuse_not_ok"]

FORMATS = ("px4", "ardupilot", "kalibr", "c-header", "px4-ekf", "ardupilot-ekf")


def select_devices(cal: Calibration, device: str | None, fmt: str, max_devices: int) -> list[str]:
    """The named device, or every device of the calibration if there are few enough.

    **Arguments:**

    - ``cal``: the :class:`~diffgyro.calibration.Calibration`.
    - ``device``: the device named, or None for all.
    - ``fmt``: the format, as messages name it.
    - ``max_devices``: the most devices the format holds.
    """
    names = [d.device for d in cal.devices]
    if device is not None:
        cal.device(device)  # SpecError naming the devices it has
        return [device]
    if len(names) > max_devices:
        raise DataError(f"the calibration has {len(names)} devices; {fmt} takes "
                        f"{'one' if max_devices == 1 else f'at most {max_devices}'} per file",
                        hint=f"choose one with --device ({', '.join(names[:10])})")
    return names


def _slots(fmt: str, first: int | None, count: int, slots: range) -> int:
    first = slots.start if first is None else int(first)
    if first < slots.start or first + count - 1 > slots.stop - 1:
        raise DataError(f"{fmt} has instances {slots.start}..{slots.stop - 1}; "
                        f"{count} device(s) from --instance {first} do not fit")
    return first


def refuse_not_ok(devices: list[tuple[str, str, str]], force: bool) -> list[str]:
    """``(device, status, status_detail)`` of the devices to write: a DataError naming the
    first that is not ``ok`` and why, or with ``force`` one line per such device for the
    file's comments and the report.

    **Arguments:**

    - ``devices``: ``(device, status, status_detail)`` of each device.
    - ``force``: write them anyway, with one line each.
    """
    bad = [(name, status, detail) for name, status, detail in devices if status != "ok"]
    if bad and not force:
        name, status, detail = bad[0]
        why = detail if detail not in ("", status) else status
        raise DataError(f"refusing to export a device whose status is not ok ({why})",
                        device=name, hint="fix the recording or the model, or pass --force to "
                        "write it anyway (the file then says so)")
    return [f"WARNING: written with --force: device {name} has status {status}"
            + (f" ({detail})" if detail not in ("", status) else "") for name, status, detail in bad]


def _forced(cal: Calibration, names: list[str], force: bool) -> tuple[Calibration, list[str]]:
    """The calibration with the forced devices marked ok for the writers, and the lines
    that say so: a device whose held-out RMS stands above its noise floor
    (:func:`diffgyro.status.residual_verdict`) is written with a warning, and refused
    unless ``force`` where it stands above :data:`diffgyro.status.RESIDUAL_REFUSE`."""
    def judged(n):  # status, why not ok, and a warning for the file
        d = cal.device(n)
        if d.status != "ok":
            return d.status, d.status_detail, None
        q = d.quality or {}
        note = residual_note(n, q.get("heldout_rms"), q.get("noise_floor"))
        if residual_verdict(q.get("heldout_rms"), q.get("noise_floor"))[0] == "unexplained":
            return "unexplained_residual", note.split(": ", 1)[1], None
        return "ok", "", note

    verdicts = {n: judged(n) for n in names}
    lines = refuse_not_ok([(n, status, why) for n, (status, why, _) in verdicts.items()], force)
    warned = [f"WARNING: device {note}" for _, _, note in verdicts.values() if note]
    if not lines:
        return cal, warned
    devs = [dataclasses.replace(d, status="ok") if d.device in names else d for d in cal.devices]
    return dataclasses.replace(cal, devices=devs), lines + warned


def _with_note(text: str, lines: list[str], fmt: str) -> str:
    """``text`` with the --force and warning lines as comments: after the first line of a parameter
    file (QGroundControl reads its header line), first in a C header."""
    if not lines:
        return text
    if fmt == "c-header":
        return "".join(f"/* {ln.replace('*/', '* /')} */\n" for ln in lines) + text
    head, _, rest = text.partition("\n")
    return head + "\n" + "".join(f"# {ln}\n" for ln in lines) + rest


def render(cal: Calibration, fmt: str, device: str | None = None, instance: int | None = None,
           device_ids: list[int] | None = None, force: bool = False,
           accel: Calibration | None = None,
           accel_ids: list[int] | None = None) -> tuple[str, list[str]]:
    """Text of the ``fmt`` file for ``cal`` and report lines (not part of the file).

    ``accel``: an accelerometer calibration written beside the gyro's (px4: TC_A slots,
    ardupilot: INS_TCALn_ACC*); ``cal`` may itself be an accelerometer calibration.
    A device whose status is not ``ok`` is refused (a DataError naming it and why);
    ``force`` writes it anyway, with a comment in the file that says so.

    **Arguments:**

    - ``cal``: the :class:`~diffgyro.calibration.Calibration`.
    - ``fmt``: the format (``px4``, ``ardupilot``, ``c``, …; :data:`FORMATS`).
    - ``device``: the device to write (default: every device, where the format holds them).
    - ``instance``: the first slot or IMU instance written.
    - ``device_ids``: the sensors' device ids (default: from the calibration file).
    - ``force``: write devices whose status is not ``ok``, saying so in the file.
    - ``accel``: an accelerometer calibration written beside the gyro's.
    - ``accel_ids``: the accelerometers' device ids.
    """
    gyro, acc = _channels(cal, accel, fmt)
    if fmt in ("px4", "ardupilot", "c-header"):
        max_devices = {"px4": len(px4.SLOTS), "ardupilot": len(ardupilot.SLOTS), "c-header": 1}[fmt]
        lines = []
        if gyro is not None:
            gyro, lines = _forced(gyro, select_devices(gyro, device, fmt, max_devices), force)
        if acc is not None:
            acc, more = _forced(acc, select_devices(acc, device if gyro is None else None, fmt,
                                                    max_devices), force)
            lines += more
        text, report = _render(gyro, fmt, device, instance, device_ids, acc, accel_ids)
        return _with_note(text, lines, fmt), lines + report
    return _render(gyro, fmt, device, instance, device_ids)


def _channels(cal: Calibration, accel: Calibration | None, fmt: str):
    """(gyro calibration or None, accelerometer calibration or None), each checked."""
    gyro, acc = (cal, accel) if cal.channel == "gyro" else (None, cal)
    if accel is not None and (cal.channel != "gyro" or accel.channel != "accel"):
        raise DataError("--accel takes an accelerometer calibration beside a gyro one "
                        f"(got {cal.channel} and {accel.channel})")
    if acc is not None and fmt not in ("px4", "ardupilot"):
        raise DataError(f"an accelerometer calibration cannot be written as {fmt}",
                        hint="export it with --format px4 or ardupilot")
    return gyro, acc


def _ids(cal: Calibration, names: list[str], given: list[int] | None, what: str,
         option: str) -> tuple[list[int], list[str]]:
    """The sensors' device ids: given, else the calibration's (from the log), else 0 with a
    warning line."""
    if given is not None:
        if len(given) != len(names):
            raise DataError(f"{option} gives {len(given)} id(s) for {len(names)} device(s)")
        return list(given), []
    ids = [cal.device(n).device_id for n in names]
    if all(i is not None for i in ids):
        return ids, []
    letter = "G" if cal.channel == "gyro" else "A"
    return [0 if i is None else i for i in ids], [
        f"warning: TC_{letter}n_ID written as 0 for a device without a logged id: PX4 applies a "
        f"TC_{letter}n slot only to the sensor whose device_id equals it; pass {option} ({what})"]


def _render(cal: Calibration | None, fmt: str, device: str | None = None,
            instance: int | None = None, device_ids: list[int] | None = None,
            accel: Calibration | None = None,
            accel_ids: list[int] | None = None) -> tuple[str, list[str]]:

    if fmt == "px4":
        warn, gyro_names, first, gyro_ids, sensors = [], [], 0, [], None
        if cal is not None:
            gyro_names = select_devices(cal, device, fmt, len(px4.SLOTS))
            first = _slots(fmt, instance, len(gyro_names), px4.SLOTS)
            gyro_ids, warn = _ids(cal, gyro_names, device_ids, "sensor_gyro.device_id",
                                  "--device-id")
        if accel is not None:
            names = select_devices(accel, device if cal is None else None, fmt, len(px4.SLOTS))
            given = accel_ids if cal is not None or accel_ids is not None else device_ids
            ids, more = _ids(accel, names, given, "sensor_accel.device_id",
                             "--accel-device-id" if cal is not None else "--device-id")
            sensors = px4.Sensors(accel, names, _slots(fmt, instance, len(names), px4.SLOTS), ids)
            warn += more
        text, report = px4.write(cal, gyro_names, first, gyro_ids, accel=sensors)
        return text, warn + report
    if fmt == "ardupilot":
        names = select_devices(cal, device, fmt, len(ardupilot.SLOTS)) if cal is not None else []
        acc = None
        if accel is not None:
            acc = (accel, select_devices(accel, device if cal is None else None, fmt,
                                         len(ardupilot.SLOTS)))
            if cal is not None and len(acc[1]) != len(names):
                raise DataError(f"the gyro calibration has {len(names)} device(s), the "
                                f"accelerometer's {len(acc[1])}: ArduPilot pairs them IMU by IMU",
                                hint="export each IMU's pair with --device, or both alone")
        count = max(len(names), len(acc[1]) if acc else 0)
        return ardupilot.write(cal, names, _slots(fmt, instance, count, ardupilot.SLOTS), acc)
    if fmt == "c-header":
        names = select_devices(cal, device, fmt, 1)
        return c_header.write(cal, names[0]), []
    raise DataError(f"unknown export format {fmt!r}", hint=f"one of {', '.join(FORMATS)}")
