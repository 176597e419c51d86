"""JAX's process-wide settings (float64, the persistent compilation cache) applied when JAX
starts, not before, and who hears that a program is compiled for the first time.

A command that needs no compiled program (``export``, ``effects``, an error) should not
pay JAX's import (half a second and more). :func:`when_jax_starts` gives JAX the
settings through its own environment variables (``JAX_ENABLE_X64``, ...; JAX reads them
when it is imported) while a block runs, or sets them at once if JAX is already
running, so whichever code imports JAX first gets them. No JAX here.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import os
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager

#: Float64 on: calibration needs it.
FLOAT64 = {"jax_enable_x64": True}

#: Called (no arguments) before a program not stored on disk yet is traced, compiled and
#: stored (:mod:`diffgyro._program_cache`): the command line's "compiling programs for
#: this model" notice (None: nothing). Kept here, JAX-free, so that setting it does not
#: start JAX.
on_new_program: Callable[[], None] | None = None

#: Whether every diffgyro program compiled on the CPU is kept traced on disk, not only
#: those marked ``persistent`` (:func:`diffgyro._jit.filter_jit`): the command line turns
#: this on, so that a second run loads its programs instead of tracing them again. Off
#: elsewhere: a process that runs a program once gains nothing and pays the export.
store_programs: bool = False

#: Whether the objects alive after a new program is traced and stored are moved out of the
#: cyclic collector's reach (``gc.freeze``): the trace leaves hundreds of thousands of
#: them (jaxprs, lowered modules, caches), which the next young and middle collections
#: would each walk again. The command line turns this on for one command and unfreezes
#: after it; off elsewhere (a long-lived process would keep the trace's cyclic garbage).
freeze_after_trace: bool = False

#: What a process that ends without the interpreter's teardown (the command line's exit)
#: runs first, before it joins its threads: the package's kept worker pools register
#: their shutdown here (:func:`diffgyro._jit.shutdown_pools`), since their idle threads
#: never end by themselves.
before_exit: list[Callable[[], None]] = []


def cache_dir(path: str | None = None) -> str:
    """The persistent cache's folder: ``path``, else ``$DIFFGYRO_CACHE_DIR``, else
    ``~/.cache/diffgyro/jax``."""
    return path or os.environ.get("DIFFGYRO_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "diffgyro", "jax")


def cache_settings(path: str | None = None) -> dict:
    """JAX's settings of a persistent compilation cache in :func:`cache_dir` (made if
    missing): every program is kept, the small ones too (a warm command would compile
    each again; reading one back takes milliseconds). Empty where the folder
    cannot be made (a read-only home must not stop a calibration)."""
    folder = cache_dir(path)
    try:
        os.makedirs(folder, exist_ok=True)
    except OSError:
        return {}
    return {"jax_compilation_cache_dir": folder,
            "jax_persistent_cache_min_compile_time_secs": 0.0,
            "jax_persistent_cache_min_entry_size_bytes": 0}


def _env_value(value) -> str:
    return ("1" if value else "0") if isinstance(value, bool) else str(value)


@contextmanager
def when_jax_starts(settings: Mapping[str, object]) -> Iterator[None]:
    """JAX runs with ``settings`` (config name -> value) inside the block: set now if JAX
    is imported already, else given as its environment variables, which JAX reads when
    it is imported; the environment is restored afterwards (a setting JAX read stays)."""
    if "jax" in sys.modules:
        import jax

        for name, value in settings.items():
            jax.config.update(name, value)
        yield
        return
    names = {name.upper(): _env_value(value) for name, value in settings.items()}
    saved = {name: os.environ.get(name) for name in names}
    os.environ.update(names)
    try:
        yield
    finally:
        for name, old in saved.items():
            if old is None:
                os.environ.pop(name, None)
            else:
                os.environ[name] = old


#: Called with the ``jax`` module once it is imported (:func:`when_jax_imported`).
_AFTER_IMPORT: list[Callable] = []


class _JaxImportFinder:
    """A finder that lets the normal one find ``jax`` and runs :data:`_AFTER_IMPORT` once
    that module has executed (its loader's ``exec_module`` is wrapped for this one import)."""

    busy = False

    def find_spec(self, name, path=None, target=None):
        if name != "jax" or self.busy:
            return None
        self.busy = True
        try:
            spec = importlib.util.find_spec(name)
        finally:
            self.busy = False
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        run = spec.loader.exec_module

        def exec_module(module):
            run(module)
            if self in sys.meta_path:
                sys.meta_path.remove(self)
            for callback in _AFTER_IMPORT:
                callback(module)
            _AFTER_IMPORT.clear()

        spec.loader.exec_module = exec_module
        return spec


def when_jax_imported(callback: Callable) -> None:
    """Run ``callback(jax)`` now if JAX is imported, else right after JAX's import: the
    data containers register as pytrees then, so that ``import diffgyro.data`` (and the
    readers, ``export``, ``compensate``) need no JAX."""
    if "jax" in sys.modules:
        callback(sys.modules["jax"])
        return
    _AFTER_IMPORT.append(callback)
    if not any(isinstance(f, _JaxImportFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, _JaxImportFinder())


#: The two modules of scipy whose tables of BLAS and LAPACK functions jaxlib's CPU kernels
#: read (:func:`lapack_tables_only`).
LAPACK_TABLES = ("scipy.linalg.cython_blas", "scipy.linalg.cython_lapack")


def lapack_tables_only(jax=None) -> None:
    """Load scipy's BLAS and LAPACK function tables (two compiled modules) without the
    rest of ``scipy.linalg``.

    The first program with a factorisation that a process lowers or loads (every stored
    program, on the CPU) makes jaxlib import these two modules for their function
    pointers; importing them the usual way runs ``scipy.linalg``'s package first, 0.14 s
    of CPU (its array-API layer imports ``numpy.f2py``), of which the tables take
    0.01 s. Loaded here under their full names, jaxlib's import finds them and the
    package is not run; a later ``import scipy.linalg`` runs it as usual and finds them
    loaded. Nothing where the package is loaded already, and nothing (jaxlib imports as
    usual) where scipy or its modules are not where they are expected. ``jax``: unused
    (the signature of :func:`when_jax_imported`'s callbacks)."""
    if "scipy.linalg" in sys.modules:
        return
    try:
        top = importlib.util.find_spec("scipy")
        folders = [os.path.join(p, "linalg") for p in (top.submodule_search_locations or [])]
        for name in LAPACK_TABLES:
            if name in sys.modules:
                continue
            spec = importlib.machinery.PathFinder.find_spec(name, folders)
            if spec is None or not isinstance(spec.loader, importlib.machinery.ExtensionFileLoader):
                return
            module = importlib.util.module_from_spec(spec)
            sys.modules[name] = module
            try:
                spec.loader.exec_module(module)
            except BaseException:
                del sys.modules[name]
                raise
    except Exception:  # noqa: BLE001 - jaxlib imports scipy.linalg itself
        return
