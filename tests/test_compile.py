"""A new number of devices or samples within a bucket reuses the compiled fit."""

from __future__ import annotations

import numpy as np
import pytest

from diffgyro import Batch, Recording
from diffgyro import _jit as jit_module
from diffgyro.data import device_bucket
from diffgyro.fit import fit


def _recordings(n_devices, length, seed):
    rng = np.random.default_rng(seed)
    recs = []
    for k in range(n_devices):
        n = length - 13 * k
        t = np.arange(n) * 1.0
        temp = 20 + 10 * np.sin(t / 200 + k) + 0.05 * rng.normal(size=n)
        gyro = 1e-3 * (1 + 0.1 * (temp - 20))[:, None] + 1e-4 * rng.normal(size=(n, 3))
        recs.append(Recording(t=t, gyro=gyro, temp=temp, device=f"{seed}-{k}"))
    return Batch.from_recordings(recs)


@pytest.mark.parametrize("path", ["sums", "direct"])
def test_new_batch_size_in_bucket_traces_once(path):
    first = _recordings(5, 1000, seed=1)  # lengths 948..1000
    second = _recordings(7, 960, seed=2)  # lengths 882..960: the same 1024 bucket
    assert first.length == second.length == 1024
    key = path
    before = jit_module.TRACE_COUNTS[key]
    r1 = fit("bias_poly(1)", first, path=path)
    after_first = jit_module.TRACE_COUNTS[key]
    r2 = fit("bias_poly(1)", second, path=path)
    assert after_first - before <= 1  # at most one compile (none if an earlier test made it)
    assert jit_module.TRACE_COUNTS[key] == after_first, "fit compiled again for a new batch size"
    assert r1.n_devices == 5 and r2.n_devices == 7
    assert set(np.asarray(r2.status)) == {0}
    # the result of the padded run is the device's own fit
    alone = fit("bias_poly(1)", Batch.from_recordings([second.recording(6)]), path=path)
    np.testing.assert_allclose(np.asarray(alone.params.beta[0]), np.asarray(r2.params.beta[6]),
                               rtol=1e-12, atol=1e-18)


def test_device_buckets():
    assert [device_bucket(n) for n in (1, 5, 7, 8, 9, 64, 65, 100, 128, 129)] == \
        [8, 8, 8, 8, 16, 64, 128, 128, 128, 192]
    # diagnose's rule: powers of two from one device
    assert [device_bucket(n, minimum=1) for n in (1, 2, 3, 5, 64, 65)] == [1, 2, 4, 8, 64, 128]
