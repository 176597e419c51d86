"""misalignment: six off-diagonal cross-axis couplings."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AXES, AbstractEffect, register
from ._common import MIN_RATE, rate_problem

_OTHERS = ((1, 2), (0, 2), (0, 1))


@register
class Misalignment(AbstractEffect):
    """``Δω_i = Σ_{j≠i} m_ij · Ω_j``: each gyro axis also sees the other two true rates."""

    name = "misalignment"
    follows = "cross_rate"
    evidence_phrase = "follows the other axes' rates"
    family = "orientation-dependent bias"
    description = "six off-diagonal cross-axis couplings"
    needs = frozenset({"rate"})
    unit = "rad (small angle, dimensionless)"
    rate_dependent = True

    def param_names(self):
        return ("m_first", "m_second")

    def labels(self, axis):
        return tuple(f"m_{AXES[axis]}{AXES[j]}" for j in _OTHERS[axis])

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return jnp.stack([sig.rate[:, list(o)] for o in _OTHERS], axis=1)

    def range_problem(self, sig):
        return rate_problem(sig)

    def range_need(self) -> str:
        return f"a true rate above {MIN_RATE:g} rad/s on every axis (rx, ry, rz)"
