"""diffgyro.use_cpu_cores: one CPU device per core before JAX starts, the user's own
device count kept, no change once JAX has started (each case in a fresh process)."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

SCRIPT = """
import os, sys
import diffgyro
if sys.argv[1] == "started":
    import jax.numpy as jnp
    jnp.zeros(1)
n = diffgyro.use_cpu_cores(None if sys.argv[2] == "-" else int(sys.argv[2]))
import jax
print(n, len(jax.devices("cpu")))
"""


@pytest.mark.parametrize("when,ask,flags,want", [
    ("fresh", "3", "", 3),          # asked for 3 before JAX started
    ("started", "3", "", 1),        # too late: JAX's single device stays
    ("fresh", "3", "--xla_force_host_platform_device_count=2", 2),  # the user's count wins
    ("fresh", "-", "", None),       # default: the cores this process may use (≤ 16)
])
def test_cpu_devices(when, ask, flags, want):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    env["XLA_FLAGS"] = flags
    out = subprocess.run([sys.executable, "-c", SCRIPT, when, ask], env=env, text=True,
                         capture_output=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    got, devices = map(int, out.stdout.split())
    if want is None:
        want = min(len(os.sched_getaffinity(0)), 16)
    assert got == devices == want
