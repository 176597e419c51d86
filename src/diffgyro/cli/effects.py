"""``diffgyro effects``: the table of effect terms a model spec may use."""

from __future__ import annotations

import re

from rich.console import Console
from rich.table import Table

from . import app


@app.command("effects")
def effects_command() -> None:
    """List the effect terms (name, physics, data needed)."""
    from diffgyro._term_info import KINDS

    table = Table(title="diffgyro effect terms (join with '+', e.g. bias_poly(2)+gradient)")
    table.add_column("name")
    table.add_column("physics")
    table.add_column("needs")
    table.add_column("coefficients (per axis)")
    for name, kind in KINDS.items():
        args = kind.arguments
        example = {f: {"column": "NAME", "expr": "temp*az"}.get(
                   what, max(kind.default_order or 1, kind.min_order)) for f, what in args}
        shown = name
        if any(what == "column" for _, what in args):  # e.g. aux(NAME) or aux(NAME,k)
            shown = f"{name}(NAME)" + (f" or {name}(NAME,k)" if len(args) > 1 else "")
        elif any(what == "expr" for _, what in args):  # the term grammar: term(temp*az)
            shown = f"{name}(EXPR)"
        elif args and kind.default_order is None:
            shown = f"{name}(k)"
        elif args:  # an order with a default, e.g. thermal_lag = thermal_lag(1)
            shown = f"{name} or {name}(k)"
        needs = ("the signals EXPR names" if shown.endswith("(EXPR)")
                 else ", ".join(sorted(kind.requires(example))) or "—")
        coeffs = "variance (learned)" if kind.noise else ", ".join(kind.params(example))
        if any(what == "int" for _, what in args):
            coeffs = _of_order_k(kind, example)
        table.add_row(shown, kind.description, needs, coeffs)
    Console(width=160).print(table)


def _of_order_k(kind, example: dict) -> str:
    """Every coefficient of a term of order k: ``c0, c1, …, ck`` (``a1, …, ak``)."""
    low = max(kind.min_order, 1)
    first, last = kind.params(example | {"order": low}), kind.params(example | {"order": low + 1})[-1]
    return ", ".join([*first, "…", re.sub(r"[0-9]+$", "k", last)])
