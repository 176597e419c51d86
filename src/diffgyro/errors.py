"""The one exception users see for bad input, and its message format."""

from __future__ import annotations

__all__ = ["DataError", "SpecError"]


class DataError(ValueError):
    """Bad input: names the file, device, column and row where they are known.

    The command line prints ``str(err)`` (one line) and exits non-zero with no
    traceback. Fields are kept so that batch code can record the failure of
    one device and carry on with the others.
    """

    def __init__(
        self,
        problem: str,
        *,
        file: str | None = None,
        device: str | None = None,
        column: str | None = None,
        row: int | None = None,
        hint: str | None = None,
    ):
        self.problem = problem
        self.file = file
        self.device = device
        self.column = column
        self.row = row
        self.hint = hint
        super().__init__(self.message())

    def message(self) -> str:
        where = []
        if self.file is not None:
            where.append(f"file {self.file}")
        if self.device is not None:
            where.append(f"device {self.device}")
        if self.column is not None:
            where.append(f"column {self.column}")
        if self.row is not None:
            where.append(f"row {self.row}")
        text = (", ".join(where) + ": " if where else "") + self.problem
        if self.hint:
            text += f" ({self.hint})"
        return text.replace("\n", " ")

    def to_json(self) -> dict:
        """The ``--json`` error object: ``error`` (the one line, as on stderr), the bare
        ``problem``, and ``file``, ``device``, ``column``, ``row``, ``hint`` (``None``
        where not known)."""
        return {"error": self.message(), "problem": self.problem,
                "file": None if self.file is None else str(self.file),
                "device": None if self.device is None else str(self.device),
                "column": None if self.column is None else str(self.column),
                "row": None if self.row is None else int(self.row), "hint": self.hint}


class SpecError(DataError):
    """A model spec string or calibration file that cannot be understood."""
