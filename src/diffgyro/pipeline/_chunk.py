"""One chunk of a streaming run: read its devices, fit (or diagnose) them, and give the
JSON-ready records and calibration entries in plan order.

A device whose data is bad is recorded with its status and reason; the chunk's input
hash covers the data of every device read, so a resumed run can be checked.
"""

from __future__ import annotations

import hashlib
import json

import jax
import numpy as np

import diffgyro

from .._jsonio import number
from ..calibration import aux_entries, entry_json
from ..data import Batch, Recording
from ..diagnose import diagnose
from ..limits import add_figures, residual_allan
from ..status import STATUS_NAMES
from ._chunkfit import ChunkFitter
from ._dataset import ReadConfig, read_devices

INVALID = "invalid_data"   # status of a device whose data could not be read or validated


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


__all__ = ["INVALID", "PAD", "calibration_entries", "fit_chunk", "read_chunk", "run_chunk"]
