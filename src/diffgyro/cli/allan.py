"""``diffgyro allan``: overlapping Allan deviation of every device and axis, with read-outs."""

from __future__ import annotations

import html
import math
import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from . import _progress, app
from . import _tables as tables
from ._load import MIN_SAMPLES, load_from_cli, longest_static, units_json
from ._options import (
    AccUnit,
    Columns,
    DataFiles,
    DropInvalid,
    FigureReport,
    GyroUnit,
    SamplingRate,
    StaticOnly,
    TempTopic,
    TempUnit,
    TimeUnit,
    Topic,
)
from ._tables import NUMBER, TEXT

AXES = ("gx", "gy", "gz")


@app.command("allan")
def allan_command(
    data: DataFiles,
    json_out: Annotated[bool, typer.Option("--json", help="Print the curves and read-outs as JSON.")] = False,
    report: FigureReport = None,
    out: Annotated[Path | None, typer.Option("--out", "-o", help="Also write the --json object to "
                                             "this file (what 'export --format kalibr' reads).")] = None,
    per_decade: Annotated[int, typer.Option("--per-decade", min=1, max=100,
                                            help="Cluster sizes per decade of τ.")] = 10,
    taus: Annotated[str | None, typer.Option(
        "--taus", help="Compute exactly these τ in seconds, comma-separated (e.g. '1,10,100'); "
                       "each must be a whole number of sample intervals. Replaces --per-decade.",
        show_default=False)] = None,
    columns: Columns = None,
    gyro_unit: GyroUnit = None,
    acc_unit: AccUnit = None,
    temp_unit: TempUnit = None,
    time_unit: TimeUnit = None,
    sampling_rate: SamplingRate = None,
    drop_invalid: DropInvalid = False,
    topic: Topic = None,
    temp_topic: TempTopic = None,
    static_only: StaticOnly = False,
) -> None:
    """Overlapping Allan deviation per device and gyro axis (rates in rad/s).

    Read-outs: ARW (rad/s/√Hz) at τ = 1 s on the −1/2 line, bias instability
    (rad/s) = flat minimum / 0.664, RRW (rad/s²/√Hz) at τ = 3 s on the +1/2
    line; a read-out the curve does not show is null. Record the device
    static: moving data measure the motion, not the noise. With --taus the
    curve holds just the τ asked for (those longer than a quarter of a
    device's recording are left out, with a warning).

    Every device is checked for motion: a device that moved gets status
    in_motion (its read-outs are the motion's, not the sensor's noise).
    --static-only computes the curve over each device's longest static
    interval (never over static pieces glued across the motion).
    """
    from diffgyro._jsonio import dumps
    from diffgyro.io import LoadReport
    from diffgyro.motion import motion_check

    wanted = _parse_taus(taus)
    loaded = LoadReport()
    with _progress.steps(f"loading {len(data)} file(s)") as step:
        batch = load_from_cli(data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                              sampling_rate, drop_invalid, min_samples=MIN_SAMPLES,
                              topic=topic, temp_topic=temp_topic, report=loaded)
        step(f"checking {batch.n_devices} device(s) for motion")
        motion = motion_check(batch)
        recorded = [int(n) for n in batch.n_valid]
        if static_only:
            batch = longest_static(batch, motion, MIN_SAMPLES)
        _warn_uneven(batch)
        step("Allan deviation and its read-outs")
        parts = _curves(batch, per_decade, wanted)
        doc = _merged_json(parts, batch)
        doc["units"] = units_json(loaded)
        _add_motion(doc, motion, batch, recorded, static_only)
        if wanted is not None:
            _warn_missing_taus(doc, wanted)
        if report is not None:
            step(f"writing the report to {report}")
            _write_report(parts, batch, doc, report)
    if out is not None:
        from diffgyro._jsonio import atomic_write_text

        atomic_write_text(out, dumps(doc))
    if json_out:
        typer.echo(dumps(doc))
    else:
        _print_table(doc, report, wanted, batch)
        if out is not None:
            typer.echo(f"wrote {out}: Allan curves and read-outs of {batch.n_devices} device(s)")


def _add_motion(doc: dict, motion, batch, recorded, static_only: bool) -> None:
    """Each device's motion check, and a status that says whether its read-outs are a
    sensor's noise (``in_motion`` when the curve's samples include motion,
    ``rest_unverified`` when nothing shows they do not)."""
    from diffgyro.motion import rest_kept

    if static_only:
        motion = rest_kept(motion)
    for i, dev in enumerate(doc["devices"]):
        dev["status"] = motion.status(i)
        dev["status_detail"] = motion.status_detail(
            i, "these read-outs may measure the motion, not the sensor's noise: record at "
               "rest" + ("" if static_only else ", or use --static-only"))
        dev["motion"] = motion.record(i)
        if static_only:
            n = int(batch.n_valid[i])
            t = batch.t[i]
            dev.update(static_only=True, n_samples=n, n_recorded=recorded[i],
                       segment=[float(t[0]), float(t[n - 1])])


def _parse_taus(text: str | None) -> list[float] | None:
    """The --taus list as positive finite floats (exit 2 with a clear line otherwise)."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise typer.BadParameter(f"{text!r} is not a comma-separated list of seconds",
                                 param_hint="--taus") from None
    if not values or not all(math.isfinite(v) and v > 0 for v in values):
        raise typer.BadParameter(f"{text!r}: give one or more positive τ in seconds",
                                 param_hint="--taus")
    return values


def _curves(batch, per_decade: int, taus: list[float] | None):
    """[(device indices, AllanResult)]: one part for all devices, or one per cluster-size set."""
    import numpy as np

    from diffgyro.allan import allan_at_taus, allan_batch

    if taus is None:
        return [(np.arange(batch.n_devices), allan_batch(batch, per_decade=per_decade))]
    return allan_at_taus(batch, taus)


def _merged_json(parts, batch) -> dict:
    """The ``allan --json`` object of every device, in the batch's order."""
    from diffgyro.allan import to_json

    by_index = {}
    for idx, result in parts:
        for i, entry in zip(idx, to_json(result, [batch.devices[i] for i in idx], AXES)["devices"]):
            for ax in entry["axes"].values():  # τ = m·dt to the digits dt holds: 0.02, not 0.0199…96
                ax["tau"] = [float(f"{t:.10g}") for t in ax["tau"]]
            by_index[int(i)] = entry
    return {"devices": [by_index[i] for i in range(batch.n_devices)]}


def _warn_missing_taus(doc: dict, taus: list[float]) -> None:
    for dev in doc["devices"]:
        got = dev["axes"]["gx"]["tau"]
        missing = [t for t in taus if not any(math.isclose(t, g, rel_tol=1e-6) for g in got)]
        if missing:
            print(f"diffgyro: warning: device {dev['device']}: τ {', '.join(f'{t:g}' for t in missing)} s "
                  f"longer than a quarter of the recording, left out", file=sys.stderr)


def _warn_uneven(batch) -> None:
    import numpy as np

    for i, dev in enumerate(batch.devices):
        n = int(batch.n_valid[i])
        gaps = np.diff(np.asarray(batch.t[i, :n]))
        med = float(np.median(gaps))
        worst = float(np.max(gaps))
        if med > 0 and worst > 1.5 * med:
            print(f"diffgyro: warning: device {dev}: uneven sampling (largest gap {worst:.4g} s, "
                  f"median {med:.4g} s); the Allan deviation assumes evenly spaced samples",
                  file=sys.stderr)


def _fmt(x) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.4g}"


def _print_table(doc: dict, report: Path | None, wanted: list[float] | None = None,
                 batch=None) -> None:
    """The read-outs (and with --taus σ at each τ asked for); each dash is numbered and
    its reason printed under the table."""

    notes: list[str] = []

    def dash(reason: str) -> str:
        if reason not in notes:
            notes.append(reason)
        return f"— [{notes.index(reason) + 1}]"

    def cell(ax: dict, key: str) -> str:
        x = ax[key]
        if x is not None and math.isfinite(x):
            return f"{x:.4g}"
        return dash((ax.get("missing") or {}).get(key) or "not defined by this curve")

    rows = []
    for dev in doc["devices"]:
        for name, ax in dev["axes"].items():
            span = f"{ax['tau'][0]:.3g} – {ax['tau'][-1]:.3g}" if ax["tau"] else "—"
            rows.append([escape(str(dev["device"])), name, cell(ax, "arw"),
                         cell(ax, "bias_instability"), cell(ax, "rrw"), span])
    table = tables.table("Allan deviation read-outs", [
        ("device", TEXT), ("axis", TEXT), ("ARW (rad/s/√Hz)", NUMBER),
        ("bias instability (rad/s)", NUMBER), ("RRW (rad/s²/√Hz)", NUMBER),
        ("τ range (s)", NUMBER)], rows, (con := tables.console(120)).width)
    con.print(table)
    if wanted:
        con.print(_tau_table(doc, wanted, batch, dash, con.width))
    for i, reason in enumerate(notes, 1):
        con.print(f"[{i}] {reason}", markup=False, highlight=False, soft_wrap=True)
    for dev in doc["devices"]:
        if dev.get("status", "ok") != "ok":
            print(f"{dev['device']}: {dev['status_detail']}")
        elif dev.get("static_only"):
            print(f"{dev['device']}: static only: {dev['n_samples']} of {dev['n_recorded']} samples "
                  f"(the longest static interval, t = {dev['segment'][0]:.6g} to "
                  f"{dev['segment'][1]:.6g} s)")
    if report is not None:
        con.print(f"report: {report / 'index.html'}")


def _tau_table(doc: dict, wanted: list[float], batch, dash, width: int):
    """σ(τ) at exactly the τ asked for, per device and axis."""

    rows = []
    for i, dev in enumerate(doc["devices"]):
        span = None
        if batch is not None:
            n = int(batch.n_valid[i])
            span = float(batch.t[i, n - 1] - batch.t[i, 0])
        for name, ax in dev["axes"].items():
            row = []
            for t in wanted:
                hit = [a for g, a in zip(ax["tau"], ax["adev"], strict=True)
                       if math.isclose(t, g, rel_tol=1e-6)]
                if hit:
                    row.append(f"{hit[0]:.4g}")
                else:
                    row.append(dash("τ longer than a quarter of the recording"
                                    + (f" ({span:.4g} s)" if span is not None else "")
                                    + ": too few clusters to average"))
            rows.append([escape(str(dev["device"])), name, *row])
    return tables.table("Allan deviation σ(τ) at the τ asked for (rad/s)",
                        [("device", TEXT), ("axis", TEXT),
                         *((f"τ = {t:g} s", NUMBER) for t in wanted)], rows, width)


def _write_report(parts, batch, doc: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffgyro._jsonio import atomic_write_text, dumps
    from diffgyro.allan import plot_allan

    out.mkdir(parents=True, exist_ok=True)
    rows, figs = [], []
    where = {int(i): (result, j) for idx, result in parts for j, i in enumerate(idx)}
    for i, dev in enumerate(batch.devices):
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in str(dev)) or f"device{i}"
        name = f"allan_{i:03d}_{safe}.png"
        result, j = where[i]
        fig = plot_allan(result, device=j, axes=AXES, title=f"{dev}: overlapping Allan deviation")
        fig.savefig(out / name, dpi=110, bbox_inches="tight")
        plt.close(fig)
        figs.append((dev, name))
        for axname, ax in doc["devices"][i]["axes"].items():
            rows.append(f"<tr><td>{html.escape(str(dev))}</td><td>{axname}</td>"
                        f"<td>{_fmt(ax['arw'])}</td><td>{_fmt(ax['bias_instability'])}</td>"
                        f"<td>{_fmt(ax['rrw'])}</td></tr>")
    notes = "\n".join(f"<p class=\"status\"><b>{html.escape(str(d['device']))}</b>: "
                      f"{html.escape(d['status_detail'])}</p>" for d in doc["devices"]
                      if d.get("status", "ok") != "ok")
    imgs = "\n".join(f"<h2>{html.escape(str(d))}</h2><img src=\"{n}\" alt=\"Allan deviation of "
                     f"{html.escape(str(d))}\">" for d, n in figs)
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>diffgyro allan</title>
<style>body{{font-family:sans-serif;max-width:60em;margin:2em auto}}
table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:.2em .6em;text-align:right}}
img{{max-width:100%}}</style></head><body>
<h1>Overlapping Allan deviation</h1>
{notes}
<p>Rates in rad/s. ARW: the −1/2 line read at τ = 1 s (rad/s/√Hz). Bias instability: the flat
minimum divided by 0.664 (rad/s). RRW: the +1/2 line read at τ = 3 s (rad/s²/√Hz). Shaded bands:
one-sigma chi-square intervals. A dash means the curve shows no such region.</p>
<table><tr><th>device</th><th>axis</th><th>ARW (rad/s/√Hz)</th><th>bias instability (rad/s)</th>
<th>RRW (rad/s²/√Hz)</th></tr>
{chr(10).join(rows)}
</table>
{imgs}
</body></html>
"""
    atomic_write_text(out / "index.html", page)
    atomic_write_text(out / "allan.json", dumps(doc))
