"""Chunks as Dask tasks (``--dask ADDRESS`` or ``--dask local:N``); needs ``diffgyro[dask]``.

Each chunk is one task, the chunk function the caller gives
(:func:`diffgyro.pipeline._chunk.run_chunk`): the worker
reads the chunk's rows itself (the data files must be readable at the same
paths on every worker: a shared file system or object store mount), fits
them and returns the JSON-ready results; the client writes each chunk's
result file as it arrives, so resuming works exactly as for a local run.

Workers stay warm: a worker plugin turns on float64 and the persistent
compilation cache when a worker starts, and each worker process keeps its
chunk fitter (and so its compiled functions) across the tasks it runs. A
worker that dies mid-task loses nothing: the scheduler runs the task again
on another worker (Dask's ``allowed-failures``), and a chunk's result is
written only once it is complete.
"""

from __future__ import annotations

import logging
import uuid
from collections.abc import Callable

import jax

import diffgyro

from ..errors import DataError

try:  # the optional extra: pip install diffgyro[dask]
    from distributed import WorkerPlugin as _PluginBase
except ImportError:  # pragma: no cover - exercised only without the extra
    _PluginBase = object


class WarmWorker(_PluginBase):
    """Float64 and the persistent compilation cache in every worker process."""

    name = "diffgyro-warm-worker"

    def __init__(self, cache_dir: str | None = None):
        self.cache_dir = cache_dir

    def setup(self, worker=None):

        diffgyro.enable_x64()
        diffgyro.enable_compilation_cache(self.cache_dir)


def _client(address: str):
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise DataError("--dask needs the dask extra", hint="pip install 'diffgyro[dask]'") from None
    if address.startswith("local:"):
        try:
            n = int(address.split(":", 1)[1])
        except ValueError:
            n = 0
        if n < 1:
            raise DataError(f"--dask {address!r}: write local:N with N ≥ 1 worker processes")
        cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                               host="127.0.0.1", dashboard_address=None,
                               silence_logs=logging.ERROR)
        return Client(cluster), cluster
    try:
        return Client(address, timeout="30s"), None
    except OSError as err:
        raise DataError(f"cannot reach the Dask scheduler at {address!r} ({err})",
                        hint="give tcp://HOST:PORT of a running scheduler, or local:N") from None


def run_on_dask(address: str, run_chunk: Callable[[dict, dict], dict], pending: list[dict],
                setup: dict, finished: Callable[[dict], None]) -> None:
    """Run ``run_chunk(job, setup)`` for every ``pending`` job on a Dask cluster;
    ``finished`` gets each result as it arrives. ``run_chunk`` must be importable by
    name on the workers (a module-level function)."""
    from distributed import as_completed

    client, cluster = _client(address)
    try:
        cache_dir = jax.config.jax_compilation_cache_dir
        client.register_plugin(WarmWorker(cache_dir), name=WarmWorker.name)
        token = uuid.uuid4().hex[:8]
        futures = as_completed()
        for job in pending:
            futures.add(client.submit(run_chunk, job, setup, key=f"diffgyro-chunk-{token}-"
                                      f"{job['chunk']}", pure=False, retries=1))
        for fut in futures:
            try:
                result = fut.result()
            except Exception as err:
                if type(err).__name__ == "KilledWorker":
                    raise DataError(f"Dask workers kept dying on chunk {fut.key} ({err})",
                                    hint="finished chunks are kept; run the command again "
                                         "to resume") from None
                raise
            fut.release()
            finished(result)
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
