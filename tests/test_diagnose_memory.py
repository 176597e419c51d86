"""diagnose's memory grows with the record by a few per-sample arrays, not by its candidates.

Scores come from per-block sums (``diffgyro.diagnose._scoring``); what still grows
with the record is a few per-sample arrays of one device (its signals, the base
design and residual, one candidate's columns). Measured in one child process: the
peak RSS of a second ``diagnose`` call (the first compiles) on a short and then on a
four times longer 200 Hz record, both run by the same programs. One JAX start-up serves both; what the short record's
calls leave behind can only raise the longer one's peak, so both checks are at least
as strict as with a process each. The absolute figures at raw-log sizes live in
``benchmarks/README.md`` (the ``diagnose_native`` case).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

CHILD = r"""
import json, sys
import numpy as np
import diffgyro
diffgyro.enable_x64()
from diffgyro.data import Batch, Recording
from diffgyro.diagnose import diagnose

def hwm_kb():
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM"))

def record(n, fs=200.0, seed=3):
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    temp = np.interp(t, [0, t[-1] / 3, 2 * t[-1] / 3, t[-1]], [-10.0, 50.0, 50.0, 0.0])
    temp = temp + 0.02 * rng.normal(size=n)
    gyro = (1e-3 * (temp - 20) / 40)[:, None] + 2e-3 * rng.normal(size=(n, 3))
    return Recording(t=t, gyro=gyro, temp=temp, temp_ext=0.7 * temp + 5.0, device=f"n{n}")

res = {}
for n in map(int, sys.argv[1:]):
    batch = Batch.from_recordings([record(n)])
    diagnose("bias_poly(2)", batch)  # compiles
    open("/proc/self/clear_refs", "w").write("5")  # the peak from here on
    before = hwm_kb()
    d = diagnose("bias_poly(2)", batch).devices[0]
    res[n] = {"peak_kB": hwm_kb(), "before_kB": before, "verdict": d.verdict}
    del batch, d
print(json.dumps(res))
"""


def _peaks(sizes: list[int], env: dict) -> dict:
    """Peak RSS (kB) of the second diagnose call on a record of each of ``sizes`` samples,
    in that order, in one child process: size -> its figures."""
    try:
        proc = subprocess.run([sys.executable, "-c", CHILD, *map(str, sizes)], env=env,
                              capture_output=True, text=True, timeout=600)
    except subprocess.TimeoutExpired:
        pytest.fail("diagnose did not finish in 10 minutes")
    if proc.returncode != 0 and "clear_refs" in proc.stderr:
        pytest.skip("cannot reset the peak RSS here (/proc/self/clear_refs)")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return {int(n): r for n, r in json.loads(proc.stdout.strip().splitlines()[-1]).items()}


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="peak RSS from /proc (Linux)")
def test_memory_per_sample_is_a_few_arrays():
    """A call's peak over what was resident before it grows by less than 3 kB per sample
    (under 400 float64 values; the old diagnose, which materialised every candidate's
    columns, took about 15 kB), and the record four times longer stays within 1.5 times
    the short one's peak."""
    # both records within one size class of programs (diffgyro._xla_options.SMALL_WORK: a
    # small batch's are compiled apart), so the longer one's peak holds no other programs
    sizes = [16_384, 65_536]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(SRC)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}
    res = _peaks(sizes, env)
    small, large = res[sizes[0]], res[sizes[1]]
    # what each call adds to what was resident before it (the longer record's first call
    # compiled programs of its own shapes, resident before its second)
    growth = {n: r["peak_kB"] - r["before_kB"] for n, r in res.items()}
    per_sample = (growth[sizes[1]] - growth[sizes[0]]) * 1e3 / (sizes[1] - sizes[0])
    assert per_sample < 3000, res
    assert large["peak_kB"] < 1.5 * small["peak_kB"], res
    assert small["verdict"] == large["verdict"] == "adequate", res
