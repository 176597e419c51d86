"""What a load dropped (``drop_invalid``) and the minimum-samples check."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..data import Recording
from ..errors import DataError


@dataclass(frozen=True)
class Dropped:
    """Rows skipped by ``drop_invalid`` for one device of one file."""

    file: str
    device: str
    rows: int
    first_row: int

    def message(self) -> str:
        s = "" if self.rows == 1 else "s"
        return (f"dropped {self.rows} row{s} with empty, NaN, inf or non-physical cells "
                f"in file {self.file} "
                f"device {self.device} (first: row {self.first_row})")


@dataclass
class LoadReport:
    """What :func:`load` skipped or noticed; pass one in as ``report=`` to receive it."""

    dropped: list[Dropped] = field(default_factory=list)
    # one line each, "warning: file F: ..." (e.g. a log reader's fallback)
    warnings: list[str] = field(default_factory=list)
    #: One line per file that had extra columns holding text (they are not loaded).
    ignored: list[str] = field(default_factory=list)

    @property
    def n_dropped(self) -> int:
        return sum(d.rows for d in self.dropped)

    def lines(self) -> list[str]:
        return [d.message() for d in self.dropped] + list(self.warnings) + list(self.ignored)


def check_min_samples(recording: Recording, n_needed: int, why: str = "the model") -> None:
    """Raise :class:`DataError` when ``recording`` has fewer than ``n_needed`` samples."""
    if recording.n < n_needed:
        raise DataError(
            f"{recording.n} sample{'' if recording.n == 1 else 's'}: "
            f"fewer samples than {why} needs ({n_needed})",
            file=recording.source, device=recording.device)


