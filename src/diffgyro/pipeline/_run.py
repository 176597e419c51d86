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
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

import jax
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

import diffgyro

from .. import __version__
from .._jsonio import AtomicFile, dumps, number
from ..calibration import aux_entries, entry_json, units_of
from ..data import Batch, Recording
from ..diagnose import diagnose
from ..errors import DataError
from ..io import parse_columns, resolve_units
from ..limits import Limits, add_figures, check_model, load, lookup, residual_allan, summary
from ..limits import check as check_limits
from ..model import ErrorModel
from ..status import STATUS_NAMES
from ._chunkfit import ChunkFitter
from ._dataset import ReadConfig, expand_inputs, fingerprint, index_dataset, read_devices
from ._progress import RunProgress
from ._workdir import FORMAT, FORMAT_VERSION, WorkDir

DEFAULT_CHUNK_DEVICES = 256
INVALID = "invalid_data"   # status of a device whose data could not be read or validated


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


# --------------------------------------------------------------------------- one chunk

_FITTERS: dict[str, object] = {}


def _fitter(setup: dict):
    """The chunk fitter of this process for ``setup`` (kept warm: compiled once per process)."""

    key = json.dumps([setup["model"], setup["fit_options"], setup["chunk_devices"],
                      setup.get("shard")], sort_keys=True)
    fitter = _FITTERS.get(key)
    if fitter is None:
        fitter = ChunkFitter(setup["model"], setup["chunk_devices"], setup["fit_options"],
                             shard=setup.get("shard"))
        _FITTERS[key] = fitter
    return fitter


def read_chunk(job: dict, setup: dict) -> tuple[dict[str, Recording], dict[str, str]]:
    """Recordings of a chunk's devices and the reasons of those that cannot be fitted.

    **Arguments:**

    - ``job``: the chunk's job: its devices and their files.
    - ``setup``: the run's settings (loading).
    """
    cfg = ReadConfig.from_json(setup["read"])
    failed: dict[str, str] = dict(job.get("excluded", {}))
    devices = [d for d in job["devices"] if d not in failed]
    sources = [(int(k), None if rgs is None else list(rgs)) for k, rgs in job["sources"]]
    recs, errors = read_devices(setup["files"], sources, devices, cfg)
    for dev, err in errors.items():
        failed[dev] = str(err)
    for dev in devices:
        if dev not in recs and dev not in failed:
            failed[dev] = "device not found in its file (was the file changed?)"
    return recs, failed


def _device_hash(h, rec: Recording) -> None:
    h.update(rec.device.encode())
    for s in rec.signals:
        h.update(s.encode())
        h.update(np.ascontiguousarray(np.asarray(getattr(rec, s), np.float64)).tobytes())


def _invalid_record(device: str, reason: str) -> dict:
    return {"device": device, "status": INVALID, "status_detail": f"{INVALID}: {reason}",
            "rms": None, "heldout_rms": None, "noise_floor": None, "steps": 0, "n_samples": 0,
            "params": None, "reason": reason}


def calibration_entries(result) -> list[dict]:
    """Every device's calibration entry, exactly as ``calibration.from_fit`` gives it
    (JSON-cleaned ``DeviceCalibration`` fields), built with the labels computed once per
    model instead of once per device: a 256-device chunk in milliseconds rather than
    seconds (tests/test_pipeline.py checks the two agree)."""


    model = result.model
    labels = model.param_labels()
    beta = np.asarray(result.params.beta, float)
    theta = np.asarray(result.params.theta, float)
    shared = []
    for t, _, qs in model.slices():
        if t.n_nonlinear:
            vals = np.asarray(jax.vmap(t.nonlinear_values)(theta[:, qs]), float)
            shared.append(([f"{t.spec}.{n}" for n in t.nonlinear_names()], vals))
    rms, held, floor = (np.asarray(x, float) for x in
                        (result.rms, result.heldout_rms, result.noise_floor))
    steps, n_samples = np.asarray(result.steps), np.asarray(result.n_samples)
    status = np.asarray(result.status)
    centre, scale = np.asarray(result.norm.centre, float), np.asarray(result.norm.scale, float)
    trange = None if result.temp_range is None else np.asarray(result.temp_range, float)
    out = []
    for i, name in enumerate(result.devices):
        params = {ax: {lab: float(v) for lab, v in zip(labels[k], beta[i, k])}
                  for k, ax in enumerate("xyz")}
        if shared:
            params["shared"] = {n: float(v) for names, vals in shared
                                for n, v in zip(names, vals[i])}
        st = STATUS_NAMES[int(status[i])]
        out.append(entry_json({
            "device": name, "status": st, "beta": beta[i].tolist(), "theta": theta[i].tolist(),
            "temp_centre": float(centre[i]), "temp_scale": float(scale[i]),
            "temp_range": None if trange is None else trange[i].tolist(),
            "quality": {"rms": number(rms[i]), "heldout_rms": number(held[i]),
                        "noise_floor": number(floor[i]), "n_samples": int(n_samples[i]),
                        "steps": int(steps[i])},
            "params": params,
            "status_detail": st if st == "ok" else result.status_detail(i),
            "aux": aux_entries(result, i),
            "motion": {} if result.motion is None else result.motion.record(i)}))
    return out


PAD = "__diffgyro_pad_{}__"


def _figures(records: list[dict], result, batch: Batch, wanted, residuals=None) -> None:
    """Add the computed figures a limits file asks for (:mod:`diffgyro.limits._figures`) to the
    records of one group, in place: the Allan read-outs of the fit residual need the samples,
    so they are taken here, in the chunk, where the samples are."""

    n = len(records)
    allan = [None] * n
    if "allan" in wanted:
        res = np.asarray(result.residuals(batch)) if residuals is None else residuals
        allan = residual_allan(res[:n], np.asarray(batch.t)[:n], np.asarray(batch.n_valid)[:n])
    trange = None if result.temp_range is None else np.asarray(result.temp_range, float)
    centre, scale = np.asarray(result.norm.centre, float), np.asarray(result.norm.scale, float)
    for i, r in enumerate(records):
        fig = add_figures(r, set(wanted), allan=allan[i],
                          centre=float(np.broadcast_to(centre, (batch.n_devices,))[i]),
                          scale=float(np.broadcast_to(scale, (batch.n_devices,))[i]),
                          temp_range=None if trange is None else trange[i].tolist())
        r.update({k: v for k, v in fig.items() if k not in r})


def _diagnose_group(group: list[Recording], setup: dict) -> dict[str, dict]:
    """``diagnose`` records of one group, padded to the chunk size (one compiled shape)."""

    n = len(group)
    pads = [Recording(**{s: getattr(group[-1], s) for s in ("t", "gyro", "temp", "temp_ext",
                                                             "accel", "mag", "rate", "quat")},
                      device=PAD.format(k), source=None)
            for k in range(max(0, int(setup["chunk_devices"]) - n))]
    opts = dict(setup["fit_options"])
    if opts.get("dtemp_window") is None:
        opts.pop("dtemp_window", None)
    batch = Batch.from_recordings(group + pads)
    diag = diagnose(setup["model"], batch, setup["task_options"].get("candidates"), **opts)
    records = diag.to_json()["devices"][:n]
    if setup["task_options"].get("figures"):
        _figures(records, diag.fit, batch, setup["task_options"]["figures"], diag.residuals)
    return {r["device"]: r for r in records}


def _invalid_diagnosis(device: str, reason: str) -> dict:
    return {"device": device, "rms": None, "heldout_rms": None, "noise_floor": None,
            "verdict": None, "candidates": [], "status": INVALID, "reason": reason}


def fit_chunk(job: dict, setup: dict, prepared=None) -> dict:
    """Fit (or diagnose) one chunk; its JSON-ready result: records and calibration
    entries, in plan order.

    **Arguments:**

    - ``job``: the chunk's job: its devices and their files.
    - ``setup``: the run's settings (model, options, loading).
    - ``prepared``: the chunk's recordings already read (:func:`read_chunk`), or None to
      read them.
    """
    recs, failed = prepared if prepared is not None else read_chunk(job, setup)
    diagnosing = setup.get("command", "fit") == "diagnose"
    records: dict[str, dict] = {}
    cal: dict[str, dict] = {}
    # devices recording different signal sets are fitted apart: a device's result never
    # depends on which other devices share its chunk
    groups: dict[tuple, list[Recording]] = {}
    for dev in job["devices"]:
        if dev in recs:
            groups.setdefault(recs[dev].signals, []).append(recs[dev])
    for group in groups.values():
        if diagnosing:
            records.update(_diagnose_group(group, setup))
            continue
        batch = Batch.from_recordings(group)
        result = _fitter(setup).fit(batch)
        added = []
        for entry in calibration_entries(result):
            name = entry["device"]
            cal[name] = entry
            q = entry["quality"]
            records[name] = {"device": name, "status": entry["status"],
                                 "status_detail": entry["status_detail"], "rms": q["rms"],
                                 "heldout_rms": q["heldout_rms"], "noise_floor": q["noise_floor"],
                                 "steps": q["steps"], "n_samples": q["n_samples"],
                                 "params": entry["params"]}
            added.append(records[name])
        if setup["task_options"].get("figures"):
            _figures(added, result, batch, setup["task_options"]["figures"])
    for dev, reason in failed.items():
        records[dev] = (_invalid_diagnosis if diagnosing else _invalid_record)(dev, reason)
    h = hashlib.sha256()
    for dev in job["devices"]:
        if dev in recs:
            _device_hash(h, recs[dev])
    return {"chunk": job["chunk"], "devices": list(job["devices"]),
            "records": [records[d] for d in job["devices"]],
            "calibration": [cal.get(d) for d in job["devices"]],
            "input_hash": h.hexdigest()}


def run_chunk(job: dict, setup: dict) -> dict:
    """Read and fit (or diagnose) one chunk: the unit of work a Dask worker runs."""

    diffgyro.enable_x64()
    return fit_chunk(job, setup)


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


# --------------------------------------------------------------------------- merging


_RESULT_COLUMNS = ("device", "status", "status_detail", "reason", "rms", "heldout_rms",
                   "noise_floor", "steps", "n_samples", "params")


class _ResultsWriter:
    """The per-device results table, JSON lines or Parquet (by the file suffix)."""

    def __init__(self, path: Path, limits: bool = False):
        self.path = path
        self.limits = limits  # two more columns: limits_result and limits (JSON)
        self.parquet = path.suffix.lower() in (".parquet", ".pq")
        self._file = AtomicFile(path, None if self.parquet else "w")
        self._pq = None

    def write(self, records: list[dict]) -> None:
        if not self.parquet:
            for r in records:
                self._file.fh.write(dumps(r) + "\n")
            return

        cols = {c: [r.get(c) for r in records] for c in _RESULT_COLUMNS}
        cols["params"] = [None if p is None else dumps(p) for p in cols["params"]]
        fields = [("device", pa.string()), ("status", pa.string()),
                  ("status_detail", pa.string()), ("reason", pa.string()),
                  ("rms", pa.float64()), ("heldout_rms", pa.float64()),
                  ("noise_floor", pa.float64()), ("steps", pa.int64()),
                  ("n_samples", pa.int64()), ("params", pa.string())]
        if self.limits:
            cols["limits_result"] = [r["limits"]["result"] for r in records]
            cols["limits"] = [dumps(r["limits"]) for r in records]
            fields += [("limits_result", pa.string()), ("limits", pa.string())]
        schema = pa.schema(fields)
        table = pa.table(cols, schema=schema)
        if self._pq is None:
            self._pq = pq.ParquetWriter(self._file.tmp, schema)
        self._pq.write_table(table)

    def commit(self) -> None:
        if self._pq is not None:
            self._pq.close()
        self._file.commit()

    def abort(self) -> None:
        if self._pq is not None:
            self._pq.close()
        self._file.abort()


class _CalibrationWriter:
    """A calibration file streamed device by device (the format of :mod:`diffgyro.calibration`)."""

    def __init__(self, path: Path, header: dict):
        self.path = path
        self._file = AtomicFile(path, "w")
        head = dumps({**header, "devices": []}, indent=1)
        assert head.endswith('"devices": []\n}')
        self._file.fh.write(head[: -len("[]\n}")] + "[")
        self.n = 0

    def write(self, entry: dict) -> None:
        self._file.fh.write(("\n" if self.n == 0 else ",\n") + dumps(entry))
        self.n += 1

    def commit(self, tail: dict | None = None) -> None:
        """Close the devices list; ``tail``: top-level keys written after it (the limits
        summary, known only once every device is written)."""
        more = "".join(f",\n{dumps(k)}: {dumps(v)}" for k, v in (tail or {}).items())
        self._file.fh.write(f"\n]{more}\n}}\n")
        self._file.commit()

    def abort(self) -> None:
        self._file.abort()


def merge(work: WorkDir, manifest: dict, out: Path | None, results: Path | None,
          json_stream: IO[str] | None = None, limits=None) -> dict[str, int]:
    """Write the outputs from the chunk files in plan order; counts of each status.
    ``limits`` (:class:`diffgyro.limits.Limits`): every record and calibration entry gets
    its pass/fail, and the calibration file and JSON object the batch's summary
    (``counts["limits"]``)."""

    spec = manifest["key"]["model"]
    plan = manifest["chunks"]
    counts: dict[str, int] = {}
    writers = []
    cal_w = res_w = None
    try:
        if results is not None:
            res_w = _ResultsWriter(results, limits is not None)
            writers.append(res_w)
        if out is not None:
            header = {"format": "diffgyro-calibration", "format_version": 1, "model": spec,
                      "dtemp_window": float(manifest["key"]["options"]["fit"]["dtemp_window"]),
                      "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
                      "diffgyro_version": __version__, "input_hash": None,
                      "units": units_of(ErrorModel.from_spec(spec))}
            # the input hash (of every chunk's data) is known only at the end: a second
            # pass would cost a re-read, so it goes into the header from the manifest
            header["input_hash"] = manifest.get("input_hash")
            cal_w = _CalibrationWriter(out, header)
            writers.append(cal_w)
        if json_stream is not None:
            json_stream.write(dumps({"model": spec})[:-1] + ', "devices": [')
        first = True
        judged: list[dict] = []
        for c in plan:
            obj = work.read_chunk(c["chunk"], c["devices"])
            if obj is None:
                raise DataError(f"chunk {c['chunk']} has no result file", file=str(work.path),
                                hint="run the command again to finish it")
            if limits is not None:
                for rec, entry in zip(obj["records"], obj["calibration"]):
                    rec["limits"] = check_limits(limits, rec)
                    judged.append({"device": rec["device"], "limits": rec["limits"],
                                   "found": _found(limits, rec)})
                    if entry is not None:
                        entry["limits"] = rec["limits"]
            for rec, entry in zip(obj["records"], obj["calibration"]):
                counts[rec["status"]] = counts.get(rec["status"], 0) + 1
                if cal_w is not None and entry is not None:
                    cal_w.write(entry)
                if json_stream is not None:
                    json_stream.write(("" if first else ",") + "\n" + dumps(rec))
                    first = False
            if res_w is not None:
                res_w.write(obj["records"])
        tail = {}
        if limits is not None:
            tail = {"limits": _limits_summary(limits, judged)}
            counts["limits"] = tail["limits"]
        if json_stream is not None:
            json_stream.write("\n]" + "".join(f", {dumps(k)}: {dumps(v)}" for k, v in tail.items())
                              + "}\n")
            json_stream.flush()
        if cal_w is not None:
            if cal_w.n == 0:
                cal_w.abort()
                writers.remove(cal_w)
                print("diffgyro: no device could be fitted; no calibration file written",
                      file=sys.stderr)
            else:
                cal_w.commit(tail)
                writers.remove(cal_w)
        if res_w is not None:
            res_w.commit()
            writers.remove(res_w)
    finally:
        for w in writers:
            w.abort()
    return counts


def _found(limits, rec: dict) -> set[str]:
    """The limit paths that name a field of ``rec`` (to warn of those no record holds)."""

    return {lim.path for lim in limits.limits if lookup(rec, lim.path)}


def _limits_summary(limits, judged: list[dict]) -> dict:
    """The batch's limits summary; a warning for each limit no device record matched."""

    found = set().union(*(j.pop("found") for j in judged)) if judged else set()
    for lim in limits.limits:
        if lim.path not in found:
            print(f"diffgyro: warning: limits file {limits.file}: {lim.path!r} matched no field "
                  f"of any device record (every device fails it unless optional = true)",
                  file=sys.stderr)
    return summary(limits, judged)


def combined_hash(chunk_hashes: Sequence[str]) -> str:
    """Input hash of a streamed run: SHA-256 over the chunks' SHA-256 of their devices' data."""
    h = hashlib.sha256()
    for x in chunk_hashes:
        h.update(bytes.fromhex(x))
    return "sha256-chunks:" + h.hexdigest()


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
