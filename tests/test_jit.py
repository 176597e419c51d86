"""diffgyro.jit.filter_jit: arrays traced, everything else static, one trace per
static configuration and shape, results equal to the uncompiled function."""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

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


def test_compiler_options_reach_xla_and_eval_shape_reuses_the_trace():
    traces = []

    def body(x, n):
        traces.append(n)
        return {"s": jnp.sum(x.reshape(n, -1), axis=1), "k": jnp.zeros((), jnp.int32) + n}

    plain = filter_jit(body)
    fast = filter_jit(compiler_options={"xla_cpu_enable_fast_math": True,
                                        "xla_cpu_fast_math_honor_nans": True})(body)
    x = np.random.default_rng(0).normal(size=4096)
    a, b = plain(x, 4), fast(x, 4)
    np.testing.assert_allclose(b["s"], a["s"], rtol=1e-12)  # reassociated sums, to rounding
    assert int(b["k"]) == 4
    shapes = fast.eval_shape(x, 4)
    assert shapes["s"].shape == (4,) and shapes["k"].dtype == jnp.int32
    assert traces == [4, 4]  # eval_shape after the call: no third trace
    # an option XLA does not know is an error, so the options are not silently dropped
    bad = filter_jit(compiler_options={"xla_no_such_option": True})(body)
    with pytest.raises(Exception, match="xla_no_such_option"):
        bad(x, 4)
