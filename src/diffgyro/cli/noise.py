"""``diffgyro noise``: the stochastic model of every device and gyro axis, with intervals.

Per device and axis: the structure chosen from the catalogue (white noise,
quantization, up to two first-order Gauss–Markov processes, random walk, rate
ramp) by the wavelet-variance criterion, each parameter with its 95 % interval
(:mod:`diffgyro.stochastic`). ``--json`` follows the contract of docs/noise.md
(SI units); the text output adds the display units (°/√h, °/h, °/h/√h).
"""

from __future__ import annotations

import html
import math
import sys
from pathlib import Path
from typing import Annotated

import typer

from . import _progress, app
from ._load import load_from_cli
from ._options import (
    AccUnit,
    Columns,
    DataFiles,
    DropInvalid,
    FigureReport,
    GyroUnit,
    SamplingRate,
    TempTopic,
    TempUnit,
    TimeUnit,
    Topic,
)

AXES = ("x", "y", "z")
_NAMES = {"arw": "ARW", "q": "quantization Q", "sigma": "GM σ (bias instability)",
          "tau": "GM correlation time", "rrw": "RRW", "r": "rate ramp"}


@app.command("noise")
def noise_command(
    data: DataFiles,
    json_out: Annotated[bool, typer.Option("--json", help="Print the models as JSON (SI units).")] = False,
    report: FigureReport = None,
    max_gm: Annotated[int, typer.Option("--max-gauss-markov", min=0, max=2,
                                        help="Most Gauss–Markov processes per model.")] = 2,
    penalty: Annotated[float | None, typer.Option(
        "--penalty", min=0.0, help="Criterion's factor on the parameters the data determine "
                                   "(2: WVIC; default: the documented one).", show_default=False)] = None,
    slow_part: Annotated[bool, typer.Option(
        "--slow-part", help="Choose the slow components (a second Gauss–Markov process, a random "
                            "walk, a ramp) again by the exact likelihood of the record's block means, "
                            "close calls by a parametric bootstrap: better on long records with "
                            "several of them; the identification takes several times as long.")] = False,
    columns: Columns = None,
    gyro_unit: GyroUnit = None,
    acc_unit: AccUnit = None,
    temp_unit: TempUnit = None,
    time_unit: TimeUnit = None,
    sampling_rate: SamplingRate = None,
    drop_invalid: DropInvalid = False,
    topic: Topic = None,
    temp_topic: TempTopic = None,
) -> None:
    """Identify the gyro noise model per device and axis (static recordings; rates in rad/s).

    The structure is chosen from white noise, quantization, up to two
    first-order Gauss–Markov processes, a random walk and a rate ramp by a
    criterion that charges each parameter (WVIC); every parameter comes with
    its 95 % interval; the rejected structures are listed with their
    criterion values. Record the device static: motion is not noise.
    """
    from diffgyro._jsonio import dumps

    with _progress.steps(f"loading {len(data)} file(s)") as step:
        batch = load_from_cli(data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                              sampling_rate, drop_invalid, min_samples=2,
                              topic=topic, temp_topic=temp_topic)
        _warn_uneven(batch)
        doc, models = identify_batch(batch, max_gm=max_gm, penalty=penalty, progress=step,
                                     slow_part=slow_part)
        if report is not None:
            step(f"writing the report to {report}")
            _write_report(doc, models, report)
    if json_out:
        typer.echo(dumps(doc))
    else:
        _print_text(doc, report)


def identify_batch(batch, max_gm: int = 2, penalty: float | None = None, progress=None,
                   slow_part: bool = False):
    """(``noise --json`` object, {device index: (NoiseModels, row)}) of a batch's gyro
    (``progress``: told each stage)."""
    from diffgyro.stochastic import identify_ahead, identify_devices

    # the identification's program loads on a thread while the motion check runs
    loaded = identify_ahead(batch.n_valid, max_gm)
    if progress is not None:
        progress(f"checking that the {batch.n_devices} device(s) are at rest")
    motion = moved_reasons(batch)
    loaded()
    entries, models = identify_devices(batch.gyro, batch.n_valid, batch.t, batch.devices,
                                       motion=motion, max_gm=max_gm, penalty=penalty,
                                       progress=progress, slow_part=slow_part)
    from diffgyro.stochastic import INTERVAL_LEVEL

    return {"interval_level": INTERVAL_LEVEL, "devices": entries}, models


def moved_reasons(batch) -> list[str | None]:
    """Per device, None when the motion check (:func:`diffgyro.motion.motion_check`) found
    it at rest, else why not (its status becomes ``in_motion`` or ``rest_unverified``, its
    axes null)."""
    from diffgyro.motion import motion_check

    motion = motion_check(batch)
    return [None if motion.at_rest(i) else motion.status_detail(
        i, "a noise model of this recording would measure the motion, not the sensor: "
           "record at rest") for i in range(batch.n_devices)]


def _warn_uneven(batch) -> None:
    """A warning per device whose sampling is uneven: the wavelet variance assumes even steps."""

    import numpy as np

    for i, dev in enumerate(batch.devices):
        gaps = np.diff(np.asarray(batch.t[i, :int(batch.n_valid[i])]))
        if gaps.size and np.median(gaps) > 0 and np.max(gaps) > 1.5 * np.median(gaps):
            print(f"diffgyro: warning: device {dev}: uneven sampling (largest gap {np.max(gaps):.4g} s,"
                  f" median {np.median(gaps):.4g} s); the noise model assumes evenly spaced samples",
                  file=sys.stderr)


def _fmt(x) -> str:
    return "—" if x is None or not math.isfinite(x) else f"{x:.4g}"


def display_line(name: str, p: dict) -> str:
    """One parameter in display units and SI (the other spelling of the SI unit beside it),
    with its interval; a parameter the record does not determine says so and why."""
    from diffgyro.stochastic import DISPLAY

    unit, same, k, dunit = DISPLAY[name]
    lo, hi = p["ci"]
    sc = lambda v: None if v is None else v * k  # noqa: E731
    text = (f"{_NAMES[name]}: {_fmt(sc(p['value']))} {dunit} "
            f"[{_fmt(sc(lo))}, {_fmt(sc(hi))}]")
    if dunit != unit:
        text += f"  ({_fmt(p['value'])} {p.get('unit', unit)}"
        text += f" = {same})" if same else ")"
    if p.get("status") == "not_identified":
        text += f"  NOT IDENTIFIED: {p.get('why', '')}"
    return text


def _print_text(doc: dict, report: Path | None) -> None:

    from diffgyro.stochastic import label

    for dev in doc["devices"]:
        if dev["status"] != "ok":
            typer.echo(f"{dev['device']}: {dev['status']}: {dev['status_detail']}")
            continue
        for ax, a in dev["axes"].items():
            typer.echo(f"{dev['device']} {ax}: {label(tuple(a['structure']))}")
            for c in a["components"]:
                for name, p in c["params"].items():
                    typer.echo(f"    {display_line(name, p)}")
            alts = [f"{r['structure']} (+{_fmt(r['delta'])})" for r in a["rejected"][:3]
                    if r.get("resolvable", True)]
            typer.echo(f"    next best: {'; '.join(alts)}")
            for note in (a.get("resolution") or {}).get("notes", []):
                typer.echo(f"    resolution: {note}")
    level = doc.get("interval_level", 0.95)
    typer.echo(f"intervals: {level * 100:g} %; criterion differences in parentheses (lower is better)")
    if report is not None:
        typer.echo(f"report: {report / 'index.html'}")


def plot_noise(res, j: int, title: str | None = None):
    """Allan deviation of one device's three axes: the empirical curve with 95 % intervals,
    each identified component and their sum."""
    import matplotlib.pyplot as plt
    import numpy as np

    from diffgyro.stochastic import label

    names = ("white", "quantization", "Gauss–Markov 1", "Gauss–Markov 2", "random walk", "rate ramp")
    fig, axs = plt.subplots(1, 3, figsize=(15, 4.5), sharey=True)
    for a, ax in enumerate(axs):
        tau = res.tau[j, a]
        ok = res.valid[j, a]
        avar = 2.0 * res.wv[j, a]
        half = 2.0 * 1.96 * res.wv_sd[j, a]
        lo = np.sqrt(np.maximum(avar - half, avar * 1e-3))
        ax.errorbar(tau[ok], np.sqrt(avar[ok]), yerr=[np.sqrt(avar[ok]) - lo[ok],
                    np.sqrt(avar[ok] + half[ok]) - np.sqrt(avar[ok])], fmt="o", ms=3, color="k",
                    label="empirical (95 %)")
        fine = np.geomspace(tau[0], tau[ok][-1] if ok.any() else tau[-1], 200)
        rows, total = res.model_curve((j, a), fine)
        for r, nm in zip(rows, names):
            if np.all(np.isnan(r)):
                continue
            ax.loglog(fine, np.sqrt(r), "--", lw=1, label=nm)
        ax.loglog(fine, np.sqrt(total), "-", lw=2, color="C3", label="model")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{AXES[a]}: {label(res.structure(j, a))}", fontsize=9)
        ax.set_xlabel("τ (s)")
        ax.grid(True, which="both", alpha=0.3)
        ymin = np.nanmin(np.sqrt(avar[ok])) / 10 if ok.any() else None
        if ymin:
            ax.set_ylim(bottom=ymin)
    axs[0].set_ylabel("Allan deviation (rad/s)")
    axs[0].legend(fontsize=7)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def _write_report(doc: dict, models: dict, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from diffgyro._jsonio import atomic_write_text, dumps
    from diffgyro.stochastic import label

    out.mkdir(parents=True, exist_ok=True)
    parts = []
    for i, dev in enumerate(doc["devices"]):
        name = dev["device"]
        if i not in models:
            parts.append(f"<h2>{html.escape(str(name))}</h2><p>{html.escape(dev['status'])}: "
                         f"{html.escape(dev['status_detail'])}</p>")
            continue
        res, j = models[i]
        safe = "".join(c if c.isalnum() or c in "-_." else "_" for c in str(name)) or f"device{i}"
        png = f"noise_{i:03d}_{safe}.png"
        fig = plot_noise(res, j, title=f"{name}: identified noise model")
        fig.savefig(out / png, dpi=110, bbox_inches="tight")
        plt.close(fig)
        rows = []
        for ax, a in dev["axes"].items():
            for c in a["components"]:
                for pname, p in c["params"].items():
                    rows.append(f"<tr><td>{ax}</td><td>{html.escape(c['kind'])}</td>"
                                f"<td>{html.escape(display_line(pname, p))}</td></tr>")
            alts = "; ".join(f"{r['structure']} (+{_fmt(r['delta'])})" for r in a["rejected"][:3])
            rows.append(f"<tr><td>{ax}</td><td>chosen: {html.escape(label(tuple(a['structure'])))}"
                        f"</td><td>next best: {html.escape(alts)}</td></tr>")
            rows += [f"<tr><td>{ax}</td><td>resolution</td><td>{html.escape(note)}</td></tr>"
                     for note in (a.get("resolution") or {}).get("notes", [])]
        parts.append(f"<h2>{html.escape(str(name))}</h2><table>{''.join(rows)}</table>"
                     f"<img src=\"{png}\" alt=\"noise model of {html.escape(str(name))}\">")
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>diffgyro noise</title>
<style>body{{font-family:sans-serif;max-width:75em;margin:2em auto}}
table{{border-collapse:collapse}}td{{border:1px solid #ccc;padding:.2em .6em}}
img{{max-width:100%}}</style></head><body>
<h1>Identified gyro noise models</h1>
<p>Points: overlapping Allan deviation at dyadic τ with 95 % intervals (from the identified
model). Dashed: each component; solid: their sum. Intervals of parameters are 95 %.</p>
{''.join(parts)}
</body></html>
"""
    atomic_write_text(out / "index.html", page)
    atomic_write_text(out / "noise.json", dumps(doc))
