"""``--limits FILE.toml`` on ``fit`` and ``diagnose``: pass/fail per device, the batch's yield.

This module starts with ``_`` so it is not imported as a command.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer

#: Broken limits shown per device in the text output (--json lists them all).
SHOWN = 4

LimitsOpt = Annotated[
    Path | None,
    typer.Option("--limits", help="Pass/fail limits (TOML): bounds on any field of a device's "
                                  "record, e.g. heldout_rms = { max = 0.002 } (rad/s); each "
                                  "device passes or fails, the batch gets its yield "
                                  "(see docs/limits.md)."),
]


def load_limits(path: Path | None, model, channel: str = "gyro"):
    """The checked limits file (None without --limits), its bounds in the units of
    ``channel``'s records; a DataError naming file and key."""
    if path is None:
        return None
    from diffgyro.limits import check_model, load

    limits = load(path, channel)
    check_model(limits, model)
    return limits


def _temperature(result, i: int):
    """(centre, scale, range) of device ``i``'s temperature normalisation, or Nones."""
    import numpy as np

    if result.temp_range is None:
        return None, None, None
    return (float(np.asarray(result.norm.centre)[i]), float(np.asarray(result.norm.scale)[i]),
            np.asarray(result.temp_range[i], float).tolist())


def judge(limits, records: list[dict], result, batch, residuals=None) -> tuple[list[dict], dict]:
    """Records with the figures the limits ask for and their ``limits`` result, and the
    batch summary. ``result`` is the (base) FitResult; ``residuals`` (devices, n, 3) the
    fit residual when already at hand (diagnose holds it)."""
    import numpy as np

    from diffgyro.limits import add_figures, check, residual_allan, summary, unmatched

    wanted = limits.computed
    allan = [None] * len(records)
    if "allan" in wanted:
        res = residuals if residuals is not None else np.asarray(result.residuals(batch))
        allan = residual_allan(res, np.asarray(batch.t), np.asarray(batch.n_valid))
    out = []
    for i, r in enumerate(records):
        centre, scale, trange = _temperature(result, i)
        rec = add_figures(r, wanted, allan=allan[i], centre=centre, scale=scale,
                          temp_range=trange)
        rec["limits"] = check(limits, rec)
        out.append(rec)
    for path in unmatched(limits, out):
        print(f"diffgyro: warning: limits file {limits.file}: {path!r} matched no field of any "
              f"device record (every device fails it unless optional = true)", file=sys.stderr)
    return out, summary(limits, out)


def attach(cal, records: list[dict], summary: dict):
    """The calibration ``cal`` with each device's pass/fail and the batch summary."""
    by_name = {r["device"]: r["limits"] for r in records}
    for d in cal.devices:
        d.limits = by_name.get(d.device, {})
    cal.limits = summary
    return cal


def lines(records: list[dict], summary: dict) -> list[str]:
    """The text output: every failed device with the limits it broke, then the yield."""
    from diffgyro.limits import broken_text

    out = []
    for r in records:
        lim = r["limits"]
        if lim["result"] == "fail":
            shown = [broken_text(b) for b in lim["broken"][:SHOWN]]
            more = len(lim["broken"]) - len(shown)
            out.append(f"{r['device']}: fail — " + "; ".join(shown)
                       + (f"; and {more} more (see --json)" if more > 0 else ""))
    y = summary["yield"]
    rejected = ", ".join(summary["rejected"]) or "none"
    out.append(f"limits {summary['name']} ({summary['file']}): {summary['passed']} of "
               f"{summary['passed'] + summary['failed']} devices pass"
               + ("" if y is None else f" (yield {100 * y:.1f} %)") + f"; rejected: {rejected}")
    return out


def print_lines(records: list[dict], summary: dict, console=None) -> None:
    for line in lines(records, summary):
        if console is None:
            print(line)
        else:
            console.print(line, markup=False, highlight=False, soft_wrap=True)
