"""Shared test set-up: float64, the persistent compilation cache, compiled programs
released before a worker runs out of memory mappings, module fixtures built on one
xdist worker only, and shared paths."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import diffgyro
from diffgyro.jit import release_compiled_if_crowded

pytest_plugins = ["_no_skips"]  # under CI=true an undocumented skip fails the run

diffgyro.enable_x64()
diffgyro.enable_compilation_cache(os.environ.get("DIFFGYRO_CACHE_DIR"))

TESTS = Path(__file__).parent
DATA = TESTS / "data"
ROOT = TESTS.parent


def pytest_runtest_teardown(item, nextitem):
    # a worker compiles hundreds of programs; XLA's CPU JIT holds memory mappings for
    # each, and at vm.max_map_count the next compile failed and crashed the worker
    release_compiled_if_crowded()


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    # under `--dist loadgroup` (pyproject's addopts) the tests that share a module-scoped
    # fixture of their own module go to one worker, so the fixture (a diagnosed catalogue,
    # a simulated batch) is built once rather than once per worker
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None:
            continue
        module = item.nodeid.split("::")[0]
        if any(d.scope == "module" and d.baseid.split("::")[0] == module
               for defs in info.name2fixturedefs.values() for d in defs):
            item.add_marker(pytest.mark.xdist_group(module))
