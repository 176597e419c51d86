"""Pass or fail of one device record against a limits file, and the yield of a batch.

Each device record gains ``"limits": {"result": "pass"|"fail", "broken": [...]}``;
every broken limit is ``{"limit", "value", "min", "max", "by"}`` (the concrete
path, e.g. ``params.x.bias_poly(1).c0``; bounds and excess in the record's
units; ``abs`` and a ``detail`` in words where they apply). A batch gets
``{"file", "name", "yield", "passed", "failed", "rejected"}``.
"""

from __future__ import annotations

import math
from fnmatch import fnmatchcase

from ._spec import Limit, Limits, fail, split_path


def lookup(record: dict, path: str) -> list[tuple[str, object]]:
    """Every (concrete path, value) that ``path`` names in ``record``: segments are matched
    against the keys, several segments joined by dots where a key holds dots
    (``bias_poly(2).c0``); ``*`` alone matches every key of its level, and inside a segment
    any text (``bias_poly(*).c0``: any order); [] where nothing matches.

    **Arguments:**

    - ``record``: the device's record.
    - ``path``: the limit's key (``*`` matches any segment).
    """
    out: list[tuple[str, object]] = []

    def walk(node, parts: list[str], done: str) -> None:
        if not parts:
            out.append((done, node))
            return
        if not isinstance(node, dict):
            return
        for j in range(len(parts), 0, -1):  # the longest key first
            key = ".".join(parts[:j])
            if "*" in key:
                found = [k for k in node if fnmatchcase(str(k), key.replace("[", "[[]"))]
            else:
                found = [key] if key in node else []
            for k in found:
                walk(node[k], parts[j:], f"{done}.{k}" if done else str(k))
            if found:
                return

    walk(record, split_path(path), "")
    return out


def _number(v) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def _fmt(x) -> str:
    return "null" if x is None else f"{x:.4g}"


def _check_one(lim: Limit, path: str, value) -> dict | None:
    """The broken-limit entry of one value, or None when it is within the limit."""
    base = {"limit": path, "value": value if _number(value) is None else float(value),
            "min": lim.min, "max": lim.max, "by": None}
    if lim.one_of is not None:
        if isinstance(value, str) and value in lim.one_of:
            return None
        want = " or ".join(repr(v) for v in lim.one_of)
        return {**base, "min": None, "max": None, "expected": list(lim.one_of),
                "detail": f"{path} is {value!r}, not {want}"}
    v = _number(value)
    if v is None:
        missing = value is None or (isinstance(value, float) and not math.isfinite(value))
        if lim.optional and missing:
            return None
        base["value"] = None if missing else value
        what = "no value" if missing else f"not a number ({type(value).__name__})"
        return {**base, "detail": f"{path}: {what}; the limit cannot be checked"}
    x = abs(v) if lim.abs else v
    name = f"|{path}|" if lim.abs else path
    if lim.max is not None and x > lim.max:
        by = x - lim.max
        entry = {**base, "by": by, "detail": f"{name} = {_fmt(x)} above max {_fmt(lim.max)} "
                                             f"by {_fmt(by)}"}
    elif lim.min is not None and x < lim.min:
        by = lim.min - x
        entry = {**base, "by": by, "detail": f"{name} = {_fmt(x)} below min {_fmt(lim.min)} "
                                             f"by {_fmt(by)}"}
    else:
        return None
    if lim.abs:
        entry["abs"] = True
    return entry


def check(limits: Limits, record: dict) -> dict:
    """``{"result": "pass"|"fail", "broken": [...]}`` of one device record.

    **Arguments:**

    - ``limits``: the :class:`Limits`.
    - ``record``: the device's record (``fit --json``).
    """
    broken = []
    for lim in limits.limits:
        found = lookup(record, lim.path)
        if not found:
            found = [(lim.path, None)]  # a field this record lacks: no value
        for path, value in found:
            entry = _check_one(lim, path, value)
            if entry is not None:
                broken.append(entry)
    return {"result": "fail" if broken else "pass", "broken": broken}


def unmatched(limits: Limits, records: list[dict]) -> list[str]:
    """The limits that name a field no record holds (every device failed them for a missing
    value: often a misspelt path).

    **Arguments:**

    - ``limits``: the :class:`Limits`.
    - ``records``: the device records.
    """
    return [lim.path for lim in limits.limits
            if not any(lookup(r, lim.path) for r in records)]


def summary(limits: Limits, records: list[dict]) -> dict:
    """The batch's ``limits`` object from records that hold their ``limits`` result.

    **Arguments:**

    - ``limits``: the :class:`Limits`.
    - ``records``: the device records.
    """
    rejected = [r["device"] for r in records if r.get("limits", {}).get("result") != "pass"]
    n = len(records)
    return {"file": limits.file, "name": limits.name, "yield": (n - len(rejected)) / n if n else None,
            "passed": n - len(rejected), "failed": len(rejected), "rejected": rejected}


def broken_text(entry: dict) -> str:
    """One broken limit in words (the text output and the report).

    **Arguments:**

    - ``entry``: one entry of a result's ``broken`` list.
    """
    return entry.get("detail") or entry["limit"]


def check_model(limits: Limits, model) -> None:
    """A DataError naming the file and key for a ``params`` limit that names no coefficient
    of ``model`` (a typo would otherwise fail, or pass, every device).

    **Arguments:**

    - ``limits``: the :class:`Limits`.
    - ``model``: the fitted :class:`~diffgyro.model.ErrorModel`.
    """
    labels = model.param_labels()
    params = {ax: dict.fromkeys(labels[k], 0.0) for k, ax in enumerate("xyz")}
    shared = [f"{t.spec}.{n}" for t in model.terms for n in t.nonlinear_names()]
    if shared:
        params["shared"] = dict.fromkeys(shared, 0.0)
    for lim in limits.limits:
        if lim.parts[0] != "params":
            continue
        if not lookup({"params": params}, lim.path):
            names = ", ".join(sorted({lab for ax in params.values() for lab in ax}))
            raise fail(limits.file, lim.path, f"names no coefficient of model {model.spec!r}",
                        f"write params.AXIS.LABEL (AXIS x, y, z, shared or *); labels: {names}")
