"""diffgyro._jit.filter_jit: arrays traced, everything else static, one trace per
static configuration and shape, results equal to the uncompiled function."""
from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro._jit import (
    collector_paused,
    filter_jit,
    map_limit,
    mapped_regions,
    release_compiled_if_crowded,
)


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
    # called inside another program it is part of that one (JAX refuses options on a
    # nested jit): the outer program's options hold, the unknown option never reaches XLA
    bad = filter_jit(compiler_options={"xla_no_such_option": True})(body)
    outer = jax.jit(lambda v: bad(v, 4)["s"] * 2.0)
    np.testing.assert_allclose(outer(x), 2.0 * a["s"], rtol=1e-12)


def test_compile_ahead_leaves_the_call_nothing_to_compile():
    compiles = []

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    def body(x, k):
        return jnp.cumsum(x * k) - jnp.sort(x)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        f = filter_jit(body)
        x = np.random.default_rng(1).normal(size=1000)
        f.compile_ahead(x, 3.0).join()
        assert len(compiles) == 1  # compiled on the other thread
        np.testing.assert_allclose(f(x, 3.0), np.cumsum(3.0 * x) - np.sort(x), rtol=1e-12)
        assert len(compiles) == 1  # the call found it compiled
        # asked again (a second caller, while or after the first compiles): the first
        # thread, nothing lowered or compiled again
        again = f.compile_ahead(x, 3.0)
        assert again is f.compile_ahead(x, 3.0)
        again.join()
        assert len(compiles) == 1
        # an argument the program cannot take: the thread swallows the error, the call raises it
        f.compile_ahead(x, "three").join()
        with pytest.raises(TypeError):
            f(x, "three")
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_compile_ahead_from_shapes_serves_a_call_with_arrays():
    """fit() compiles a program from its arguments' shapes (``jax.ShapeDtypeStruct`` on
    the device the call's arrays are on) before the arrays exist."""
    compiles = []

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            compiles.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        f = filter_jit(lambda x, y, k: jnp.cumsum(x * k) + y["b"])
        device = jax.devices()[0]
        x_np = np.linspace(0.0, 1.0, 17)
        want = np.cumsum(2.0 * x_np) + 2.0 * x_np
        x, b = (jax.device_put(x_np * i, device) for i in (1, 2))
        on = jax.sharding.SingleDeviceSharding(device)
        shape = jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=on)
        f.compile_ahead(shape, {"b": shape}, 2.0).join()
        assert len(compiles) == 1
        np.testing.assert_allclose(np.asarray(f(x, {"b": b}, 2.0)), want, rtol=1e-12)
        assert len(compiles) == 1  # the call found it compiled
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_collector_paused_restores_the_collector():
    import gc

    assert gc.isenabled()
    with collector_paused():
        assert not gc.isenabled()
    assert gc.isenabled()
    with pytest.raises(ZeroDivisionError), collector_paused():
        raise ZeroDivisionError
    assert gc.isenabled()  # restored after an error too
    gc.disable()
    try:
        with collector_paused():
            pass
        assert not gc.isenabled()  # left as the caller had it
    finally:
        gc.enable()


def test_compiled_programs_are_released_near_the_mapping_limit():
    held = mapped_regions()
    if held is None or map_limit() is None:
        pytest.skip("no /proc/self/maps or vm.max_map_count here")
    traces = []

    @filter_jit
    def f(x, k):
        traces.append(k)
        return jnp.cumsum(jnp.sin(x) * k)

    x = np.linspace(0.0, 1.0, 33)
    for k in range(4):  # a few programs, each holding its own mappings
        f(x, k)
    assert not release_compiled_if_crowded(limit=10 * map_limit())  # far from the limit: kept
    f(x, 0)
    assert traces == [0, 1, 2, 3]
    held = mapped_regions()
    assert release_compiled_if_crowded(fraction=0.5, limit=held)  # over half a limit this low
    assert mapped_regions() < held  # the programs' mappings are gone
    f(x, 0)
    assert traces == [0, 1, 2, 3, 0]  # traced and compiled again
    # within ``interval`` of the last check nothing is counted, so nothing is released
    assert release_compiled_if_crowded(fraction=0.0, limit=1)
    assert not release_compiled_if_crowded(fraction=0.0, limit=1, interval=60.0)


def test_fit_checks_the_mappings_before_it_compiles(monkeypatch):
    import diffgyro.fit as F
    from diffgyro.simulate import demo_batch

    calls = []
    monkeypatch.setattr(F, "release_compiled_if_crowded", lambda **kw: calls.append(kw) or False)
    batch, _ = demo_batch(n_devices=2, effects="bias_poly(1)", duration=600.0)
    F.fit("bias_poly(1)", batch)
    assert calls == [{"interval": 1.0}]  # at most one count of the mappings a second


@pytest.mark.parametrize("module, call", [
    ("diagnose._run", lambda m, b: m.diagnose("bias_poly(1)", b)),
    ("allan._curves", lambda m, b: m.allan_batch(b)),
    ("kalman", lambda m, b: m.fit_random_walk("bias_poly(1)", b)),
    ("sensitivity", lambda m, b: m.hac_covariance(None, b)),
    ("sensitivity", lambda m, b: m.block_bootstrap(None, b)),
])
def test_entry_points_check_the_mappings_first(monkeypatch, module, call):
    """Every entry point that compiles programs of its own checks the mappings before
    anything else (stopped there: nothing is compiled)."""
    import importlib

    from diffgyro.simulate import demo_batch

    class Checked(Exception):
        pass

    def check(**kw):
        assert kw == {"interval": 1.0}
        raise Checked

    mod = importlib.import_module(f"diffgyro.{module}")
    monkeypatch.setattr(mod, "release_compiled_if_crowded", check)
    batch, _ = demo_batch(n_devices=2, effects="bias_poly(1)", duration=60.0)
    with pytest.raises(Checked):
        call(mod, batch)



def test_every_option_is_known_to_this_xla():
    """The package's XLA options all reach the installed XLA (a misspelt one is an error
    here, not a silently dropped option)."""
    from diffgyro.internal import xla_options as opts

    for options in (opts.REASSOCIATE, opts.FAST_COMPILE, opts.LIGHT_COMPILE, opts.ONCE,
                    opts.ONE_PART):
        assert float(jax.jit(lambda v: v + 1.0, compiler_options=options)(1.0)) == 2.0
    assert not opts.REFUSED


def test_an_option_this_xla_refuses_is_dropped():
    """A program whose options name one this XLA does not know (another jaxlib renames
    or drops its flags) compiles without it, and every later program too."""
    import jax.numpy as jnp

    from diffgyro.internal import filter_jit
    from diffgyro.internal import xla_options as opts

    name = "xla_cpu_option_no_xla_has"
    opts.REFUSED.discard(name)
    twice = filter_jit(compiler_options={name: True, "xla_backend_optimization_level": 0})(
        lambda x: 2 * x)
    try:
        assert float(twice(jnp.asarray(3.0))) == 6.0
        assert name in opts.REFUSED
        assert opts.accepted({name: True, "xla_backend_optimization_level": 0}) == {
            "xla_backend_optimization_level": 0}
        assert float(twice(jnp.asarray(4.0))) == 8.0
    finally:
        opts.REFUSED.discard(name)
