"""``diffgyro effects``: the table of effect terms a model spec may use."""

from __future__ import annotations

from rich.console import Console
from rich.table import Table

from . import app


@app.command("effects")
def effects_command() -> None:
    """List the effect terms (name, physics, data needed)."""
    from diffgyro.effects import registry

    table = Table(title="diffgyro effect terms (join with '+', e.g. bias_poly(2)+gradient)")
    table.add_column("name")
    table.add_column("physics")
    table.add_column("needs")
    table.add_column("coefficients (per axis)")
    for name, cls in registry().items():
        term = cls() if not cls.order_arg else cls(order=cls.default_order or 1)
        shown = f"{name}(k)" if cls.order_arg and cls.default_order is None else name
        needs = ", ".join(sorted(term.requires())) or "—"
        coeffs = ", ".join(term.param_names()) if not cls.stochastic else "variance (learned)"
        table.add_row(shown, cls.description, needs, coeffs)
    Console(width=160).print(table)
