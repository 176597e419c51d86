"""diffgyro._xla_options: the XLA options programs set for themselves."""

from __future__ import annotations

import importlib

from diffgyro import _xla_options


def test_an_optimisation_level_in_xla_flags_is_kept(monkeypatch):
    """LIGHT_COMPILE's level 1 would override the level XLA_FLAGS sets (the suite's 0)."""
    try:
        monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false "
                                        "--xla_backend_optimization_level=0")
        assert "xla_backend_optimization_level" not in importlib.reload(_xla_options).LIGHT_COMPILE
        monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
        light = importlib.reload(_xla_options).LIGHT_COMPILE
        assert light == {"xla_cpu_use_fusion_emitters": False, "xla_backend_optimization_level": 1}
    finally:
        monkeypatch.undo()
        importlib.reload(_xla_options)


def test_without_the_verifier_xla_compiles_the_same_program(monkeypatch):
    """The HLO verifier only checks: the optimised module is the same text without it. A
    list of disabled passes in XLA_FLAGS is kept (the program's option would replace it)."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    def f(x, y):
        s = jnp.cumsum(jnp.where(x > 0, jnp.exp(-x) * y, jnp.log1p(x * x)), axis=0)
        return jax.lax.fori_loop(0, 3, lambda i, c: c * 0.5 + jnp.sin(c), s).sum(axis=1)

    x = np.linspace(-2.0, 2.0, 64).reshape(16, 4)
    base = dict(xla_backend_optimization_level=0, xla_cpu_use_fusion_emitters=False)
    texts = [jax.jit(f, compiler_options={**base, **extra}).lower(x, x).compile().as_text()
             for extra in ({}, _xla_options.NO_VERIFIER)]
    assert _xla_options.NO_VERIFIER == {"xla_disable_hlo_passes": "hlo-verifier"}
    assert texts[0] == texts[1]
    try:
        monkeypatch.setenv("XLA_FLAGS", "--xla_disable_hlo_passes=algsimp")
        assert importlib.reload(_xla_options).NO_VERIFIER == {}
    finally:
        monkeypatch.undo()
        importlib.reload(_xla_options)
