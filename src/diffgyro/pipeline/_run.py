"""Streaming fits: plan chunks, run the missing ones (here or on Dask), merge the results.

:func:`fit_dataset` is what ``diffgyro fit`` runs for a directory of Parquet
files or with ``--chunk-devices`` / ``--dask``:

1. index the inputs (device column only) and plan chunks of ``chunk_devices``
   devices in dataset order, or reuse the plan of an earlier run of the same
   command in the work directory;
2. run every chunk without a result file: read its rows, validate each device,
   fit (sharded over local JAX devices), write the chunk's results atomically;
3. merge the chunk files in plan order into the calibration file and the
   per-device results table (streamed, each written atomically).

A device whose data is bad, or whose fit is not ``ok``, is recorded with its
status and reason; it never stops the run. The output depends only on the
inputs, the model, the options and the chunk size, so a run killed at any
moment and started again gives exactly the output of an uninterrupted run.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import numpy as np

from ..errors import DataError
from ..io import parse_columns, resolve_units
from ..limits import Limits, check_model, load
from ..model import ErrorModel
from ._chunk import INVALID, fit_chunk, read_chunk, run_chunk
from ._dataset import ReadConfig, expand_inputs, fingerprint, index_dataset
from ._merge import combined_hash, merge
from ._progress import RunProgress
from ._workdir import FORMAT, FORMAT_VERSION, WorkDir

DEFAULT_CHUNK_DEVICES = 256


@dataclass
class RunSummary:
    """What a streaming run did (also returned when every chunk was already done)."""

    n_devices: int
    n_ok: int
    n_failed: int
    statuses: dict[str, int]
    chunks_total: int
    chunks_run: int
    seconds: float
    devices_per_second: float
    work_dir: str
    outputs: dict[str, str] = field(default_factory=dict)
    #: The batch's pass/fail against ``limits=`` (:func:`diffgyro.limits.summary`), or None.
    limits: dict | None = None


# --------------------------------------------------------------------------- planning


def plan_chunks(index, chunk_devices: int) -> list[dict]:
    """Chunks of ``chunk_devices`` devices in dataset order, with what to read for each."""
    plan = []
    devs = index.devices
    for c, lo in enumerate(range(0, len(devs), chunk_devices)):
        chunk = devs[lo:lo + chunk_devices]
        excluded = {}
        sources: dict[int, set[int] | None] = {}
        for d in chunk:
            if d in index.duplicates:
                names = ", ".join(index.files[k] for k in index.duplicates[d])
                excluded[d] = (f"device id appears in several files: {names} "
                               "(give each device a unique id)")
                continue
            if d in index.missing_signal:
                s = index.missing_signal[d]
                excluded[d] = (f"file {index.files[index.locations[d][0]]} has no {s!r} "
                               f"column(s), which the model needs")
                continue
            k, rgs = index.locations[d]
            if rgs is None:
                sources[k] = None
            else:
                sources.setdefault(k, set()).update(rgs)
        plan.append({"chunk": c, "devices": chunk, "excluded": excluded,
                     "sources": [[k, None if v is None else sorted(v)]
                                 for k, v in sorted(sources.items())]})
    return plan


def _needed_signals(model) -> tuple[str, ...]:
    return tuple(s for s in ("temp", "temp_ext", "accel", "rate") if s in model.requires())


#: Optional signals read for each command (diagnose tries effects that need any of them).
_WANTED = {"fit": lambda em: {"rate", *_needed_signals(em)},
           "diagnose": lambda em: {"rate", "temp", "temp_ext", "accel"}}


def default_work_dir(out: Path | None, results: Path | None, key: dict) -> Path:
    """Beside the output (``CAL.json.work``); else ``.diffgyro-work/<hash>`` here."""
    if out is not None:
        return Path(str(out) + ".work")
    if results is not None:
        return Path(str(results) + ".work")
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:12]
    return Path(".diffgyro-work") / digest


# --------------------------------------------------------------------------- the run


def fit_dataset(paths: Sequence[str | os.PathLike], model: str, **kwargs) -> RunSummary:
    """Fit ``model`` to every device of a Parquet dataset, chunk by chunk, resumably.

    ``out`` is the calibration file; ``results`` the per-device table
    (``.jsonl`` or ``.parquet``; default beside ``out`` as ``NAME.devices.jsonl``,
    else in the work directory). ``work_dir`` holds the resumable state
    (default ``OUT.work``); ``resume=False`` discards it first. ``dask`` is a
    scheduler address, or ``local:N`` for a local cluster of N worker
    processes. ``fit_options`` are :class:`~diffgyro.fit.FitOptions` fields.
    ``json_stream`` receives the ``fit --json`` object, device by device.
    ``columns``, ``units``, ``drop_invalid``, ``sampling_rate`` are as in
    :func:`diffgyro.io.load`; ``shard=False`` keeps each chunk on one JAX device.

    **Arguments:**

    - ``paths``: the Parquet files (or folders of them).
    - ``model``: the model spec.
    - ``**kwargs``: ``out``, ``results``, ``work_dir``, ``resume``, ``dask``,
      ``fit_options``, ``json_stream``, ``columns``, ``units``, ``drop_invalid``,
      ``sampling_rate``, ``shard``, as above.
    """
    kwargs["fit_options"] = {"dtemp_window": 60.0, **(kwargs.get("fit_options") or {})}
    return _run("fit", paths, model, **kwargs)


def diagnose_dataset(paths: Sequence[str | os.PathLike], model: str,
                     candidates: Sequence[str] | None = None, **kwargs) -> RunSummary:
    """:func:`diffgyro.diagnose.diagnose` over a Parquet dataset, chunk by chunk, resumably.

    ``json_stream`` receives the ``diagnose --json`` object (``model``, ``devices``);
    ``results`` the per-device table. Without ``fit_options["dtemp_window"]`` each
    chunk chooses its own dT/dt window from its temperature read-outs (as
    ``diagnose`` does for a batch); give one to make it the same for all. Other
    keywords as for :func:`fit_dataset` (no calibration file: ``out`` is refused).

    **Arguments:**

    - ``paths``: the Parquet files (or folders of them).
    - ``model``: the base model spec.
    - ``candidates``: the effects tried, as for :func:`diffgyro.diagnose.diagnose`.
    - ``**kwargs``: as for :func:`fit_dataset`, ``out`` aside.
    """
    if kwargs.get("out") is not None:
        raise DataError("diagnose writes no calibration file; use results= for the table")
    task = {"candidates": None if candidates is None else list(dict.fromkeys(candidates))}
    return _run("diagnose", paths, model, task_options=task, **kwargs)


def _run(
    command: str,
    paths: Sequence[str | os.PathLike],
    model: str,
    *,
    out: str | os.PathLike | None = None,
    results: str | os.PathLike | None = None,
    work_dir: str | os.PathLike | None = None,
    chunk_devices: int = DEFAULT_CHUNK_DEVICES,
    resume: bool = True,
    dask: str | None = None,
    columns: dict[str, str] | None = None,
    units: dict[str, str] | None = None,
    drop_invalid: bool = False,
    sampling_rate: float | None = None,
    fit_options: dict | None = None,
    task_options: dict | None = None,
    shard: bool | None = None,
    progress: bool = True,
    json_stream: IO[str] | None = None,
    on_chunk: Callable[[dict], None] | None = None,
    limits=None,
) -> RunSummary:
    """The streaming run behind :func:`fit_dataset` and :func:`diagnose_dataset`.
    ``limits``: a :class:`diffgyro.limits.Limits` (or the path of a limits file) every
    device is checked against when the outputs are merged; the figures it asks for are
    computed in the chunks (they join the run's key, the bounds do not: a run finished
    with other bounds is merged again without fitting)."""
    t_start = time.monotonic()
    if limits is not None:

        if not isinstance(limits, Limits):
            limits = load(limits)
        check_model(limits, ErrorModel.from_spec(model))
        if limits.computed:
            task_options = {**(task_options or {}), "figures": sorted(limits.computed)}
    em, files, cfg, key = _run_key(command, paths, model, chunk_devices, columns, units,
                                   drop_invalid, sampling_rate, fit_options, task_options)
    out = None if out is None else Path(out)
    if results is None and out is not None:
        results = out.with_name(out.name.removesuffix(".json") + ".devices.jsonl")
    results = None if results is None else Path(results)
    work = WorkDir(work_dir if work_dir is not None else default_work_dir(out, results, key))
    if results is None:
        results = work.path / "results.jsonl"

    work.lock()
    try:
        manifest = _open_manifest(work, key, resume, files, cfg, em)
        plan = manifest["chunks"]
        setup = {"command": command, "model": em.spec, "fit_options": key["options"]["fit"],
                 "task_options": key["options"]["task"], "chunk_devices": key["chunk_devices"],
                 "shard": shard, "read": key["options"]["read"], "files": manifest["files"]}
        done, skipped_failed = _finished_chunks(work, plan)
        pending = [c for c in plan if c["chunk"] not in done]
        bar = _progress(progress, command, manifest["n_devices"],
                        sum(len(c["devices"]) for c in plan if c["chunk"] in done), skipped_failed)
        try:
            if pending:
                _run_pending(work, manifest, pending, setup, dask, bar, on_chunk)
        finally:
            bar.close()
        counts = _merge_all(work, manifest, out, results, json_stream, limits)
        judged = counts.pop("limits", None)
    finally:
        work.unlock()
    n_dev = manifest["n_devices"]
    n_ok = counts.get("ok", 0)
    seconds = time.monotonic() - t_start
    return RunSummary(n_devices=n_dev, n_ok=n_ok, n_failed=n_dev - n_ok, statuses=counts,
                      chunks_total=len(plan), chunks_run=len(pending), seconds=seconds,
                      devices_per_second=bar.rate, work_dir=str(work.path),
                      outputs={k: v for k, v in manifest["outputs"].items() if v}, limits=judged)


def _run_key(command, paths, model, chunk_devices, columns, units, drop_invalid,
             sampling_rate, fit_options, task_options):
    """The checked model, input files and read configuration, and the run's key (what a
    work directory must match to be resumed)."""

    em = ErrorModel.from_spec(model)
    if any(r.startswith("aux:") for r in em.requires()):  # the readers keep standard columns
        raise DataError(f"the streaming run reads the standard columns only; model {em.spec!r} "
                        f"reads an extra column", hint="fit it with diffgyro fit")
    if isinstance(chunk_devices, bool) or int(chunk_devices) < 1:
        raise DataError(f"--chunk-devices must be a positive integer, not {chunk_devices!r}")
    if isinstance(columns, str):
        columns = parse_columns(columns)
    resolve_units(units)  # unknown units fail here, before any work
    if sampling_rate is not None and not (np.isfinite(sampling_rate) and sampling_rate > 0):
        raise DataError(f"sampling rate must be a positive number of Hz, got {sampling_rate}")
    files = expand_inputs(paths)
    cfg = ReadConfig(columns=dict(columns or {}), units=dict(units or {}),
                     drop_invalid=bool(drop_invalid), sampling_rate=sampling_rate,
                     wanted=tuple(sorted(_WANTED[command](em))))
    key = {"command": command, "model": em.spec, "chunk_devices": int(chunk_devices),
           "options": {"fit": dict(fit_options or {}), "task": dict(task_options or {}),
                       "read": cfg.to_json()},
           "inputs": [fingerprint(f) for f in files]}
    return em, files, cfg, key


def _open_manifest(work: WorkDir, key: dict, resume: bool, files, cfg: ReadConfig, em) -> dict:
    """The work directory's manifest: the one there when it holds this run and ``resume``,
    else a new one from indexing the inputs (the directory cleared)."""
    manifest = work.read_manifest()
    if manifest is not None and resume and manifest.get("key") != key:
        raise DataError(
            "the work directory holds a different run (other command, model, options, "
            "chunk size or changed input files)", file=str(work.path),
            hint="use --no-resume to discard it, or another --work-dir")
    if manifest is None or not resume:
        work.clear()
        index = index_dataset(files, cfg, needed=[s for s in _needed_signals(em) if s != "rate"])
        manifest = {"format": FORMAT, "format_version": FORMAT_VERSION, "key": key,
                    "files": index.files, "n_devices": len(index.devices),
                    "chunks": plan_chunks(index, key["chunk_devices"]), "complete": False,
                    "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds")}
        del index
        work.write_manifest(manifest)
    work.remove_temporaries()
    return manifest


def _finished_chunks(work: WorkDir, plan: list[dict]) -> tuple[set[int], int]:
    """The chunks with a result file already, and how many of their devices are not ok."""
    done: set[int] = set()
    not_ok = 0
    for c in plan:
        obj = work.read_chunk(c["chunk"], c["devices"])
        if obj is not None:
            done.add(c["chunk"])
            not_ok += sum(r["status"] != "ok" for r in obj["records"])
        del obj
    return done, not_ok


def _run_pending(work: WorkDir, manifest: dict, pending: list[dict], setup: dict,
                 dask: str | None, bar, on_chunk) -> None:
    """Run the pending chunks (here or on a Dask cluster), each result written as it comes;
    the manifest is rewritten at most every 2 s."""
    plan = manifest["chunks"]
    last_manifest = [time.monotonic()]

    def finished(res: dict) -> None:
        work.write_chunk(res["chunk"], res)
        plan[res["chunk"]]["status"] = "done"
        bar.update(len(res["devices"]), sum(r["status"] != "ok" for r in res["records"]))
        if time.monotonic() - last_manifest[0] > 2.0:
            work.write_manifest(manifest)
            last_manifest[0] = time.monotonic()
        if on_chunk is not None:
            on_chunk(res)

    if dask:
        from ._cluster import run_on_dask

        run_on_dask(dask, run_chunk, pending, setup, finished)
    else:
        _run_local(pending, setup, finished)


def _merge_all(work: WorkDir, manifest: dict, out: Path | None, results: Path,
               json_stream, limits=None) -> dict:
    """Every chunk's result merged into the outputs; the manifest marked complete."""
    hashes = []
    for c in manifest["chunks"]:
        obj = work.read_chunk(c["chunk"], c["devices"])
        if obj is None:
            raise DataError(f"chunk {c['chunk']} has no result file", file=str(work.path))
        c["status"] = "done"
        hashes.append(obj["input_hash"])
    manifest["input_hash"] = combined_hash(hashes)
    work.write_manifest(manifest)
    counts = merge(work, manifest, out, results, json_stream, limits)
    manifest["complete"] = True
    manifest["outputs"] = {"calibration": None if out is None else str(out),
                           "results": str(results)}
    work.write_manifest(manifest)
    return counts


def _progress(enabled: bool, label: str, total: int, skipped: int, skipped_failed: int):

    return RunProgress(total, skipped, skipped_failed, enabled=enabled, label=label)


def _run_local(pending: list[dict], setup: dict, finished: Callable[[dict], None]) -> None:
    """Chunks one after another in this process; the next chunk is read while one is fitted."""

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="diffgyro-read") as pool:
        nxt = pool.submit(read_chunk, pending[0], setup)
        for k, job in enumerate(pending):
            prepared = nxt.result()
            if k + 1 < len(pending):
                nxt = pool.submit(read_chunk, pending[k + 1], setup)
            finished(fit_chunk(job, setup, prepared))
            del prepared


__all__ = ["DEFAULT_CHUNK_DEVICES", "INVALID", "RunSummary",
           "diagnose_dataset", "fit_chunk", "fit_dataset", "merge", "plan_chunks", "read_chunk",
           "run_chunk"]
