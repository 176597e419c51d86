"""The resumable state of a streaming run: a manifest and one result file per chunk.

Layout of a work directory::

    manifest.json          what is being run (command, model, options, inputs with
                           size and mtime, chunk size), the chunk plan (chunk ->
                           device ids and where to read them) and each chunk's status
    chunks/chunk-000012.json   the results of chunk 12 (written once, atomically)
    lock                   held (flock) by the run using the directory

Every file is written to a temporary name and renamed into place, so a run
killed at any moment leaves whole files only. The chunk files are the truth:
a chunk is done exactly when its file exists and lists its planned devices;
the statuses in the manifest are a summary for people. Re-running the same
command finds the manifest, checks that the command and the inputs are the
same, and runs only the chunks without a result file.
"""

from __future__ import annotations

import errno
import json
import os
from pathlib import Path

from .._jsonio import atomic_write_bytes, dumps
from ..errors import DataError

FORMAT = "diffgyro-work"
FORMAT_VERSION = 1


def _dumps(obj) -> bytes:
    return (dumps(obj, separators=(",", ":")) + "\n").encode()


class WorkDir:
    """A run's work directory (see the module notes)."""

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.chunks = self.path / "chunks"
        self._lock_fd: int | None = None

    # -- locking: one run per work directory
    def lock(self) -> None:
        import fcntl

        self.path.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path / "lock", os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            os.close(fd)
            if err.errno in (errno.EAGAIN, errno.EACCES):
                raise DataError("another diffgyro run is using this work directory",
                                file=str(self.path),
                                hint="wait for it, or give another --work-dir") from None
            raise
        self._lock_fd = fd

    def unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # closing releases the flock
            self._lock_fd = None

    # -- manifest
    @property
    def manifest_path(self) -> Path:
        return self.path / "manifest.json"

    def read_manifest(self) -> dict | None:
        try:
            with open(self.manifest_path, encoding="utf-8") as fh:
                obj = json.load(fh)
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as err:
            raise DataError(f"cannot read the work manifest ({err})", file=str(self.manifest_path),
                            hint="use --no-resume to start again") from None
        if not isinstance(obj, dict) or obj.get("format") != FORMAT:
            raise DataError("not a diffgyro work manifest", file=str(self.manifest_path),
                            hint="give another --work-dir")
        if obj.get("format_version") != FORMAT_VERSION:
            raise DataError(f"work manifest version {obj.get('format_version')!r} is not "
                            f"{FORMAT_VERSION}", file=str(self.manifest_path),
                            hint="use --no-resume to start again")
        return obj

    def write_manifest(self, manifest: dict) -> None:
        atomic_write_bytes(self.manifest_path, _dumps(manifest))

    # -- chunks
    def chunk_path(self, i: int) -> Path:
        return self.chunks / f"chunk-{i:06d}.json"

    def read_chunk(self, i: int, devices: list[str]) -> dict | None:
        """Chunk ``i``'s results if its file is whole and lists ``devices``; else None."""
        try:
            with open(self.chunk_path(i), encoding="utf-8") as fh:
                obj = json.load(fh)
        except (FileNotFoundError, ValueError, OSError):
            return None
        if not isinstance(obj, dict) or obj.get("chunk") != i or obj.get("devices") != devices:
            return None
        recs = obj.get("records")
        if not isinstance(recs, list) or [r.get("device") for r in recs] != devices:
            return None
        return obj

    def write_chunk(self, i: int, payload: dict) -> None:
        atomic_write_bytes(self.chunk_path(i), _dumps(payload))

    # -- cleaning
    def clear(self) -> None:
        """Remove this run's state (manifest, chunk files, temporary files), nothing else."""
        if self.chunks.is_dir():
            for p in self.chunks.iterdir():
                if p.name.startswith("chunk-") or p.name.startswith(".tmp-"):
                    p.unlink()
        if self.manifest_path.exists():
            self.manifest_path.unlink()
        self.remove_temporaries()

    def remove_temporaries(self) -> None:
        """Temporary files left by a run that was killed while writing."""
        for d in (self.path, self.chunks):
            if d.is_dir():
                for p in d.iterdir():
                    if p.name.startswith(".tmp-"):
                        p.unlink(missing_ok=True)
