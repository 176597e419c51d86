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
