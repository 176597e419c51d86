"""bias_poly(k): per-axis bias as a polynomial of (centred, scaled) temperature."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import MIN_SPAN_PER_ORDER, per_axis, powers, span_problem


@register
class BiasPoly(AbstractEffect):
    """``b_i(T) = Σ_j c_ij · T_s^j``, ``T_s = (T - centre) / half_range``; k = 0 is a constant."""

    order: int = eqx.field(static=True, default=0)
    name = "bias_poly"
    constant_bias = True
    follows = "temp"
    evidence_phrase = "curves with temperature beyond the current polynomial"
    description = "per-axis bias, polynomial of temperature (k = 0: constant)"
    unit = "rad/s per T_s^j"
    order_arg = True

    @property
    def spec(self):
        return f"{self.name}({self.order})"

    def requires(self) -> frozenset[str]:
        return frozenset({"temp"}) if self.order >= 1 else frozenset()

    def param_names(self):
        return tuple(f"c{j}" for j in range(self.order + 1))

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        if self.order == 0:
            return per_axis(sig.t * 0 + 1.0)
        p = powers(sig.temp_s, 0, self.order)
        return p[:, None, :].repeat(3, axis=1)

    def range_problem(self, sig):
        return span_problem(sig, self.order)

    @property
    def min_temp_span(self) -> float:
        return MIN_SPAN_PER_ORDER * self.order

    def range_need(self) -> str:
        return f"a temperature span of at least {self.min_temp_span:g} °C"
