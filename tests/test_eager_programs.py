"""A command's cold path compiles only diffgyro's own programs: no small standalone program
for one ``jax.numpy``/``lax`` operation on host values (``jnp.asarray`` of a numpy array
is a ``stage`` program, a cast ``convert_element_type``, indexing a JAX array on the host
``dynamic_slice`` and ``squeeze``, ...). Each such program costs a cold command a trace, a
compilation and a cache write, and a warm one a cache read."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax._src import dispatch

from diffgyro.cli import main


def _eager(name: str) -> bool:
    """Whether the lowered module ``jit(name)`` is one operation run outside a program."""
    inner = name[len("jit("):-1] if name.startswith("jit(") else name
    return hasattr(jax.lax, inner) or hasattr(jnp, inner)


@pytest.fixture
def lowered():
    """The names of the modules lowered while the test runs. The cache of one-operation
    programs is emptied first, so that an operation run by an earlier test is lowered
    again (diffgyro's own programs keep theirs)."""
    names: list[str] = []

    def listen(event, duration, fun_name=None, **kw):
        if event == dispatch.JAXPR_TO_MLIR_MODULE_EVENT:
            names.append(str(fun_name))

    dispatch.xla_primitive_callable.cache_clear()
    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def test_the_rule_sees_an_eager_operation(lowered):
    """The check can fail: a cast of a JAX array outside a program is seen."""
    x = jax.device_put(np.zeros(3))
    x.astype(np.float32).block_until_ready()
    assert any(_eager(n) for n in lowered), lowered
    assert not _eager("jit(_allan_core)") and not _eager("jit(call)")


def test_simulate_and_allan_compile_no_eager_program(tmp_path, capsys, lowered):
    out = tmp_path / "static.csv"
    assert main(["simulate", "--plan", "static", "--devices", "1", "--duration", "300",
                 "--rate", "10", "--noise", "rrw=2e-5", "--out", str(out)]) == 0
    capsys.readouterr()
    assert main(["allan", str(out), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [d["device"] for d in doc["devices"]] == ["dev000"]
    eager = [n for n in lowered if _eager(n)]
    assert not eager, f"standalone one-operation programs compiled: {eager} (all: {lowered})"
