"""Writing recordings in the standard schema, atomically and round-trip exact."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .._jsonio import AtomicFile
from ..data import OPTIONAL_SIGNALS, SIGNALS, Batch, Recording
from ..errors import DataError
from ._float_text import float_texts
from ._source import OPENERS, format_of

#: Files of at most this many numbers are formatted in Python (io._float_text): quicker
#: than importing pyarrow and pandas (0.2-0.3 s) up to about this size.
SMALL_VALUES = 1 << 18


def _as_recordings(data) -> list[Recording]:
    if isinstance(data, Recording):
        return [data]
    if isinstance(data, Batch):
        return data.recordings()
    recs = list(data)
    if not recs or not all(isinstance(r, Recording) for r in recs):
        raise DataError("save needs a Recording, a Batch or a non-empty list of Recordings")
    return recs


def save(data: Recording | Batch | Sequence[Recording], path: str | os.PathLike) -> Path:
    """Write recordings in the standard schema (long format) to CSV, Parquet or NPZ.

    Extra columns (``aux``) follow the standard ones under their names.

    The format follows the extension (``.csv``, ``.tsv``, ``.csv.gz``,
    ``.parquet``, ``.npz``). Values are written as float64 in the shortest
    decimal form that reads back bitwise identical. The file is written to a
    temporary name in the same folder and moved into place, so a crash never
    leaves half a file. Returns the path written.

    **Arguments:**

    - ``data``: one Recording, a Batch or a list of Recordings.
    - ``path``: the file; its extension chooses the format.
    """
    path = Path(path)
    recs = _as_recordings(data)
    seen: set[str] = set()
    for r in recs:
        if r.device in seen:
            raise DataError("device id appears more than once", device=r.device, file=str(path))
        seen.add(r.device)
        if r.signals != recs[0].signals:
            raise DataError(
                f"devices record different signals ({', '.join(r.signals)} vs "
                f"{', '.join(recs[0].signals)} for {recs[0].device}); one long-format file "
                f"needs the same columns for all", device=r.device, file=str(path),
                hint="save them to separate files")
        if list(r.aux) != list(recs[0].aux):
            raise DataError(
                f"devices have different extra columns ({', '.join(r.aux) or 'none'} vs "
                f"{', '.join(recs[0].aux) or 'none'} for {recs[0].device}); one long-format "
                f"file needs the same columns for all", device=r.device, file=str(path),
                hint="save them to separate files")
    fmt, compression = format_of(path)
    cols: dict[str, np.ndarray] = {
        "device": np.concatenate([np.full(r.n, r.device, dtype=object) for r in recs])}
    for sig in ("t", "gyro", *OPTIONAL_SIGNALS):
        if getattr(recs[0], sig) is None:
            continue
        names = ("t",) if sig == "t" else SIGNALS[sig]
        stacked = np.concatenate(
            [np.asarray(getattr(r, sig), dtype=np.float64).reshape(r.n, len(names))
             for r in recs])
        for k, name in enumerate(names):
            cols[name] = stacked[:, k]
    for name in recs[0].aux:
        cols[name] = np.concatenate([np.asarray(r.aux[name], dtype=np.float64) for r in recs])
    with AtomicFile(path, None) as f:
        tmp = f.tmp
        if fmt == "csv":
            _write_csv(cols, tmp, "\t" if ".tsv" in [s.lower() for s in path.suffixes] else ",",
                       compression)
        elif fmt == "parquet":
            import pyarrow as pa
            import pyarrow.parquet as pq

            table = pa.table({k: (pa.array(v.tolist(), pa.string()) if k == "device" else v)
                              for k, v in cols.items()})
            pq.write_table(table, tmp)
        else:
            arrays = {k: (np.asarray(v.tolist(), dtype=np.str_) if k == "device" else v)
                      for k, v in cols.items()}
            with open(tmp, "wb") as fh:
                np.savez(fh, **arrays)
    return path


def _write_csv(cols: dict[str, np.ndarray], tmp: str, sep: str, compression: str | None) -> None:
    plain = not any(ch in d for d in set(cols["device"].tolist()) for ch in (sep, '"', "\n", "\r"))
    opener = OPENERS[compression] if compression else open
    n_values = sum(v.size for k, v in cols.items() if k != "device")
    with opener(tmp, "wb") as fh:
        fh.write((sep.join(cols) + "\n").encode())
        if plain and n_values <= SMALL_VALUES:  # the same bytes as Arrow's, without pyarrow
            texts = [cols["device"].tolist()] + [float_texts(v) for k, v in cols.items()
                                                 if k != "device"]
            fh.write("".join(sep.join(row) + "\n" for row in zip(*texts)).encode())
            return
        import pyarrow as pa  # loaded to write a large file, not by every reader of diffgyro.io
        import pyarrow.csv as pcsv

        table = pa.table({k: (pa.array(v.tolist(), pa.string()) if k == "device" else v)
                          for k, v in cols.items()})
        # Arrow formats float64 in the shortest round-trip form, ~10x faster than pandas
        pcsv.write_csv(table, fh, pcsv.WriteOptions(include_header=False, delimiter=sep,
                                                   quoting_style="none" if plain else "needed"))
