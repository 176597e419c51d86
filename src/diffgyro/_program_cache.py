"""Traced programs kept on disk between processes (``filter_jit(persistent=True)``, and
every ``filter_jit`` program while the command line runs: ``_jax_setup.store_programs``).

JAX's persistent compilation cache skips XLA's compilation, but every process
still traces the Python function and lowers it to StableHLO before it can look
the program up: 0.45 s of each ``diagnose`` call for its scoring program with
every candidate. Here the lowered program itself is stored (``jax.export``,
serialised) beside that cache, keyed by everything the trace depends on:

* the function's name and a digest of diffgyro's source files (so only
  diffgyro's own functions are kept);
* the static arguments and the argument tree, pickled; an argument whose class
  or function comes from outside diffgyro and the libraries it builds on (a
  user's registered term) can not be keyed by its code, so such calls are
  traced as usual;
* every array's shape, dtype and weak type;
* the versions of JAX, jaxlib, equinox and numpy, the backend, 64-bit mode and
  matmul precision.

A later process with the same key deserialises the program (milliseconds) and
calls it (with the XLA options the function was given); its compiled form comes from
the compilation cache, and its result shapes (``eval_shape``) from its signature. A program that
can not be exported (or whose results are not plain dicts, lists and tuples of
arrays) is marked so, and traced as usual from then on.
"""
from __future__ import annotations

import functools
import gc
import hashlib
import io
import logging
import pickle
from collections.abc import Callable
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import equinox
import jax
import jaxlib
import numpy

from . import _jax_setup
from ._jsonio import atomic_write_bytes

#: Top-level modules whose classes and functions may appear in a key (by reference).
TRUSTED = frozenset({"diffgyro", "builtins", "numpy", "jax", "jaxlib", "equinox", "jaxtyping",
                     "collections", "functools", "operator", "_operator", "math", "typing",
                     "dataclasses", "enum", "copyreg", "types"})

_loaded: dict[str, Callable | None] = {}  # key -> program (None: traced as usual)
#: (function, folder, argument tree, static arguments, options, JAX's settings, shapes) ->
#: program: a call seen before in this process is not keyed (pickled and hashed) again.
_seen: dict[tuple, Callable | None] = {}


class _Untrusted(Exception):
    pass


class _KeyPickler(pickle.Pickler):
    """Pickles the static arguments; refuses classes and functions from outside
    :data:`TRUSTED` (their code is not in the key)."""

    def reducer_override(self, obj):
        if isinstance(obj, type) or callable(obj):
            module = getattr(obj, "__module__", None) or ""
            if module.split(".")[0] not in TRUSTED:
                raise _Untrusted(module)
        return NotImplemented


@functools.cache
def _source_digest() -> str | None:
    """sha256 of diffgyro's version and source files (names and contents); None where the
    sources can not be read (an install without them: nothing is kept)."""

    try:
        release = version("diffgyro")
    except PackageNotFoundError:
        release = "unknown"
    root = Path(__file__).resolve().parent
    files = sorted(root.rglob("*.py"))
    if Path(__file__).resolve() not in files:
        return None
    h = hashlib.sha256(release.encode())
    for path in files:
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _directory() -> Path | None:
    """Where programs are kept: beside JAX's compilation cache (None when it is off)."""
    base = jax.config.jax_compilation_cache_dir
    return Path(base) / "diffgyro-programs" if base else None


def _key(fun: Callable, treedef, static, dynamic) -> str | None:
    """The program's key, or None when the function or an argument can not be keyed."""
    if fun.__module__.split(".")[0] != "diffgyro" or _source_digest() is None:
        return None
    buf = io.BytesIO()
    try:
        _KeyPickler(buf, protocol=5).dump((treedef, static))
    except (_Untrusted, pickle.PicklingError, TypeError, AttributeError):
        return None
    shapes = [None if d is None else (tuple(d.shape), str(d.dtype), bool(getattr(d, "weak_type", False)))
              for d in dynamic]

    env = (jax.__version__, jaxlib.__version__, equinox.__version__, numpy.__version__,
           jax.default_backend(),
           bool(jax.config.jax_enable_x64), str(jax.config.jax_default_matmul_precision))
    h = hashlib.sha256()
    for part in (f"{fun.__module__}.{fun.__qualname__}", _source_digest(), repr(env), repr(shapes)):
        h.update(part.encode())
    h.update(buf.getvalue())
    return h.hexdigest()


def _write(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, data)


def program(fun: Callable, treedef, static, dynamic, body: Callable,
            options: dict | None = None) -> Callable | None:
    """The stored program for this call of ``fun`` (``program(dynamic)`` runs it), exported
    from ``body`` (``body(dynamic)`` calls ``fun``) and stored now if it is new; None when
    the call is to be traced as usual. ``options``: XLA's options for its compilation."""
    folder = _directory()
    if folder is None:
        return None
    opts = tuple(sorted((options or {}).items()))
    try:
        seen = (fun, folder, treedef, static, opts, bool(jax.config.jax_enable_x64),
                str(jax.config.jax_default_matmul_precision), jax.default_backend(),
                tuple(None if d is None else (tuple(d.shape), str(d.dtype),
                                              bool(getattr(d, "weak_type", False)))
                      for d in dynamic))
        return _seen[seen]
    except KeyError:
        pass
    except TypeError:  # a static argument that can not be hashed: keyed every call
        seen = None
    found = _program(fun, treedef, static, dynamic, body, options, folder)
    if seen is not None:
        _seen[seen] = found
    return found


def _program(fun, treedef, static, dynamic, body, options, folder: Path) -> Callable | None:
    key = _key(fun, treedef, static, dynamic)
    if key is None:
        return None
    if options:
        key = hashlib.sha256((key + repr(sorted(options.items()))).encode()).hexdigest()
    if key in _loaded:
        return _loaded[key]
    path, failed = folder / f"{key}.bin", folder / f"{key}.fail"
    found = None
    try:
        if path.exists():
            found = jax.jit(jax.export.deserialize(bytearray(path.read_bytes())).call,
                            compiler_options=options)
        elif not failed.exists():
            if _jax_setup.on_new_program is not None:  # the command line's notice
                _jax_setup.on_new_program()
            found = _export(fun, body, dynamic, path, failed, options)
    except Exception:  # noqa: BLE001 - a damaged or foreign file: trace as usual
        logging.getLogger("diffgyro").debug("stored program %s not used", key, exc_info=True)
        found = None
    _loaded[key] = found
    return found


def _export(fun, body, dynamic, path: Path, failed: Path, options=None) -> Callable | None:
    specs = [None if d is None else jax.ShapeDtypeStruct(d.shape, d.dtype,
                                                         weak_type=getattr(d, "weak_type", False))
             for d in dynamic]
    try:
        exported = jax.export.export(jax.jit(body))(specs)
        data = exported.serialize()
    except Exception:  # noqa: BLE001 - not exportable: remember, trace as usual
        logging.getLogger("diffgyro").debug("%s not exportable", fun.__qualname__, exc_info=True)
        _write(failed, b"")
        return None
    _write(path, bytes(data))
    if _jax_setup.freeze_after_trace:
        gc.freeze()
    return jax.jit(exported.call, compiler_options=options)


def forget() -> None:
    """Drop the programs loaded in this process (they are read again from disk)."""
    _loaded.clear()
    _seen.clear()

