"""aux(NAME, k): bias as a polynomial of an extra logged column (supply voltage, ...)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..data import aux_key
from ..signals import Signals, masked_range
from ._base import AbstractEffect, register
from ._common import powers

#: Span of the centred, scaled column (about [-1, 1]) below which the term is not trusted.
MIN_SCALED_SPAN = 1e-6


@register
class Aux(AbstractEffect):
    """``Δω_i = Σ_{j=1..k} a_ij · x_s^j``, ``x_s = (x − centre) / half_range`` of extra column
    ``x``; no constant (that is the bias term's)."""

    column: str = eqx.field(static=True, default="")
    order: int = eqx.field(static=True, default=1)
    name = "aux"
    description = "bias ∝ an extra logged column NAME (polynomial of order k, default 1)"
    unit = "rad/s per x_s^j"
    arguments = (("column", "column"), ("order", "int"))
    default_order = 1
    min_order = 1
    follows = "aux:NAME"  # the instance's column: followed_signal()

    @property
    def spec(self):
        return f"aux({self.column})" if self.order == 1 else f"aux({self.column},{self.order})"

    def requires(self) -> frozenset[str]:
        return frozenset({aux_key(self.column)})

    def followed_signal(self):
        return f"aux:{self.column}"

    def param_names(self):
        return tuple(f"a{j}" for j in range(1, self.order + 1))

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        p = powers(sig.aux[self.column], 1, self.order)
        return jnp.broadcast_to(p[:, None, :], (p.shape[0], 3, self.order))

    def range_problem(self, sig):
        lo, hi = masked_range(sig.aux[self.column], sig.mask)
        return jnp.maximum(MIN_SCALED_SPAN - (hi - lo), 0.0)

    def range_need(self) -> str:
        return f"a column {self.column!r} that varies (it is constant in this recording)"
