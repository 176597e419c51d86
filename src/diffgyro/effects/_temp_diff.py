"""temp_diff: bias proportional to the inside–outside temperature difference."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import per_axis


@register
class TempDiff(AbstractEffect):
    """``Δω_i = d_i · (T − T_ext)``: heat flowing through the housing bends the bias."""

    name = "temp_diff"
    follows = "temp_diff"
    evidence_phrase = "follows the inside–outside temperature difference"
    family = "thermal transient"
    description = "bias proportional to (temp − temp_ext)"
    needs = frozenset({"temp", "temp_ext"})
    unit = "rad/s per °C"

    def param_names(self):
        return ("d",)

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return per_axis(sig.temp - sig.temp_ext)

    def range_problem(self, sig):
        d = jnp.where(sig.mask, sig.temp - sig.temp_ext, jnp.nan)
        return jnp.maximum(0.5 - (jnp.nanmax(d) - jnp.nanmin(d)), 0.0)

    def range_need(self) -> str:
        return "a difference temp − temp_ext that varies by at least 0.5 °C"
