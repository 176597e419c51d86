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


@dataclass(frozen=True)
class UnitNote:
    """One line on the units of one file: a unit read from its headers (``kind``
    ``"mapped"``) or numbers only plausible in another unit (``"warning"``); the
    numbers are kept as loaded. A refusal is a :class:`DataError` instead."""

    file: str
    signal: str   # "t", "gyro", "accel", "temp" ... ("" for a whole-file mapping line)
    kind: str     # "mapped" | "warning"
    text: str

    def message(self) -> str:
        head = "warning: " if self.kind == "warning" else ""
        return f"{head}file {self.file}: {self.text}"


@dataclass
class LoadReport:
    """What :func:`load` skipped or noticed; pass one in as ``report=`` to receive it."""

    dropped: list[Dropped] = field(default_factory=list)
    # one line each, "warning: file F: ..." (e.g. a log reader's fallback)
    warnings: list[str] = field(default_factory=list)
    #: One line per file that had extra columns holding text (they are not loaded).
    ignored: list[str] = field(default_factory=list)
    #: Units read from headers and unit warnings (:class:`UnitNote`), one line each.
    units: list[UnitNote] = field(default_factory=list)
    #: The sensor id of each device a log names one for (PX4's ``device_id``).
    device_ids: dict[str, int] = field(default_factory=dict)

    @property
    def n_dropped(self) -> int:
        return sum(d.rows for d in self.dropped)

    def lines(self) -> list[str]:
        return ([d.message() for d in self.dropped] + list(self.warnings) + list(self.ignored)
                + [u.message() for u in self.units])


def check_min_samples(recording: Recording, n_needed: int, why: str = "the model") -> None:
    """Raise :class:`DataError` when ``recording`` has fewer than ``n_needed`` samples.

    **Arguments:**

    - ``recording``: the recording.
    - ``n_needed``: the fewest samples needed.
    - ``why``: what needs them, as the message says it.
    """
    if recording.n < n_needed:
        raise DataError(
            f"{recording.n} sample{'' if recording.n == 1 else 's'}: "
            f"fewer samples than {why} needs ({n_needed})",
            file=recording.source, device=recording.device)


