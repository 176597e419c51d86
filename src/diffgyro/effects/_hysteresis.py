"""hysteresis: a bias offset set by whether the sensor last heated or cooled."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import per_axis


@register
class Hysteresis(AbstractEffect):
    """``Δω_i = h_i · s(t)``, ``s = +1`` after heating, ``−1`` after cooling, kept through soaks."""

    name = "hysteresis"
    follows = "heating"
    evidence_phrase = "separates heating from cooling and keeps the offset through soaks"
    family = "thermal transient"
    description = "bias offset set by whether the sensor last heated or cooled, kept through soaks"
    needs = frozenset({"temp"})
    unit = "rad/s"

    def param_names(self):
        return ("h",)

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return per_axis(sig.heating)

    def range_problem(self, sig):
        h = jnp.where(sig.mask, sig.heating, 0.0)
        both = (jnp.max(h) > 0) & (jnp.min(h) < 0)
        return jnp.where(both, 0.0, 1.0)

    def range_need(self) -> str:
        return "both heating and cooling in the recording"
