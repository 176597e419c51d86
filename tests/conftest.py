"""Shared test set-up: XLA flags for compile time, one OpenBLAS thread, float64, the
persistent compilation cache, compiled programs released before a worker runs out of memory
mappings, module fixtures built on one xdist worker only, and shared paths."""

from __future__ import annotations

import contextlib
import os

# The suite builds hundreds of XLA programs and runs most of them once or twice: compile
# them with XLA's loop emitters instead of its MLIR fusion emitters (as fit() already does
# for its costlier programs, diffgyro._xla_options.FAST_COMPILE) and without
# LLVM's optimisation passes: the same programs, about half the compile time, slower to
# run, results equal to rounding. Each program's machine code is emitted in one piece, not
# split for parallel code generation: with a worker per core the split only adds work
# (about 15 % of the compile time). Set before JAX starts its CPU client; child processes
# inherit them; the flags are part of the persistent cache's key. Users and benchmarks/
# keep XLA's defaults.
TEST_XLA_FLAGS = ("--xla_cpu_use_fusion_emitters=false", "--xla_backend_optimization_level=0",
                  "--xla_cpu_parallel_codegen_split_count=1")
os.environ["XLA_FLAGS"] = " ".join(
    [f for f in os.environ.get("XLA_FLAGS", "").split() if f not in TEST_XLA_FLAGS]
    + list(TEST_XLA_FLAGS))
# numpy's OpenBLAS splits a product (even a dot of ten thousand numbers) over a thread
# per core; with a worker per core busy, its second thread waits for a core, and the
# product takes many times longer than on one thread (synthesis's block sums, diagnose's
# evidence). One thread each. Set here for the processes started after this (xdist's
# workers, the suite's subprocesses): numpy is loaded before this file is read, so a run
# without -n keeps its threads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

import diffgyro  # noqa: E402
from diffgyro import release_compiled_if_crowded  # noqa: E402

pytest_plugins = ["_no_skips"]  # under CI=true an undocumented skip fails the run

diffgyro.enable_x64()
diffgyro.enable_compilation_cache(os.environ.get("DIFFGYRO_CACHE_DIR"))

TESTS = Path(__file__).parent
DATA = TESTS / "data"
ROOT = TESTS.parent


@contextlib.contextmanager
def registered(*classes):
    """A test's own effect or noise classes in the registry while the block runs; taken out
    afterwards, as other tests expect."""
    from diffgyro.effects import register
    from diffgyro.internal import REGISTRY

    for cls in classes:
        register(cls)
    try:
        yield
    finally:
        for cls in classes:
            REGISTRY.pop(cls.name, None)


def pytest_runtest_teardown(item, nextitem):
    # a worker compiles hundreds of programs; XLA's CPU JIT holds memory mappings for
    # each, and at vm.max_map_count the next compile failed and crashed the worker. At
    # most one count a second (as fit() and the other compiling entry points check): a
    # count reads all of /proc/self/maps (tens of ms at the tens of thousands of mappings a
    # worker holds), after each of the suite's hundreds of tests of a few milliseconds,
    # while no second of compiling comes near the half of the limit left as headroom.
    release_compiled_if_crowded(interval=1.0)


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


@pytest.fixture(autouse=True)
def _no_inherited_terminal_width(monkeypatch):
    """pytest-xdist's workers inherit COLUMNS=80, and the command line's tables follow
    COLUMNS when it is set: every test starts without it (a test that wants a width sets
    it), so that the tables are as wide with ``-n 2`` as without."""
    monkeypatch.delenv("COLUMNS", raising=False)
