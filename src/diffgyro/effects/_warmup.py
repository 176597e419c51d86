"""warmup: exponential bias transient after power-on."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import duration, log_grid, per_axis, time_constant


@register
class Warmup(AbstractEffect):
    """``Δω_i = w_i · exp(−t/τ)``, t from the first sample (power-on); τ shared by the axes."""

    name = "warmup"
    follows = "early"
    evidence_phrase = "decays in the first minutes after power-on"
    description = "exponential bias transient after power-on, fitted amplitude and time constant"
    needs = frozenset({"t"})
    unit = "rad/s"

    def param_names(self):
        return ("w",)

    def nonlinear_names(self):
        return ("tau",)

    def nonlinear_init(self, sig):
        return jnp.log(jnp.clip(duration(sig) / 20.0, 5.0, 3600.0))[None]

    def nonlinear_grid(self, sig):
        return log_grid(3.0 * (sig.t[1] - sig.t[0]) + 1.0, jnp.maximum(duration(sig) / 4.0, 30.0), 12)

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return per_axis(jnp.exp(-sig.t / time_constant(theta[0])))

    def nonlinear_values(self, theta):
        return time_constant(theta)
