"""diffgyro.jit.filter_jit: arrays traced, everything else static, one trace per
static configuration and shape, results equal to the uncompiled function."""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from diffgyro.jit import filter_jit


class Poly(eqx.Module):
    coef: jax.Array
    degree: int = eqx.field(static=True)

    def __call__(self, x):
        return sum(self.coef[k] * x**k for k in range(self.degree + 1))


def test_arrays_traced_and_the_rest_static():
    traces = []

    @filter_jit
    def f(model, x, scale, *, name, offset=None):
        traces.append(name)
        y = model(x) * scale
        return y if offset is None else y + offset

    x = np.linspace(-1, 1, 7)
    m = Poly(jnp.array([1.0, 2.0, 3.0]), 2)
    want = (1 + 2 * x + 3 * x**2) * 2.0
    np.testing.assert_allclose(f(m, x, 2.0, name="a"), want, rtol=1e-14)
    # new array values (numpy or JAX), same shapes: no new trace
    np.testing.assert_allclose(f(Poly(jnp.array([0.0, 0.0, 1.0]), 2), jnp.asarray(x), 2.0,
                                 name="a"), 2 * x**2, rtol=1e-14)
    assert traces == ["a"]
    # a Python scalar or a keyword is static: a new value is a new trace
    f(m, x, 3.0, name="a")
    f(m, x, 3.0, name="b")
    assert traces == ["a", "a", "b"]
    # an optional array given, and a new shape, trace again
    np.testing.assert_allclose(f(m, x, 2.0, name="b", offset=np.ones(7)), want + 1, rtol=1e-14)
    f(m, x[:3], 2.0, name="b")
    assert len(traces) == 5


def test_returns_jax_arrays_and_lowers():
    @filter_jit
    def f(x, k):
        return jnp.cumsum(x) * k

    out = f(np.arange(4.0), 2)
    assert isinstance(out, jax.Array)
    np.testing.assert_array_equal(np.asarray(out), [0.0, 2.0, 6.0, 12.0])
    assert "func.func" in f.lower(np.arange(4.0), 2).as_text()  # the same arguments lower



SCRIPT_TWO_DEVICES = """
import json, sys, numpy as np, diffgyro
diffgyro.enable_x64()
import jax, jax.numpy as jnp
if sys.argv[1] != "-":
    diffgyro.enable_compilation_cache(sys.argv[1])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
from diffgyro import jit as J
@J.filter_jit
def f(x, k, *, scale):
    y = jnp.pad(jnp.sin(x), (3, 5)) * k
    return jnp.concatenate([jnp.cumsum(y), y[::-1]]) * scale
dev = jax.local_devices()
x = np.linspace(0.0, 3.0, 257)
out = [f(jax.device_put(x, d), jnp.asarray(2.0), scale=3) for d in (dev[0], dev[1], dev[1])]
f(jax.device_put(x[:5], dev[1]), 2.0, scale=3)  # a new shape compiles again
y = np.pad(np.sin(x), (3, 5)) * 2.0
want = np.concatenate([np.cumsum(y), y[::-1]]) * 3
print(json.dumps({"devices": [next(iter(o.devices())).id for o in out],
                  "err": max(float(np.max(np.abs(np.asarray(o) - want))) for o in out)
                         / float(np.max(np.abs(want))),
                  "same": all(np.array_equal(np.asarray(o), np.asarray(out[0])) for o in out),
                  "events": {k[1]: v for k, v in J.EVENTS.items()}}))
"""


def test_compiled_once_for_all_cpu_devices(tmp_path):
    """With two CPU devices a fresh executable of the first device is loaded on the
    second (no second compile); one from the persistent cache is not (it serializes
    without its kernels), each device then takes its own. Results equal, each on its
    own device."""
    import json
    import os
    import subprocess
    import sys

    env = dict(os.environ, JAX_PLATFORMS="cpu",
               XLA_FLAGS="--xla_force_host_platform_device_count=2")

    def run(cache):
        proc = subprocess.run([sys.executable, "-c", SCRIPT_TWO_DEVICES, cache], env=env,
                              capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr[-3000:]
        out = json.loads(proc.stdout.strip().splitlines()[-1])
        assert out["devices"] == [0, 1, 1]
        assert out["err"] < 1e-13 and out["same"]
        return out["events"]

    assert run("-") == {"compile": 2, "copy": 1}
    cache = str(tmp_path / "cache")
    assert run(cache) == {"compile": 2, "copy": 1}  # fresh compiles, stored
    assert run(cache) == {"compile": 3}  # loaded from the cache on every device
