"""scale_poly(k): per-axis scale-factor error as a polynomial of temperature."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import MIN_RATE, MIN_SPAN_PER_ORDER, powers, rate_problem, span_problem


@register
class ScalePoly(AbstractEffect):
    """``Δω_i = Ω_i · Σ_j s_ij · T_s^j``: the scale factor drifts with temperature."""

    order: int = eqx.field(static=True, default=0)
    name = "scale_poly"
    follows = "rate"
    evidence_phrase = "grows in proportion to the input rate"
    family = "rate-dependent scale factor"
    description = "per-axis scale-factor error, polynomial of temperature"
    unit = "1 per T_s^j (dimensionless)"
    order_arg = True
    rate_dependent = True

    @property
    def spec(self):
        return f"{self.name}({self.order})"

    def requires(self) -> frozenset[str]:
        return frozenset({"rate", "temp"}) if self.order >= 1 else frozenset({"rate"})

    def param_names(self):
        return tuple(f"s{j}" for j in range(self.order + 1))

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        if self.order == 0:
            return sig.rate[:, :, None]
        return sig.rate[:, :, None] * powers(sig.temp_s, 0, self.order)[:, None, :]

    def range_problem(self, sig):
        return rate_problem(sig) + span_problem(sig, self.order)

    @property
    def min_temp_span(self) -> float:
        return MIN_SPAN_PER_ORDER * self.order

    def range_need(self) -> str:
        return (f"a true rate above {MIN_RATE:g} rad/s on every axis (rx, ry, rz) and a "
                f"temperature span of at least {self.min_temp_span:g} °C")
