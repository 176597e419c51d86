"""``diffgyro effects``: the table of effect terms a model spec may use."""

from __future__ import annotations

import re

from rich.console import Console
from rich.table import Table

from . import app


@app.command("effects")
def effects_command() -> None:
    """List the effect terms (name, physics, data needed)."""
    from diffgyro.effects import registry, spec_arguments

    table = Table(title="diffgyro effect terms (join with '+', e.g. bias_poly(2)+gradient)")
    table.add_column("name")
    table.add_column("physics")
    table.add_column("needs")
    table.add_column("coefficients (per axis)")
    for name, cls in registry().items():
        args = spec_arguments(cls)
        example = {f: {"column": "NAME", "expr": "temp*az"}.get(
                   kind, max(cls.default_order or 1, cls.min_order)) for f, kind in args}
        term = cls(**example)
        shown = name
        if any(kind == "column" for _, kind in args):  # e.g. aux(NAME) or aux(NAME,k)
            shown = f"{name}(NAME)" + (f" or {name}(NAME,k)" if len(args) > 1 else "")
        elif any(kind == "expr" for _, kind in args):  # the term grammar: term(temp*az)
            shown = f"{name}(EXPR)"
        elif args and cls.default_order is None:
            shown = f"{name}(k)"
        elif args:  # an order with a default, e.g. thermal_lag = thermal_lag(1)
            shown = f"{name} or {name}(k)"
        needs = ("the signals EXPR names" if shown.endswith("(EXPR)")
                 else ", ".join(sorted(term.requires())) or "—")
        coeffs = term.coefficient_summary()
        if any(kind == "int" for _, kind in args):
            coeffs = _of_order_k(cls, args)
        table.add_row(shown, cls.description, needs, coeffs)
    Console(width=160).print(table)


def _of_order_k(cls, args) -> str:
    """Every coefficient of a term of order k: ``c0, c1, …, ck`` (``a1, …, ak``)."""

    def names(k: int) -> list[str]:
        term = cls(**{f: ("NAME" if kind == "column" else k) for f, kind in args})
        return term.coefficient_summary().split(", ")

    low = max(cls.min_order, 1)
    first, last = names(low), names(low + 1)[-1]
    return ", ".join([*first, "…", re.sub(r"[0-9]+$", "k", last)])
