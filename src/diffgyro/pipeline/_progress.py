"""Progress of a streaming run: devices done, devices/s, ETA, devices failed.

On a terminal a rich progress bar (on stderr, so ``--json`` output on stdout
stays clean); elsewhere (logs, CI) one line per chunk at most every few
seconds, and a last line at the end.
"""

from __future__ import annotations

import sys
import time

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)


class RunProgress:
    """Counts devices as chunks finish; ``skipped`` devices came from an earlier run."""

    def __init__(self, total: int, skipped: int = 0, skipped_failed: int = 0,
                 enabled: bool = True, label: str = "fit", min_interval: float = 5.0):
        self.total, self.done, self.failed = total, skipped, skipped_failed
        self.new = 0
        self.start = time.monotonic()
        self.label = label
        self.enabled = enabled
        self.min_interval = min_interval
        self._last_line = 0.0
        self._bar = None
        if enabled and sys.stderr.isatty():

            self._bar = Progress(
                TextColumn(f"[bold]{label}"), BarColumn(), MofNCompleteColumn(),
                TextColumn("devices"), TextColumn("{task.fields[rate]}"),
                TextColumn("[red]{task.fields[failed]} failed"),
                TextColumn("ETA"), TimeRemainingColumn(), TimeElapsedColumn(),
                console=Console(stderr=True), transient=False)
            self._task = self._bar.add_task(label, total=total, completed=skipped,
                                            rate="", failed=skipped_failed)
            self._bar.start()
        elif enabled and skipped:
            print(f"diffgyro {label}: resuming, {skipped} of {total} devices already done",
                  file=sys.stderr)

    @property
    def rate(self) -> float:
        """Devices per second fitted by this run (devices resumed from disk not counted)."""
        elapsed = time.monotonic() - self.start
        return self.new / elapsed if elapsed > 0 else 0.0

    def update(self, n_devices: int, n_failed: int) -> None:
        self.done += n_devices
        self.new += n_devices
        self.failed += n_failed
        if not self.enabled:
            return
        if self._bar is not None:
            self._bar.update(self._task, completed=self.done, failed=self.failed,
                             rate=f"{self.rate:.1f}/s")
            return
        now = time.monotonic()
        if now - self._last_line >= self.min_interval or self.done == self.total:
            self._last_line = now
            left = self.total - self.done
            eta = f", ETA {left / self.rate:.0f} s" if self.rate > 0 and left else ""
            print(f"diffgyro {self.label}: {self.done}/{self.total} devices, "
                  f"{self.rate:.1f} devices/s, {self.failed} failed{eta}", file=sys.stderr)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None
