"""Loading recordings for the commands: one helper every command that reads data uses.

:func:`load_from_cli` loads files from the shared options (:mod:`._options`),
prints "dropped N rows ... in file F device D" lines and the units read from
headers to stderr, and lets :class:`~diffgyro.errors.DataError` propagate (the
CLI turns it into one line on stderr and exit code 2); :func:`load_for_model`
adds the check that some device is long enough for a model; :func:`longest_static`
keeps each device's longest static interval (``--static-only``).
This module starts with ``_`` so it is not imported as a command; it imports no
JAX at module level, so ``diffgyro --help`` stays fast.
"""

from __future__ import annotations

import sys
from dataclasses import asdict
from pathlib import Path

from diffgyro.errors import DataError

#: Fewest samples per device for an Allan curve with a few τ (m = 1 needs 4 samples per
#: cluster ratio): the recordings of ``allan`` and ``export --format kalibr``, and the
#: static interval ``--static-only`` keeps.
MIN_SAMPLES = 16


def streamed_dir(path: Path) -> bool:
    """A folder of Parquet files (streamed); a rosbag2 folder is a log, read whole."""
    from diffgyro.logs import is_rosbag_dir

    return path.is_dir() and not is_rosbag_dir(path)


def units_from_cli(gyro_unit: str | None = None, acc_unit: str | None = None,
                   temp_unit: str | None = None, time_unit: str | None = None) -> dict[str, str]:
    """The ``units=`` mapping of :func:`diffgyro.io.load` from the unit options."""
    given = {"gyro": gyro_unit, "accel": acc_unit, "temp": temp_unit, "t": time_unit}
    return {sig: unit for sig, unit in given.items() if unit is not None}


def load_from_cli(
    paths: list[Path],
    columns: str | None = None,
    gyro_unit: str | None = None,
    acc_unit: str | None = None,
    temp_unit: str | None = None,
    time_unit: str | None = None,
    sampling_rate: float | None = None,
    drop_invalid: bool = False,
    *,
    min_samples: int = 2,
    batch: bool = True,
    topic: str | None = None,
    temp_topic: str | None = None,
    report=None,
    channel: str = "gyro",
):
    """Load data files from command-line options; report dropped rows, warnings and the
    units read from headers on stderr (and in ``report``, a :class:`LoadReport`, if given).

    Returns a :class:`~diffgyro.data.Batch` (or a list of recordings with
    ``batch=False``). Raises :class:`~diffgyro.errors.DataError` on bad input.
    """
    from diffgyro.data import Batch
    from diffgyro.io import LoadReport, load, parse_columns

    report = LoadReport() if report is None else report
    recordings = load(paths, parse_columns(columns),
                      units_from_cli(gyro_unit, acc_unit, temp_unit, time_unit),
                      drop_invalid=drop_invalid, sampling_rate=sampling_rate,
                      min_samples=min_samples, report=report, topic=topic,
                      temp_topic=temp_topic, channel=channel)
    for line in report.lines():
        print(f"diffgyro: {line}", file=sys.stderr)
    return Batch.from_recordings(recordings) if batch else recordings


def units_json(report) -> list[dict]:
    """The ``"units"`` field of ``--json`` output: the load's unit lines (read from
    headers, or warned), each ``{"file", "signal", "kind", "text"}``."""

    return [asdict(u) for u in report.units]


def load_for_model(model, data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                   sampling_rate, drop_invalid, *, topic=None, temp_topic=None, batch=True,
                   report=None, channel="gyro"):
    """Load data for ``model``: a DataError if every device is too short for it (``batch=False``:
    the recordings, not padded into a batch). Unit notes go to ``report`` if given."""
    from diffgyro._vocabulary import min_samples
    from diffgyro.io import check_min_samples

    recs = load_from_cli(data, columns, gyro_unit, acc_unit, temp_unit, time_unit,
                         sampling_rate, drop_invalid, topic=topic, temp_topic=temp_topic,
                         batch=False, report=report, channel=channel)
    need = min_samples(model.n_params + model.n_nonlinear)
    if all(r.n < need for r in recs):
        check_min_samples(recs[0], need, f"model {model.spec!r}")
    if not batch:
        return recs
    from diffgyro.data import Batch

    return Batch.from_recordings(recs)


def longest_static(batch, motion, min_samples: int):
    """Each device's longest run of static samples, as a batch (a DataError naming the
    device when that run is shorter than ``min_samples``)."""
    import numpy as np

    from diffgyro.data import Batch

    recs = []
    for i, rec in enumerate(batch.recordings()):
        st = np.asarray(motion.static[i])[:rec.n]
        edges = np.flatnonzero(np.diff(np.concatenate([[0], st.astype(np.int8), [0]])))
        starts, stops = edges[::2], edges[1::2]
        if not len(starts) or (stops - starts).max() < min_samples:
            raise DataError(f"no static interval of at least {min_samples} samples for "
                            "--static-only", device=batch.devices[i],
                            file=batch.sources[i] if i < len(batch.sources) else None,
                            hint="record the device at rest")
        k = int(np.argmax(stops - starts))
        recs.append(rec.slice(int(starts[k]), int(stops[k])))
    return Batch.from_recordings(recs)
