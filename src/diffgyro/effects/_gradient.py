"""gradient: bias proportional to the rate of change of temperature."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import per_axis


@register
class Gradient(AbstractEffect):
    """``Δω_i = g_i · dT/dt`` (°C/s): a temperature gradient across the sensing element."""

    name = "gradient"
    follows = "dtemp"
    evidence_phrase = "scales with dT/dt"
    family = "thermal transient"
    description = "bias proportional to dT/dt"
    needs = frozenset({"temp"})
    unit = "rad/s per °C/s"

    def param_names(self):
        return ("g",)

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return per_axis(sig.dtemp)

    def range_problem(self, sig):
        peak = jnp.max(jnp.where(sig.mask, jnp.abs(sig.dtemp), 0.0))
        return jnp.maximum(0.05 / 60.0 - peak, 0.0)

    def range_need(self) -> str:
        return "a temperature rate |dT/dt| reaching 0.05 °C/min"
