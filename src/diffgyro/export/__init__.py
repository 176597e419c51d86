"""Calibrations out to the tools that fly and fuse: PX4, ArduPilot, Kalibr, C firmware.

One module per target format; :func:`render` picks the devices and returns the
file's text with report lines (the float32 error of autopilot parameters,
warnings). The formulas, signs, clamping and units are in docs/export.md.
"""

from __future__ import annotations

import dataclasses

from ..calibration import Calibration
from ..errors import DataError
from ..status import residual_note, residual_verdict
from . import ardupilot, c_header, px4

__all__ = ["render", "FORMATS", "select_devices", "refuse_not_ok"]

FORMATS = ("px4", "ardupilot", "kalibr", "c-header", "px4-ekf", "ardupilot-ekf")


def select_devices(cal: Calibration, device: str | None, fmt: str, max_devices: int) -> list[str]:
    """The named device, or every device of the calibration if there are few enough."""
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
    file's comments and the report."""
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
           device_ids: list[int] | None = None, force: bool = False) -> tuple[str, list[str]]:
    """Text of the ``fmt`` file for ``cal`` and report lines (not part of the file).

    A device whose status is not ``ok`` is refused (a DataError naming it and why);
    ``force`` writes it anyway, with a comment in the file that says so."""
    if fmt in ("px4", "ardupilot", "c-header"):

        max_devices = {"px4": len(px4.SLOTS), "ardupilot": len(ardupilot.SLOTS), "c-header": 1}[fmt]
        names = select_devices(cal, device, fmt, max_devices)
        cal, lines = _forced(cal, names, force)
        text, report = _render(cal, fmt, device, instance, device_ids)
        return _with_note(text, lines, fmt), lines + report
    return _render(cal, fmt, device, instance, device_ids)


def _render(cal: Calibration, fmt: str, device: str | None = None, instance: int | None = None,
            device_ids: list[int] | None = None) -> tuple[str, list[str]]:

    if fmt == "px4":
        names = select_devices(cal, device, fmt, len(px4.SLOTS))
        first = _slots(fmt, instance, len(names), px4.SLOTS)
        warn = []
        if device_ids is None:
            device_ids = [0] * len(names)
            warn.append("warning: TC_Gn_ID written as 0: PX4 applies a TC_Gn slot only to the sensor "
                        "whose device_id equals it; pass --device-id (sensor_gyro.device_id)")
        elif len(device_ids) != len(names):
            raise DataError(f"--device-id gives {len(device_ids)} id(s) for {len(names)} device(s)")
        text, report = px4.write(cal, names, first, device_ids)
        return text, warn + report
    if fmt == "ardupilot":
        names = select_devices(cal, device, fmt, len(ardupilot.SLOTS))
        return ardupilot.write(cal, names, _slots(fmt, instance, len(names), ardupilot.SLOTS))
    if fmt == "c-header":
        names = select_devices(cal, device, fmt, 1)
        return c_header.write(cal, names[0]), []
    raise DataError(f"unknown export format {fmt!r}", hint=f"one of {', '.join(FORMATS)}")
