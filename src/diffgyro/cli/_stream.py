"""Options and dispatch for streaming runs (``--chunk-devices``, ``--work-dir``,
``--resume/--no-resume``, ``--dask``, ``--results``); see :mod:`diffgyro.pipeline`.

This module starts with ``_`` so it is not imported as a command.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated

import typer

from diffgyro.errors import DataError

from . import _progress
from ._load import units_from_cli

ChunkDevices = Annotated[
    int | None,
    typer.Option("--chunk-devices", min=1,
                 help="Stream the data in chunks of this many devices (default 256 when DATA "
                      "is a directory); peak memory follows the chunk size."),
]
WorkDirOpt = Annotated[
    Path | None,
    typer.Option("--work-dir", help="Resumable state of a streaming run (default: OUT.work, "
                                    "beside --out)."),
]
Resume = Annotated[
    bool,
    typer.Option("--resume/--no-resume", help="Skip the chunks an earlier run of the same "
                                              "command finished (--no-resume starts again)."),
]
DaskOpt = Annotated[
    str | None,
    typer.Option("--dask", metavar="ADDRESS|local:N",
                 help="Run the chunks on a Dask cluster (scheduler address), or on N local "
                      "worker processes; needs pip install 'diffgyro[dask]'."),
]
ResultsOpt = Annotated[
    Path | None,
    typer.Option("--results", help="Per-device results table of a streaming run (.jsonl or "
                                   ".parquet; default OUT.devices.jsonl beside --out)."),
]


def stream_fit(data, model, out, as_json, dtemp_window, columns, gyro_unit, acc_unit, temp_unit,
               time_unit, sampling_rate, drop_invalid, chunk_devices, work_dir, resume, dask,
               results, limits=None) -> None:
    """``diffgyro fit`` over a dataset in chunks; same ``--json`` object as the plain fit."""
    from diffgyro.io import parse_columns
    from diffgyro.pipeline import DEFAULT_CHUNK_DEVICES, fit_dataset

    summary = fit_dataset(
        data, model, out=out, results=results, work_dir=work_dir,
        chunk_devices=chunk_devices or DEFAULT_CHUNK_DEVICES, resume=resume, dask=dask,
        columns=parse_columns(columns),
        units=units_from_cli(gyro_unit, acc_unit, temp_unit, time_unit),
        drop_invalid=drop_invalid, sampling_rate=sampling_rate,
        fit_options={} if dtemp_window is None else {"dtemp_window": float(dtemp_window)},
        progress=not _progress.quiet(),
        json_stream=sys.stdout if as_json else None, limits=limits)
    bad = ", ".join(f"{n} {s}" for s, n in sorted(summary.statuses.items()) if s != "ok")
    print(f"diffgyro fit: {summary.n_ok} of {summary.n_devices} devices ok"
          + (f" ({bad})" if bad else "") + f"; {summary.chunks_run} of {summary.chunks_total} "
          f"chunks run, {summary.devices_per_second:.1f} devices/s", file=sys.stderr)
    _print_limits("fit", summary.limits)
    for name, path in summary.outputs.items():
        print(f"diffgyro fit: {name} written to {path}", file=sys.stderr)


def _print_limits(command: str, summary: dict | None) -> None:
    """The yield and the rejected units of a streamed run (stderr: stdout holds --json)."""
    if summary is None:
        return
    y = summary["yield"]
    rejected = summary["rejected"]
    shown = ", ".join(rejected[:20]) + (f" and {len(rejected) - 20} more" if len(rejected) > 20
                                        else "") or "none"
    print(f"diffgyro {command}: limits {summary['name']} ({summary['file']}): {summary['passed']} "
          f"of {summary['passed'] + summary['failed']} devices pass"
          + ("" if y is None else f" (yield {100 * y:.1f} %)") + f"; rejected: {shown}",
          file=sys.stderr)


def stream_diagnose(data, model, as_json, report, auto, candidates, dtemp_window, columns,
                    gyro_unit, acc_unit, temp_unit, time_unit, sampling_rate, drop_invalid,
                    chunk_devices, work_dir, resume, dask, results, limits=None) -> None:
    """``diffgyro diagnose`` over a dataset in chunks; same ``--json`` object (model, devices)."""

    from diffgyro.io import parse_columns
    from diffgyro.pipeline import DEFAULT_CHUNK_DEVICES, diagnose_dataset

    if report is not None or auto:
        raise DataError("--report and --auto need every device in memory; they do not stream",
                        hint="give data files without --chunk-devices/--dask, or a subset")
    names = [c.strip() for c in candidates.split(",") if c.strip()] if candidates else None
    if names:
        from diffgyro.effects import parse_term

        for n in names:
            parse_term(n)
    summary = diagnose_dataset(
        data, model, names, results=results, work_dir=work_dir,
        chunk_devices=chunk_devices or DEFAULT_CHUNK_DEVICES, resume=resume, dask=dask,
        columns=parse_columns(columns),
        units=units_from_cli(gyro_unit, acc_unit, temp_unit, time_unit),
        drop_invalid=drop_invalid, sampling_rate=sampling_rate,
        fit_options={} if dtemp_window is None else {"dtemp_window": float(dtemp_window)},
        progress=not _progress.quiet(), json_stream=sys.stdout if as_json else None, limits=limits)
    verdicts: dict[str, int] = {}
    missing: dict[str, int] = {}
    with open(summary.outputs["results"], encoding="utf-8") as fh:
        for line in fh:
            r = json.loads(line)
            verdicts[str(r.get("verdict") or r.get("status"))] = \
                verdicts.get(str(r.get("verdict") or r.get("status")), 0) + 1
            best = r.get("best_effect")
            if r.get("verdict") == "missing_effect" and best:
                missing[best] = missing.get(best, 0) + 1
    text = ", ".join(f"{n} {v}" for v, n in sorted(verdicts.items(), key=lambda x: -x[1]))
    print(f"diffgyro diagnose: {summary.n_devices} devices: {text}; {summary.chunks_run} of "
          f"{summary.chunks_total} chunks run", file=sys.stderr)
    if missing:
        top = ", ".join(f"{e} ({n})" for e, n in sorted(missing.items(), key=lambda x: -x[1]))
        print(f"diffgyro diagnose: missing effects found: {top}", file=sys.stderr)
    _print_limits("diagnose", summary.limits)
    print(f"diffgyro diagnose: results written to {summary.outputs['results']}", file=sys.stderr)
