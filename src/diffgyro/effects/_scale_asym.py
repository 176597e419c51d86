"""scale_asym: the scale factor differs for positive and negative input rates."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import MIN_RATE, rate_problem


@register
class ScaleAsym(AbstractEffect):
    """``Δω_i = a_i · |Ω_i|``: scale factor ``s + a`` for Ω > 0 and ``s − a`` for Ω < 0."""

    name = "scale_asym"
    follows = "abs_rate"
    evidence_phrase = "differs between positive and negative input rates"
    family = "rate-dependent scale factor"
    description = "scale factor differs for positive and negative input rates"
    needs = frozenset({"rate"})
    unit = "1 (dimensionless)"
    rate_dependent = True

    def param_names(self):
        return ("a",)

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return jnp.abs(sig.rate)[:, :, None]

    def range_problem(self, sig):
        # Both signs of rate must be seen on every axis.
        pos = jnp.max(jnp.where(sig.mask[:, None], sig.rate, 0.0), axis=0)
        neg = jnp.max(jnp.where(sig.mask[:, None], -sig.rate, 0.0), axis=0)
        return rate_problem(sig) + jnp.sum(jnp.maximum(1e-3 - jnp.minimum(pos, neg), 0.0))

    def range_need(self) -> str:
        return f"true rates of both signs beyond {MIN_RATE:g} rad/s on every axis (rx, ry, rz)"
