"""Production scale: datasets larger than memory, resumable runs, sharding, Dask.

:func:`fit_dataset` fits (and :func:`diagnose_dataset` diagnoses) a model on every device of a Parquet dataset (a
directory of files, many devices each) in chunks of devices, writing each
chunk's results atomically to a work directory so that a killed run resumes
where it stopped, then merges them into a calibration file and a per-device
results table. See :mod:`.run` for the steps, :mod:`.dataset` for reading,
:mod:`.chunkfit` for sharding over local accelerators and :mod:`.cluster` for
Dask.
"""

from __future__ import annotations

from ._run import (
           DEFAULT_CHUNK_DEVICES,
           INVALID,
           RunSummary,
           diagnose_dataset,
           fit_chunk,
           fit_dataset,
           read_chunk,
)

__all__ = ["fit_dataset", "diagnose_dataset", "RunSummary", "DEFAULT_CHUNK_DEVICES", "INVALID",
           "fit_chunk", "read_chunk"]
