"""``diffgyro diagnose``: where the model fails and which physical effect is missing."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.markup import escape

from diffgyro.errors import DataError

from . import _progress, app
from . import _tables as tables
from ._limits import LimitsOpt, attach, judge, load_limits, print_lines
from ._load import MIN_SAMPLES, load_for_model, longest_static, streamed_dir
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
    refuse_on_accel,
)
from ._stream import ChunkDevices, DaskOpt, ResultsOpt, Resume, WorkDirOpt, stream_diagnose
from ._tables import NUMBER, TEXT

Model = Annotated[str, typer.Option("--model", "-m", help="Model spec to diagnose, e.g. 'bias_poly(2)' "
                                                         "(see 'diffgyro effects').")]


def _fmt(x) -> str:
    return "—" if x is None or not math.isfinite(float(x)) else f"{float(x):.3g}"


def _add(d) -> str:
    """The term to add (and the one the next round is expected to add after it)."""
    if d.best is None:
        return ""
    text = d.best.term or d.best.effect
    return text + (f", then {d.next.term}" if d.next is not None else "")


#: The residual's noise process in the table (the explanation gives σ and τ).
NOISE_SHORT = {"white": "white", "gauss_markov": "GM", "random_walk": "RW",
               "gauss_markov+random_walk": "GM+RW"}


#: Columns left out, in this order, where the table would not fit the terminal: each
#: device's explanation names the close alternatives and the residual's noise process,
#: and --json holds the in-sample RMS.
NARROW = ("close alternatives", "noise", "rms")


def print_diagnosis(diag, console, judged: list[dict] | None = None) -> None:
    """A rich table of the devices, then each device's explanation (``judged``: the records
    with their --limits result, a column of pass/fail)."""

    rows = []
    for i, d in enumerate(diag.devices):
        colour = {"adequate": "green", "not_judged": "yellow"}.get(d.verdict, "red")
        rows.append([escape(d.device), f"[{colour}]{d.verdict}[/{colour}]", _fmt(d.rms),
                     _fmt(d.heldout_rms), _fmt(d.noise_floor), escape(_add(d)),
                     _fmt(d.best.heldout_rms) if d.best else "",
                     escape(", ".join(c.term or c.effect for c in d.alternatives)),
                     NOISE_SHORT.get(d.noise_process or "", ""),
                     *((judged[i]["limits"]["result"],) if judged else ())])
    channel = getattr(diag.fit, "channel", "gyro")
    what = "rates in rad/s" if channel == "gyro" else "accelerometer, in m/s²"
    columns, rows, dropped = tables.fit_columns([
        ("device", TEXT), ("verdict", TEXT), ("rms", NUMBER), ("held-out", NUMBER),
        ("floor", NUMBER), ("add", TEXT), ("held-out with it", NUMBER),
        ("close alternatives", TEXT), ("noise", TEXT),
        *((("limits", TEXT),) if judged else ())], rows, console.width, optional=NARROW)
    console.print(tables.table(f"diagnosis of {diag.spec} ({what})", columns, rows,
                               console.width, justify={"limits": "right"}))
    if dropped:
        console.print(f"(at {console.width} columns: {', '.join(dropped)} left out; see below "
                      "and --json)", markup=False, highlight=False, soft_wrap=True)
    for d in diag.devices:
        console.print(d.explanation, markup=False, highlight=False, soft_wrap=True)
    for line in skipped_lines(diag):
        console.print(line, markup=False, highlight=False, soft_wrap=True)


#: Reasons shown per candidate not tried (each device's own is in --json's ``skipped``).
SKIPPED_SHOWN = 4


def skipped_lines(diag) -> list[str]:
    """Each candidate not tried with each device's reason (what its data show against
    what the term needs), the devices with the same reason on one line; at most
    :data:`SKIPPED_SHOWN` reasons per candidate, then how many devices more."""
    seen: dict[str, dict[str, list[str]]] = {}
    for d in diag.devices:
        for term, why in d.skipped.items():
            seen.setdefault(term, {}).setdefault(why, []).append(d.device)
    n = len(diag.devices)
    out = []
    for term, reasons in seen.items():
        for why, devs in list(reasons.items())[:SKIPPED_SHOWN]:
            out.append(f"not tried: {term} ({why}; "
                       f"{'every device' if len(devs) == n else ', '.join(devs)})")
        more = sum(len(devs) for devs in list(reasons.values())[SKIPPED_SHOWN:])
        if more:
            out.append(f"not tried: {term} on {more} more device(s), each for its own reason "
                       f"(see --json: skipped)")
    return out


def print_ladder(ladder, console) -> None:

    rows = [[escape(added), escape(spec), _fmt(h), _fmt(f), f"{k}/{len(ladder.devices)}"]
            for added, spec, h, f, k in ladder.table_rows()]
    table = tables.table("model ladder (median over devices)", [
        ("added", TEXT), ("model", TEXT), ("held-out RMS", NUMBER), ("noise floor", NUMBER),
        ("adequate", NUMBER)], rows, console.width)
    console.print(table)


def wide_console():
    """A rich console as wide as the terminal (or ``COLUMNS``); 140 columns when stdout
    is not a terminal and ``COLUMNS`` is not set (pipes, logs, tests)."""
    return tables.console(140)


def _write_calibration(diag, batch, path: Path, err, judged=None, device_ids=None) -> None:
    """The calibration of ``diag``'s model from the fit it holds (no second fit), atomically;
    ``judged``: (records, summary) of --limits, kept in the file; ``device_ids``: the
    sensors' ids a log gave."""
    from diffgyro import calibration


    cal = calibration.from_fit(diag.fit, batch, device_ids=device_ids)
    calibration.save(cal if judged is None else attach(cal, *judged), path)
    err.print(f"calibration of {diag.spec} written to {path}", markup=False, highlight=False)


@app.command("diagnose")
def diagnose_command(
    data: DataFiles,
    model: Model,
    as_json: JsonOut = False,
    report: Annotated[Path | None, typer.Option(
        "--report", help="Write a self-contained HTML report (one page per device + summary) here.")] = None,
    auto: Annotated[bool, typer.Option(
        "--auto", help="Add the best significant candidate until every device is adequate; "
                       "print the ladder.")] = False,
    synthesis: Annotated[bool, typer.Option(
        "--synthesis/--no-synthesis",
        help="When no built-in term closes the gap, propose terms built from the recording's "
             "signals (term(...), see docs/effects.md).")] = True,
    noise: Annotated[bool, typer.Option(
        "--noise", help="Identify the residual's noise model (white, Gauss–Markov σ and τ, "
                        "random walk, with intervals) for every device; by default only where "
                        "the residual is not white and no term explains it.")] = False,
    candidates: Annotated[str | None, typer.Option(
        "--candidates", help="Comma-separated effects to try (default: every registered effect "
                             "the data supports).")] = None,
    max_steps: Annotated[int, typer.Option("--max-steps", help="Most terms --auto adds.")] = 6,
    out: Annotated[Path | None, typer.Option(
        "--out", "-o", help="Write the calibration (JSON, as 'diffgyro fit --out') of the final "
                            "model of --auto, or of MODEL, from the fit diagnose already holds.")] = None,
    dtemp_window: Annotated[float | None, typer.Option(
        "--dtemp-window", help="Seconds of the centred slope that gives dT/dt (default: chosen "
                               "from the temperature read-out's noise and steps).")] = None,
    columns: Columns = None, gyro_unit: GyroUnit = None, acc_unit: AccUnit = None,
    temp_unit: TempUnit = None, time_unit: TimeUnit = None, sampling_rate: SamplingRate = None,
    drop_invalid: DropInvalid = False, topic: Topic = None, temp_topic: TempTopic = None,
    chunk_devices: ChunkDevices = None, work_dir: WorkDirOpt = None, resume: Resume = True,
    dask: DaskOpt = None, results: ResultsOpt = None, limits: LimitsOpt = None,
    static_only: StaticOnly = False,
    channel: Channel = None,
    gravity: Gravity = None,
) -> None:
    """Diagnose MODEL on every device in DATA: held-out RMS against a model-free noise floor,
    the missing effect (if any) with the evidence, close alternatives.

    --json prints {"model", "devices": [{"device", "rms", "heldout_rms", "noise_floor",
    "verdict", "candidates": [{"effect", "spec", "heldout_rms", "significant"}, ...]}]}
    with candidates sorted best first (extra keys: explanation, evidence, alternatives, ...).
    A directory of Parquet files, --chunk-devices or --dask streams the data in chunks of
    devices with resumable state in --work-dir (see docs/dask.md). --limits FILE.toml:
    each device passes or fails the limits (records gain "limits", the object a
    top-level "limits" with the yield), in the text, --json, the report and --out.
    A device that moved (no rate reference in MODEL) gets status in_motion and no
    verdict; --static-only diagnoses each device's longest static interval.
    --channel accel (or a spec 'accel: ...') diagnoses the accelerometer's thermal offset
    relative to its gravity reference (docs/imu.md).
    """
    from diffgyro.channel import resolve

    streamed = chunk_devices is not None or dask is not None or any(streamed_dir(p) for p in data)
    channel, model = resolve(model, channel)
    refuse_on_accel(channel, static_only=static_only, streamed=streamed,
                    **{"--gravity": gravity is not None})
    _refuse_combinations(limits is not None and auto, streamed and static_only,
                         streamed and not synthesis, streamed and noise)
    if streamed:

        if out is not None:

            raise DataError("--out needs every device in memory; it does not stream",
                            hint="run 'diffgyro fit --out' on the final model, or give data files "
                                 "without --chunk-devices/--dask")

        stream_diagnose(data, model, as_json, report, auto, candidates, dtemp_window, columns,
                        gyro_unit, acc_unit, temp_unit, time_unit, sampling_rate, drop_invalid,
                        chunk_devices, work_dir, resume, dask, results, limits=limits)
        return

    lim = None
    if limits is not None:
        from diffgyro.model import ErrorModel

        lim = load_limits(limits, ErrorModel.from_spec(model), channel)
    opts = ({} if dtemp_window is None else {"dtemp_window": float(dtemp_window)}) \
        | ({} if synthesis else {"synthesis": False}) | ({"noise": True} if noise else {}) \
        | ({} if channel == "gyro" else {"channel": channel}) \
        | ({} if gravity is None else {"gravity": float(gravity)})
    err = Console(stderr=True)
    with _progress.steps(f"loading {len(data)} file(s)") as step:
        spec, batch, names, partial, ids = _load_checked(model, data, candidates, columns,
                                                         gyro_unit, acc_unit, temp_unit,
                                                         time_unit, sampling_rate, drop_invalid,
                                                         topic, temp_topic, channel)
        if static_only:
            step("finding each device's longest static interval")
        batch, static = _static_only(batch) if static_only else (batch, None)
        diag, ladder = _diagnosis(spec, batch, names, auto, max_steps, opts, step)
    if partial and (names is None or "aux" in {n.split("(")[0].strip() for n in names}):
        for d in [*diag.devices, *([] if ladder is None else ladder.final.devices)]:
            d.skipped.update(partial)
    _outputs(diag, ladder, batch, lim, report, out, as_json, err, static, ids)


def _refuse_combinations(limits_with_auto: bool, streamed_static_only: bool,
                         streamed_without_synthesis: bool, streamed_noise: bool = False) -> None:
    """One line (exit 2) for options that do not go together."""
    if limits_with_auto:

        raise DataError("--limits judges the model given with --model; with --auto the model "
                        "shipped is known only at the end",
                        hint="run diagnose or fit --limits with the final model of the ladder")
    if streamed_static_only:
        raise typer.BadParameter("is not available for streamed runs (a folder of Parquet "
                                 "files, --chunk-devices, --dask); diagnose the files directly",
                                 param_hint="--static-only")
    if streamed_without_synthesis:
        raise typer.BadParameter("is not available for streamed runs; diagnose the files "
                                 "directly", param_hint="--no-synthesis")
    if streamed_noise:
        raise typer.BadParameter("is not available for streamed runs; diagnose the files "
                                 "directly", param_hint="--noise")


def _diagnosis(spec, batch, names, auto: bool, max_steps: int, opts: dict, step):
    """The diagnosis of ``spec`` (the first rung of the ladder with --auto) and the ladder
    (``step``: told each stage, :mod:`._progress`)."""
    from diffgyro.diagnose import diagnose, diagnose_auto

    if auto:
        ladder = diagnose_auto(spec, batch, names, max_steps=max_steps, progress=step, **opts)
        return ladder.first, ladder
    return diagnose(spec, batch, names, progress=step, **opts), None


def _outputs(diag, ladder, batch, lim, report: Path | None, out: Path | None, as_json: bool,
             err, static=None, device_ids=None) -> None:
    """Judge the devices against the limits file (``lim``), then the report, the calibration
    file and the printed result (``static``: what --static-only kept, per device)."""
    judged = None
    if lim is not None:

        judged = judge(lim, diag.to_json()["devices"], diag.fit, batch, diag.residuals)
    if report is not None:
        from diffgyro.report import write_report

        with _progress.steps(f"writing the report to {report}"):
            write_report(diag, batch, report, ladder=ladder, limits=judged)
    if out is not None:
        _write_calibration(ladder.final if ladder is not None else diag, batch, out, err, judged,
                           device_ids)
    _print_result(diag, ladder, as_json, report, judged, static)


def _static_only(batch):
    """Each device's longest static interval, and per device the motion of the whole
    recording and the samples kept (extra keys of its --json record)."""
    from diffgyro.motion import motion_check


    motion = motion_check(batch)
    recorded = [int(n) for n in batch.n_valid]
    batch = longest_static(batch, motion, MIN_SAMPLES)
    return batch, [{"motion": motion.record(i), "static_only": True,
                    "n_samples": int(batch.n_valid[i]), "n_recorded": recorded[i]}
                   for i in range(batch.n_devices)]


def _load_checked(model, data, candidates, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                  sampling_rate, drop_invalid, topic, temp_topic, channel="gyro"):
    """The parsed model, the loaded batch, the candidate names, the extra columns some
    devices lack (:func:`partial_columns`) and the sensors' ids a log gave; a DataError
    (exit 2) for a bad spec, an unknown candidate or a signal the model needs that the data
    lacks."""
    from diffgyro._term_info import model_info
    from diffgyro.channel import check_model
    from diffgyro.data import Batch
    from diffgyro.io import LoadReport

    info = model_info(model)  # the spec checked, and the data read, before JAX starts
    check_model(info, channel)
    report = LoadReport()
    recs = load_for_model(info, data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                          sampling_rate, drop_invalid, topic=topic, temp_topic=temp_topic,
                          batch=False, report=report, channel=channel)
    from diffgyro.model import ErrorModel

    spec = ErrorModel.from_spec(model)
    batch = Batch.from_recordings(recs)
    names = [c.strip() for c in candidates.split(",") if c.strip()] if candidates else None
    if names:
        from diffgyro.effects import parse_term, registry

        for n in names:
            if n not in registry():
                parse_term(n)  # SpecError naming the valid effects
    from diffgyro.data import aux_key

    missing = spec.requires() - set(batch.signals) - {aux_key(k) for k in batch.aux} - {"t"}
    if missing:

        raise DataError(f"model {spec.spec!r} needs {', '.join(sorted(missing))}, not in the data",
                        file=batch.sources[0] if batch.sources else None)
    return spec, batch, names, partial_columns(recs), report.device_ids


def partial_columns(recs) -> dict[str, str]:
    """The extra columns some devices lack (a batch keeps those every device has), as the
    ``aux(NAME)`` terms diagnose does not try and why: listed under ``skipped``."""
    names = sorted({k for r in recs for k in r.aux} - set.intersection(*(set(r.aux) for r in recs)))
    out = {}
    for name in names:
        have = sum(name in r.aux for r in recs)
        out[f"aux({name})"] = (f"extra column {name!r} is logged for {have} of {len(recs)} "
                               f"devices only: a term needs it on every device of the batch; "
                               f"diagnose those devices apart to try it")
    return out


def _print_result(diag, ladder, as_json: bool, report: Path | None, judged=None,
                  static=None) -> None:
    """The JSON object (with the ladder and the final diagnosis after --auto), or the tables;
    ``judged``: (records, summary) of --limits; ``static``: per device, the motion of the
    whole recording and the samples --static-only kept."""
    if as_json:
        from diffgyro._jsonio import dumps

        obj = diag.to_json()
        if judged is not None:
            obj["devices"], obj["limits"] = judged
        for rec, extra in zip(obj["devices"], static or []):
            rec.update(extra)
        if ladder is not None:
            obj["ladder"] = ladder.records()
            obj["final"] = ladder.final.to_json()
        typer.echo(dumps(obj))
        return
    console = wide_console()
    print_diagnosis(diag, console, None if judged is None else judged[0])
    for d, extra in zip(diag.devices, static or []):
        console.print(f"{d.device}: static only: {extra['n_samples']} of {extra['n_recorded']} "
                      "samples (the longest static interval)", markup=False)
    if ladder is not None:
        print_ladder(ladder, console)
    if judged is not None:

        print_lines(*judged, console=console)
    if report is not None:
        console.print(f"report: {Path(report) / 'index.html'}")
