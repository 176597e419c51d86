"""Production scale: datasets larger than memory, resumable runs, sharding, Dask.

:func:`fit_dataset` fits (and :func:`diagnose_dataset` diagnoses) a model on every device of a Parquet dataset (a
directory of files, many devices each) in chunks of devices, writing each
chunk's results atomically to a work directory so that a killed run resumes
where it stopped, then merges them into a calibration file and a per-device
results table. See :mod:`._run` for the steps, :mod:`._dataset` for reading,
:mod:`._chunk` for one chunk's work, :mod:`._chunkfit` for sharding over local
accelerators, :mod:`._merge` for the outputs and :mod:`._cluster` for Dask.
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
