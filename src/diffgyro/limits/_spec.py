"""A limits file (TOML): the bounds a production line puts on every device record.

::

    [about]                                   # optional: shown in the outputs
    name = "ACME-9 gyro, final test"

    [limits]
    status = "ok"                             # text field: this value (or one of a list)
    heldout_rms = { max = 2e-3 }              # rad/s
    "params.*.bias_poly(1).c0" = { abs = true, max = 0.5, unit = "deg/s" }
    "allan.arw" = { max = 0.014, unit = "deg/s/sqrt(Hz)" }

A key is a dotted path into the device record that ``fit --json`` (or
``diagnose --json``) prints, plus the figures :mod:`.figures` adds when a
limit asks for them (``allan.*``, ``bias_range.*``, ``bias_tempco.*``,
``temp_range.*``); ``*`` alone stands for every key at its level
(``params.*.…``: each axis), inside a key for any text (``bias_poly(*).c0``).
Dotted keys may be quoted or written as TOML tables (``[limits.allan]`` then
``arw = {…}``).
A bound is an inline table of ``min`` and/or ``max`` (numbers, in the record's
units unless ``unit`` names another), ``abs = true`` to bound the magnitude,
``optional = true`` to pass a device where the value is missing. Anything else
is refused with one line naming the file and the key.
"""

from __future__ import annotations

import math
import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..errors import DataError
from ._units import ACCEL_UNIT_HELP, UNIT_HELP, unit_scale

#: The fields a bound may hold.
BOUND_KEYS = frozenset({"min", "max", "abs", "optional", "unit"})
#: The first segment of a limit's path: the device record's fields and the figures added
#: on request. ``motion`` and ``static_only`` are written by the motion check when present.
ROOTS = frozenset({"status", "status_detail", "rms", "heldout_rms", "noise_floor", "steps",
                   "n_samples", "params", "allan", "bias_range", "bias_tempco", "temp_range", "motion",
                   "static_only", "verdict", "excess", "white_noise_rms", "noise_floor_allan",
                   "allan_slope"})
#: Figures computed for a limit only (not in every record): their roots.
COMPUTED = frozenset({"allan", "bias_range", "bias_tempco", "temp_range"})
MAX_FILE_BYTES = 1 << 20


@dataclass(frozen=True)
class Limit:
    """One limit: a dotted ``path`` with numeric bounds (in the record's units) or the text
    values a field may take (``one_of``)."""

    path: str
    min: float | None = None
    max: float | None = None
    abs: bool = False
    optional: bool = False
    one_of: tuple[str, ...] | None = None
    unit: str | None = None      # the unit the bounds were written in (converted already)
    given: dict = field(default_factory=dict, compare=False)  # the bound as written

    @property
    def parts(self) -> list[str]:
        return split_path(self.path)


@dataclass(frozen=True)
class Limits:
    """A parsed limits file: its limits in file order and its ``about`` texts."""

    file: str
    limits: tuple[Limit, ...]
    about: dict = field(default_factory=dict)

    @property
    def computed(self) -> frozenset[str]:
        """The computed figures some limit reads (:data:`COMPUTED`)."""
        return frozenset(lim.parts[0] for lim in self.limits) & COMPUTED

    @property
    def name(self) -> str:
        return str(self.about.get("name") or Path(self.file).name)


def split_path(path: str) -> list[str]:
    """``params.*.bias_poly(2).c0`` -> ``["params", "*", "bias_poly(2)", "c0"]``: the dots
    inside parentheses belong to the segment; :func:`.check.lookup` joins segments again to
    match keys that hold dots (``bias_poly(2).c0``).

    **Arguments:**

    - ``path``: a limit's key.
    """
    out, depth, cur = [], 0, ""
    for ch in path:
        if ch == "." and depth == 0:
            out.append(cur)
            cur = ""
            continue
        depth += (ch == "(") - (ch == ")")
        cur += ch
    out.append(cur)
    return out


def load(path: str | os.PathLike, channel: str = "gyro") -> Limits:
    """Read and check a limits file; :class:`~diffgyro.errors.DataError` naming the file and
    the key for anything it cannot use. ``channel``: the sensor whose records it judges (its
    bounds' units: the gyro's rates, the accelerometer's m/s², :mod:`._units`).

    **Arguments:**

    - ``path``: the limits file (TOML).
    - ``channel``: ``gyro`` or ``accel``.
    """
    name = str(path)
    p = Path(path)
    try:
        if p.stat().st_size > MAX_FILE_BYTES:
            raise DataError(f"limits file is larger than {MAX_FILE_BYTES} bytes", file=name)
        raw = p.read_bytes()
    except OSError as err:
        raise DataError(f"cannot read limits file ({err.strerror or err})", file=name) from None
    try:
        text = raw.decode("utf-8")
        doc = tomllib.loads(text)
    except UnicodeDecodeError:
        raise DataError("limits file is not UTF-8 text", file=name) from None
    except tomllib.TOMLDecodeError as err:
        key = _key_at(text, str(err))
        at = f" at key {key!r}" if key else ""
        raise DataError(f"limits file is not valid TOML{at}: {err}", file=name) from None
    return from_dict(doc, name, channel)


def _key_at(text: str, message: str) -> str | None:
    """The key (or [table]) written on the line a TOML error points at, if any."""
    m = re.search(r"\(at line (\d+), column \d+\)", message)
    if m is None:
        return None
    lines = text.splitlines()
    k = int(m.group(1)) - 1
    if not 0 <= k < len(lines):
        return None
    line = lines[k].strip()
    if line.startswith("["):
        return line.strip("[] ") or None
    if "=" in line:
        return line.split("=", 1)[0].strip().strip("\"'") or None
    return None


def fail(file: str, key: str, problem: str, hint: str | None = None) -> DataError:
    return DataError(f"limits file: key {key!r}: {problem}", file=file, hint=hint)


def from_dict(doc: dict, file: str = "<limits>", channel: str = "gyro") -> Limits:
    """The :class:`Limits` of a parsed TOML document (see the module notes), its bounds in
    the units of ``channel``'s records.

    **Arguments:**

    - ``doc``: the parsed TOML document.
    - ``file``: the name errors give.
    - ``channel``: ``gyro`` or ``accel``.
    """
    for key in doc:
        if key not in ("about", "limits"):
            raise fail(file, key, "unknown section", "a limits file holds [about] and [limits]")
    about = doc.get("about", {})
    if not isinstance(about, dict) or not all(isinstance(v, str) for v in about.values()):
        raise fail(file, "about", "must be a table of texts")
    table = doc.get("limits")
    if not isinstance(table, dict) or not table:
        raise fail(file, "limits", "missing or empty" if table is None or table == {} else
                    "must be a table", 'e.g. [limits] then heldout_rms = { max = 0.002 }')
    out: list[Limit] = []
    _walk(table, "", file, out, channel)
    return Limits(file=file, limits=tuple(out), about=dict(about))


def _walk(table: dict, prefix: str, file: str, out: list[Limit], channel: str) -> None:
    for key, val in table.items():
        path = f"{prefix}.{key}" if prefix else str(key)
        if not prefix and split_path(path)[0] not in ROOTS:
            raise fail(file, path, "unknown field", "fields: " + ", ".join(sorted(ROOTS)))
        if (isinstance(val, dict) and val and not (set(val) & BOUND_KEYS)
                and any(isinstance(v, dict) for v in val.values())):
            _walk(val, path, file, out, channel)  # a table of deeper keys ([limits.allan])
            continue
        out.append(_limit(path, val, file, channel))


def _limit(path: str, val, file: str, channel: str) -> Limit:
    if any(not s for s in split_path(path)):
        raise fail(file, path, "empty segment in the path")
    if isinstance(val, str):
        return Limit(path=path, one_of=(val,), given={"one_of": [val]})
    if isinstance(val, list):
        if not val or not all(isinstance(v, str) for v in val):
            raise fail(file, path, "a list must hold the text values the field may take")
        return Limit(path=path, one_of=tuple(val), given={"one_of": list(val)})
    if not isinstance(val, dict):
        raise fail(file, path, f"must be a bound like {{ max = 0.002 }} or a text value, "
                                f"not {type(val).__name__} {val!r}"[:200])
    unknown = sorted(set(val) - BOUND_KEYS)
    if unknown:
        raise fail(file, f"{path}.{unknown[0]}", "unknown bound field",
                    "a bound holds min, max, abs, optional, unit")
    for flag in ("abs", "optional"):
        if flag in val and not isinstance(val[flag], bool):
            raise fail(file, f"{path}.{flag}", "must be true or false")
    bounds = {}
    for side in ("min", "max"):
        if side in val:
            v = val[side]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise fail(file, f"{path}.{side}", f"must be a finite number, not {v!r}"[:120])
            bounds[side] = float(v)
    if not bounds:
        raise fail(file, path, "a bound needs min and/or max")
    if "min" in bounds and "max" in bounds and bounds["min"] > bounds["max"]:
        raise fail(file, path, f"min {bounds['min']:g} is above max {bounds['max']:g}")
    unit = val.get("unit")
    scale = 1.0
    if unit is not None:

        if not isinstance(unit, str):
            raise fail(file, f"{path}.unit", "must be text")
        scale = unit_scale(unit, channel)
        if scale is None and channel != "gyro":
            raise fail(file, f"{path}.unit", f"unit {unit!r} is not the accelerometer's (the "
                       f"{channel} channel's records are in m/s²)"[:160], ACCEL_UNIT_HELP)
        if scale is None:

            raise fail(file, f"{path}.unit", f"unknown unit {unit!r}"[:120], UNIT_HELP)
    return Limit(path=path, min=None if "min" not in bounds else bounds["min"] * scale,
                 max=None if "max" not in bounds else bounds["max"] * scale,
                 abs=bool(val.get("abs", False)), optional=bool(val.get("optional", False)),
                 unit=unit, given=dict(val))

