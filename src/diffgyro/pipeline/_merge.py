"""The outputs of a streaming run, merged from its chunk files in plan order: the calibration
file and the per-device results table, each streamed and written atomically, and the
batch's limits summary.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import IO

import pyarrow as pa
import pyarrow.parquet as pq

from .. import __version__
from .._jsonio import AtomicFile, dumps
from ..calibration import units_of
from ..errors import DataError
from ..limits import check as check_limits
from ..limits import lookup, summary
from ..model import ErrorModel
from ._workdir import WorkDir

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


__all__ = ["combined_hash", "merge"]
