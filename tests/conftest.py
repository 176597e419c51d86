"""Shared test set-up: float64, the persistent compilation cache, compiled programs
released before a worker runs out of memory mappings, and shared paths."""

from __future__ import annotations

import os
from pathlib import Path

import diffgyro
from diffgyro.jit import release_compiled_if_crowded

diffgyro.enable_x64()
diffgyro.enable_compilation_cache(os.environ.get("DIFFGYRO_CACHE_DIR"))

TESTS = Path(__file__).parent
DATA = TESTS / "data"
ROOT = TESTS.parent


def pytest_runtest_teardown(item, nextitem):
    # a worker compiles hundreds of programs; XLA's CPU JIT holds memory mappings for
    # each, and at vm.max_map_count the next compile failed and crashed the worker
    release_compiled_if_crowded()
