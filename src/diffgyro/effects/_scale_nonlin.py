"""scale_nonlin: scale-factor error growing with the square of the rate."""

from __future__ import annotations

from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import MIN_RATE, rate_problem


@register
class ScaleNonlin(AbstractEffect):
    """``Δω_i = n_i · Ω_i³``: the scale factor grows by ``n_i·Ω_i²`` at high rates."""

    name = "scale_nonlin"
    follows = "rate3"
    evidence_phrase = "grows faster than the input rate (∝ rate³)"
    family = "rate-dependent scale factor"
    description = "scale-factor error growing with rate² (output term ∝ Ω³)"
    needs = frozenset({"rate"})
    unit = "(rad/s)^-2"
    rate_dependent = True

    def param_names(self):
        return ("n",)

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return (sig.rate**3)[:, :, None]

    def range_problem(self, sig):
        return rate_problem(sig)

    def range_need(self) -> str:
        return f"a true rate above {MIN_RATE:g} rad/s on every axis (rx, ry, rz)"
