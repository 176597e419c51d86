"""Units written in column headers (``Gyroscope X (deg/s)``, ``gyr_x[dps]``, ``t (ms)``).

A header whose last part is a unit in brackets, ``()``, ``[]`` or ``{}``, names the
unit of its column. When the rest of the header is a recognisable name of a
standard column (``Gyroscope X`` -> ``gx``, ``acc_z`` -> ``az``, ``Temperature``
-> ``temp``, ``time`` -> ``t``) the column is also mapped to it, unless the file
has that standard column already or ``--columns`` maps it. A unit option given
by the user must agree with the header (else a refusal naming the column).
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

from ..data import COLUMN_TO_SIGNAL
from ..errors import DataError
from ._units import SIGNAL_KIND, UNIT_OPTION, canonical_unit

_BRACKETED = re.compile(r"^(?P<base>.*?)\s*(?:\((?P<p>[^()]+)\)|\[(?P<b>[^\[\]]+)\]|"
                        r"\{(?P<c>[^{}]+)\})\s*$")
# the header's name, lower case without spaces, '_', '-' and '.', -> standard column
_AXIS = r"(?P<axis>[xyz])"
_NAMES: tuple[tuple[re.Pattern, str], ...] = (
    (re.compile(r"(?:gyroscope|gyro|gyr|g|omega|w|angularrate|angularvelocity|rate)" + _AXIS),
     "g"),
    (re.compile(r"(?:accelerometer|accel|acc|a|acceleration|specificforce)" + _AXIS), "a"),
    (re.compile(r"(?:r|ref|reference|refrate|tablerate)" + _AXIS), "r"),
    (re.compile(r"temp|temperature|t|imutemp|sensortemp|gyrotemp|dietemp"), "temp"),
    (re.compile(r"tempext|exttemp|chambertemp|ambienttemp"), "temp_ext"),
    (re.compile(r"t|time|timestamp|times"), "t"),
)


def split_header(name: str) -> tuple[str, str] | None:
    """``("Gyroscope X", "deg/s")`` from ``"Gyroscope X (deg/s)"``; None without a unit."""
    m = _BRACKETED.match(str(name))
    if m is None or not m.group("base").strip():
        return None
    unit = m.group("p") or m.group("b") or m.group("c")
    return m.group("base").strip(), unit.strip()


def _signal(std: str) -> str:
    return "t" if std == "t" else COLUMN_TO_SIGNAL.get(std, "")


def _standard_for(base: str, unit: str) -> tuple[str, str] | None:
    """The standard column a header base names, and the unit's canonical name, when the
    unit is one of that column's kind (``T (K)`` is a temperature, ``T (ms)`` a time)."""
    key = re.sub(r"[\s_.\-]", "", base.lower())
    for pattern, std in _NAMES:
        m = pattern.fullmatch(key)
        if m is None:
            continue
        if std in ("g", "a", "r"):
            std += m.group("axis")
        kind = SIGNAL_KIND.get(_signal(std))
        canonical = canonical_unit(kind, unit) if kind else None
        if canonical is not None:
            return std, canonical
    return None


@dataclass
class HeaderUnits:
    """What the headers of one file say: columns to map and the unit of each signal."""

    columns: dict[str, str] = field(default_factory=dict)       # standard -> file column
    units: dict[str, str] = field(default_factory=dict)         # signal -> canonical unit
    sources: dict[str, list[str]] = field(default_factory=dict)  # signal -> file columns

    def describe(self) -> str:
        """One line: each signal's unit and the headers it came from."""
        mapped = {col: std for std, col in self.columns.items()}
        parts = []
        for sig, unit in self.units.items():
            cols = ", ".join(f"{c!r}" + (f" as {mapped[c]}" if c in mapped else "")
                             for c in self.sources[sig])
            parts.append(f"{sig} in {unit} ({cols})")
        return "units from the headers: " + "; ".join(parts)


def header_units(names: Sequence[str], columns: Mapping[str, str],
                 file: str | None = None) -> HeaderUnits:
    """The units (and column names) the headers ``names`` give, ``columns`` being the
    user's mapping (it wins over a name read from a header, and its columns' headers
    still give their unit). Two columns of one signal with different units, or two
    headers naming one standard column, raise :class:`DataError`."""
    out = HeaderUnits()
    given = {col: std for std, col in columns.items()}
    present = set(names)
    for name in names:
        split = split_header(name)
        if split is None:
            continue
        base, unit = split
        if name in given:
            std = given[name]
            kind = SIGNAL_KIND.get(_signal(std))
            canonical = canonical_unit(kind, unit) if kind else None
            if canonical is None:
                continue
        else:
            found = _standard_for(base, unit)
            if found is None:
                continue
            std, canonical = found
            if std in columns or std in present:
                continue  # the user's mapping or the file's own standard column wins
            if std in out.columns:
                raise DataError(f"headers {out.columns[std]!r} and {name!r} both read as {std}",
                                file=file, column=name,
                                hint=f"choose one with --columns {std}=NAME")
            out.columns[std] = name
        sig = _signal(std)
        if sig in out.units and out.units[sig] != canonical:
            first = out.sources[sig][0]
            raise DataError(f"the headers give {sig} two units: {out.units[sig]} ({first!r}) "
                            f"and {canonical}", file=file, column=name,
                            hint="give every column of a signal the same unit")
        out.units[sig] = canonical
        out.sources.setdefault(sig, []).append(name)
    return out


def merge_units(header: HeaderUnits, given: Mapping[str, str], file: str) -> dict[str, str]:
    """The units of one file: the user's (``given``, signal -> unit) and the headers'.
    A header that contradicts a unit the user gave is a refusal naming the column."""
    given = {k: v for k, v in given.items() if v is not None}
    if "gyro" in given and "rate" not in given:
        given["rate"] = given["gyro"]
    if "temp" in given and "temp_ext" not in given:
        given["temp_ext"] = given["temp"]
    out = dict(given)
    for sig, unit in header.units.items():
        if sig in given:
            kind = SIGNAL_KIND[sig]
            theirs = canonical_unit(kind, given[sig]) if kind else None
            if theirs is not None and theirs != unit:
                opt = UNIT_OPTION.get(sig, UNIT_OPTION.get(
                    {"rate": "gyro", "temp_ext": "temp"}.get(sig, ""), f"units[{sig!r}]"))
                raise DataError(f"the header says {unit} but {opt} {given[sig]} was given",
                                file=file, column=header.sources[sig][0],
                                hint=f"drop {opt} or correct the header")
            continue
        out[sig] = unit
    return out

