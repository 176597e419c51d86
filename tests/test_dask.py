"""Chunks as Dask tasks on a local cluster of two worker processes (loopback only),
one worker killed mid-run: the lost chunk runs again and the output is complete and
identical to the single-process run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from pipeline_data import CHUNK, MODEL, load_outputs, make_dataset

from diffgyro.pipeline import fit_dataset

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("dask")
    make_dataset(root / "data", files=(6, 6, 6), seed=21)   # 18 devices: 6 chunks
    ref = root / "ref" / "cal.json"
    fit_dataset([root / "data"], MODEL, out=ref, chunk_devices=CHUNK, progress=False)
    return root, ref


def _chunk_files(work: Path) -> int:
    d = work / "chunks"
    return len([p for p in d.iterdir() if p.name.startswith("chunk-")]) if d.is_dir() else 0


def test_worker_killed_mid_run_the_chunk_is_retried(dataset):
    """``diffgyro fit --dask ADDRESS`` in its own process (as a user runs it) against a
    cluster started here; once the first chunk is written, a busy worker is SIGKILLed."""
    root, ref = dataset
    out = root / "killed" / "cal.json"
    work = Path(str(out) + ".work")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  host="127.0.0.1", dashboard_address=None) as cluster, \
            distributed.Client(cluster) as client:
        pids = client.run(os.getpid)
        cmd = [sys.executable, "-c", "from diffgyro.cli import run; run()", "fit",
               str(root / "data"), "--model", MODEL, "--chunk-devices", str(CHUNK),
               "--out", str(out), "--dask", cluster.scheduler_address]
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                text=True)
        killed: dict = {}
        try:
            deadline = time.monotonic() + 120
            while not killed:
                assert proc.poll() is None, proc.stderr.read()
                assert time.monotonic() < deadline, "no chunk finished in time"
                if _chunk_files(work) >= 1:
                    busy = {a: keys for a, keys in client.processing().items() if keys}
                    if busy:
                        addr, keys = next(iter(busy.items()))
                        os.kill(pids[addr], signal.SIGKILL)
                        killed.update(address=addr, keys=list(keys))
                time.sleep(0.005)
            _, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert proc.returncode == 0, err
        assert "18 of 18 devices ok; 6 of 6 chunks run" in err, err
        assert all(k.startswith("diffgyro-chunk-") for k in killed["keys"])
        # the scheduler's own log: chunks on the killed worker went back to the queue
        # and then ran to completion elsewhere (the nanny's fresh process or the other one)
        story = client.run_on_scheduler(
            lambda dask_scheduler, keys=killed["keys"]: [list(t) for t in
                                                         dask_scheduler.story(*keys)])
        lost = {t[0] for t in story if t[1] in ("processing", "memory") and t[2] == "released"
                and t[4].startswith("handle-worker-cleanup")}
        assert lost, story
        for key in lost:
            moves = [(t[1], t[2], t[4]) for t in story if t[0] == key]
            at = next(i for i, m in enumerate(moves) if m[2].startswith("handle-worker-cleanup"))
            assert ("processing", "memory") in [m[:2] for m in moves[at:]], moves
    assert load_outputs(out) == load_outputs(ref)


def test_local_cluster_address_form(dataset):
    root, ref = dataset
    out = root / "local" / "cal.json"
    summary = fit_dataset([root / "data"], MODEL, out=out, chunk_devices=CHUNK,
                          dask="local:1", progress=False)
    assert summary.chunks_run == 6
    assert load_outputs(out) == load_outputs(ref)
