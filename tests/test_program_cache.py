"""Programs kept on disk between processes: the same results, no second trace, and
calls that can not be keyed or exported traced as usual."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro import _program_cache as program_cache
from diffgyro._jit import filter_jit

traces: list[str] = []


def _scaled(x, y, *, power: int, name: str):
    traces.append(name)
    return {"sum": jnp.sum(x**power) + y, "parts": (x * 2.0, [y])}


class Outside(eqx.Module):  # a class whose code the key can not cover
    k: int = eqx.field(static=True)


def _outside(x, cfg):
    traces.append("outside")
    return {"y": x * cfg.k}


def _module_result(x):
    traces.append("module")
    return Outside(k=1), x  # not a plain result: not exportable


def _cubed_sum(x):
    traces.append("cubed")
    return {"sum": jnp.sum(x**3)}


for f in (_scaled, _outside, _module_result, _cubed_sum):
    f.__module__ = "diffgyro.probe"  # as if diffgyro's own (only those are kept)
scaled, outside, module_result = (filter_jit(persistent=True)(f)
                                  for f in (_scaled, _outside, _module_result))
#: Not marked persistent, with XLA options: kept only while the command line runs.
cubed_sum = filter_jit(compiler_options={"xla_cpu_enable_fast_math": False})(_cubed_sum)


@pytest.fixture
def store(tmp_path, monkeypatch):
    folder = tmp_path / "programs"
    monkeypatch.setattr(program_cache, "_directory", lambda: folder)
    program_cache.forget()
    traces.clear()
    yield folder
    program_cache.forget()


def test_stored_program_is_not_traced_again(store):
    x, y = np.arange(5.0), np.float64(0.5)
    first = scaled(x, y, power=3, name="a")
    assert traces == ["a"] and len(list(store.glob("*.bin"))) == 1
    program_cache.forget()  # a new process: the program comes from disk
    again = scaled(x + 1.0, y, power=3, name="a")
    assert traces == ["a"]
    np.testing.assert_allclose(np.asarray(again["sum"]), np.sum((x + 1.0) ** 3) + 0.5, rtol=1e-15)
    np.testing.assert_array_equal(np.asarray(again["parts"][0]), 2.0 * (x + 1.0))
    assert float(first["sum"]) == float(np.sum(x**3) + 0.5)


def test_each_static_argument_and_shape_has_its_program(store):
    x, y = np.arange(5.0), np.float64(0.5)
    scaled(x, y, power=2, name="b")
    scaled(x, y, power=3, name="b")
    scaled(np.arange(6.0), y, power=2, name="b")
    assert len(list(store.glob("*.bin"))) == 3
    program_cache.forget()
    out = scaled(x, y, power=2, name="b")
    assert float(out["sum"]) == float(np.sum(x**2) + 0.5) and traces == ["b"] * 3


def test_unkeyable_and_unexportable_calls_are_traced_as_usual(store):
    x = np.arange(4.0)
    for _ in range(2):
        program_cache.forget()
        np.testing.assert_array_equal(np.asarray(outside(x, Outside(k=3))["y"]), 3 * x)
        cfg, y = module_result(x)
        assert cfg.k == 1 and np.array_equal(np.asarray(y), x)
    assert not list(store.glob("*.bin"))
    assert len(list(store.glob("*.fail"))) == 1  # the export is not tried again
    # the failed export's trace and the usual one; after that the marker and JAX's own
    # cache of this process: no export is tried again
    assert traces.count("module") == 2 and traces.count("outside") == 1


def test_nothing_is_kept_without_readable_sources(store, monkeypatch):
    monkeypatch.setattr(program_cache, "_source_digest", lambda: None)
    out = scaled(np.arange(3.0), np.float64(1.0), power=1, name="c")
    assert float(out["sum"]) == 4.0 and not list(store.glob("*"))


def test_every_program_is_kept_while_the_command_line_runs(store, monkeypatch):
    x = np.arange(4.0)
    cubed_sum(x)  # a library call: traced, nothing kept
    assert traces == ["cubed"] and not list(store.glob("*"))
    monkeypatch.setattr(program_cache._jax_setup, "store_programs", True)  # the command line
    program_cache.forget()
    cubed_sum(x + 1.0)  # exported (its trace) and stored, options and all
    assert traces == ["cubed"] * 2 and len(list(store.glob("*.bin"))) == 1
    program_cache.forget()  # a new process: shapes, lowering, compiling and the call
    shapes = cubed_sum.eval_shape(jax.ShapeDtypeStruct((4,), np.float64))
    assert shapes["sum"].shape == () and shapes["sum"].dtype == np.float64
    cubed_sum.compile_ahead(jax.ShapeDtypeStruct((4,), np.float64)).join()
    out = cubed_sum(x + 2.0)
    assert traces == ["cubed"] * 2  # none of them traced the function again
    assert float(out["sum"]) == float(np.sum((x + 2.0) ** 3))


def test_a_new_programs_trace_is_frozen_out_of_the_collector_only_when_asked(store, monkeypatch):
    """With ``_jax_setup.freeze_after_trace`` (the command line), the objects alive after a new
    program is traced and stored are frozen (``gc.freeze``), so that later collections do
    not walk them again; a library call freezes nothing, nor does a program read back."""
    import gc

    assert gc.get_freeze_count() == 0
    x = np.arange(3.0)
    scaled(x, 1.0, power=2, name="a")  # stored, not frozen: the flag is off
    assert len(list(store.glob("*.bin"))) == 1 and gc.get_freeze_count() == 0
    monkeypatch.setattr(program_cache._jax_setup, "freeze_after_trace", True)
    try:
        program_cache.forget()
        scaled(x, 1.0, power=2, name="a")  # read back from disk: nothing traced, nothing frozen
        assert gc.get_freeze_count() == 0
        scaled(x, 1.0, power=3, name="b")  # a new program: traced, stored, frozen
        assert len(list(store.glob("*.bin"))) == 2 and gc.get_freeze_count() > 0
    finally:
        gc.unfreeze()


def test_the_command_line_unfreezes_what_its_command_froze(tmp_path, monkeypatch):
    """A command run in-process (``diffgyro.cli.main``) runs with ``freeze_after_trace`` on
    and leaves nothing frozen behind it: its objects are collected as usual afterwards."""
    import gc

    import diffgyro.io
    from diffgyro.cli import main

    _jax_setup = program_cache._jax_setup
    seen = []
    save = diffgyro.io.save

    def saving(*a, **k):  # inside the command: freeze as a new program's export would
        seen.append(_jax_setup.freeze_after_trace)
        gc.freeze()
        return save(*a, **k)

    monkeypatch.setattr(diffgyro.io, "save", saving)
    monkeypatch.setenv("DIFFGYRO_CACHE_DIR", str(tmp_path / "cache"))
    assert main(["simulate", "--plan", "static", "--devices", "1", "--duration", "60",
                 "--rate", "10", "--out", str(tmp_path / "s.csv")]) in (0, None)
    assert seen == [True] and gc.get_freeze_count() == 0 and not _jax_setup.freeze_after_trace
