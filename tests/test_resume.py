"""Kill -9 at random moments, restart: exactly the output of an uninterrupted run.

The two killed runs are the real command line in a process of its own; the run that
resumes and finishes is the same command line in the test process."""

from __future__ import annotations

import io
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

from pipeline_data import CHUNK, MODEL, load_outputs, make_dataset

from diffgyro.cli import main
from diffgyro.pipeline import fit_dataset

# The child runs the real command line; each chunk is followed by a pause so that a kill
# lands mid-run (between, or during, chunk fits and atomic writes), never after the end.
CHILD = """
import sys, time
import diffgyro.pipeline._run as run
pause = float(sys.argv[1])
fit_chunk = run.fit_chunk
def slow(*args, **kwargs):
    result = fit_chunk(*args, **kwargs)
    time.sleep(pause)
    return result
run.fit_chunk = slow
from diffgyro.cli import main
sys.exit(main(sys.argv[2:]))
"""

N_CHUNKS = 10   # 30 devices in chunks of 3


def _chunk_files(work: Path) -> int:
    d = work / "chunks"
    return len([p for p in d.iterdir() if p.name.startswith("chunk-")]) if d.is_dir() else 0


def _kill_mid_run(cmd, env, work: Path, at_least: int, rng: random.Random) -> int:
    """Start ``cmd``; once ``at_least`` chunk files exist wait a random moment, SIGKILL."""
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 90
        while _chunk_files(work) < at_least:
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "no chunk finished in time"
            time.sleep(0.005)
        time.sleep(rng.uniform(0.0, 0.5))
        os.kill(proc.pid, signal.SIGKILL)
        assert proc.wait(timeout=30) == -signal.SIGKILL
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    return _chunk_files(work)


def test_sigkill_twice_then_resume_gives_the_uninterrupted_output(tmp_path, capsys):
    data = tmp_path / "data"
    make_dataset(data, files=(10, 10, 10), seed=7)
    reference = tmp_path / "ref" / "cal.json"
    ref_json = io.StringIO()
    fit_dataset([data], MODEL, out=reference, chunk_devices=CHUNK, progress=False,
                json_stream=ref_json)

    out = tmp_path / "run" / "cal.json"
    work = Path(str(out) + ".work")
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    args = ["fit", str(data), "--model", MODEL, "--chunk-devices", str(CHUNK),
            "--out", str(out), "--json"]
    env = dict(os.environ)
    seed = random.randrange(2**32)
    rng = random.Random(seed)

    first = _kill_mid_run([sys.executable, str(script), "0.2", *args], env, work, 2, rng)
    assert 2 <= first < N_CHUNKS, f"seed {seed}: {first} chunks at the first kill"
    assert not out.exists()
    second = _kill_mid_run([sys.executable, str(script), "0.2", *args], env, work, first + 1, rng)
    assert first < second < N_CHUNKS, f"seed {seed}: {second} chunks at the second kill"

    # the resuming run is not killed: the same command line, in this process
    capsys.readouterr()
    assert main(args) == 0
    done = capsys.readouterr()
    assert f"{N_CHUNKS - second} of {N_CHUNKS} chunks run" in done.err, done.err
    # no device missing, none duplicated, identical numbers
    assert load_outputs(out) == load_outputs(reference), f"seed {seed}"
    assert json.loads(done.out) == json.loads(ref_json.getvalue())
    names = [d["device"] for d in json.loads(done.out)["devices"]]
    assert len(names) == len(set(names)) == 30
    assert not [p for p in work.rglob(".tmp-*")]
