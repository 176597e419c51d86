"""Valid JSON and whole files: the one sanitiser and the one atomic write.

Every JSON document diffgyro prints or writes goes through :func:`dumps`
(strict JSON: a NaN or infinity becomes ``null``, never the ``NaN`` token
that other parsers refuse), and every file it writes goes through
:class:`AtomicFile` (a temporary file beside the target, renamed onto it:
readers see the old content or the new, never half). A record with a
``null`` number says why in its own words (``status_detail``, ``reason``).

This module sits at the bottom of the import graph: it imports only the
standard library and numpy.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["AtomicFile", "atomic_write_bytes", "atomic_write_text", "dumps", "file_mode",
           "number", "to_json_safe"]


def number(x: Any) -> float | None:
    """``float(x)``, or ``None`` when ``x`` is not a finite number."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def to_json_safe(obj: Any) -> Any:
    """A copy of ``obj`` made of JSON types: non-finite floats become ``None``,
    numpy and JAX scalars and arrays become Python numbers and lists, tuples lists,
    objects with a ``to_dict()`` method their dict, dict keys text."""
    if isinstance(obj, dict):
        return {k if isinstance(k, str) else str(k): to_json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        return to_json_safe(obj.item())
    if isinstance(obj, np.ndarray) or (hasattr(obj, "__array__") and hasattr(obj, "dtype")):
        return to_json_safe(np.asarray(obj).tolist())  # numpy and JAX arrays
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    if hasattr(obj, "to_dict") and callable(obj.to_dict):
        return to_json_safe(obj.to_dict())
    return obj


def dumps(obj: Any, **kw) -> str:
    """Strict JSON text of ``obj`` after :func:`to_json_safe` (``json.dumps`` options pass on)."""
    return json.dumps(to_json_safe(obj), allow_nan=False, **kw)


def file_mode() -> int:
    """Permissions of a new file under the current umask (``mkstemp`` makes owner-only)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


class AtomicFile:
    """A file written under a temporary name beside ``path`` and renamed onto it.

    ``mode`` is ``"w"`` (text, UTF-8), ``"wb"``, or ``None`` for a library that
    writes by file name (write to :attr:`tmp`). :meth:`commit` syncs and renames;
    :meth:`abort` removes the temporary file. As a context manager it commits on
    success and aborts on an exception.
    """

    def __init__(self, path: str | os.PathLike, mode: str | None = "w", suffix: str = ""):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, self.tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=suffix + ".tmp",
                                        dir=self.path.parent)
        os.fchmod(fd, file_mode())
        if mode is None:
            os.close(fd)
            self.fh = None
        else:
            self.fh = os.fdopen(fd, mode, **({"encoding": "utf-8"} if "b" not in mode else {}))

    def commit(self) -> Path:
        try:
            if self.fh is not None:
                self.fh.flush()
                os.fsync(self.fh.fileno())
                self.fh.close()
            os.replace(self.tmp, self.path)
        except BaseException:
            self.abort()
            raise
        return self.path

    def abort(self) -> None:
        if self.fh is not None:
            self.fh.close()
        if os.path.exists(self.tmp):
            os.unlink(self.tmp)

    def __enter__(self) -> AtomicFile:
        return self

    def __exit__(self, kind, value, tb) -> None:
        if kind is None:
            self.commit()
        else:
            self.abort()


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all."""
    with AtomicFile(path, "wb") as f:
        f.fh.write(data)
    return Path(path)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` whole or not at all.

    **Arguments:**

    - ``path``: the file to write.
    - ``text``: its content.
    """
    if not isinstance(text, str):
        raise TypeError(f"atomic_write_text needs str, not {type(text).__name__}")
    with AtomicFile(path, "w") as f:
        f.fh.write(text)
    return Path(path)
