"""g_sens: bias proportional to specific force (3×3 g-sensitivity)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AXES, AbstractEffect, register


@register
class GSens(AbstractEffect):
    """``Δω_i = Σ_j G_ij · f_j``: the proof mass feels specific force ``f`` (m/s²)."""

    name = "g_sens"
    follows = "accel"
    evidence_phrase = "follows the specific force (changes with orientation)"
    family = "orientation-dependent bias"
    description = "3×3 g-sensitivity: bias proportional to specific force"
    needs = frozenset({"accel"})
    unit = "rad/s per m/s²"

    def param_names(self):
        return ("g_x", "g_y", "g_z")

    def labels(self, axis):
        return tuple(f"g_{AXES[axis]}{a}" for a in AXES)

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        return jnp.broadcast_to(sig.accel[:, None, :], (sig.accel.shape[0], 3, 3))

    def range_problem(self, sig):
        # Specific force must vary on at least two axes (otherwise it is a constant bias).
        f = jnp.where(sig.mask[:, None], sig.accel, jnp.nan)
        spread = jnp.nanmax(f, axis=0) - jnp.nanmin(f, axis=0)
        return jnp.maximum(1.0 - jnp.sort(spread)[1], 0.0)

    def range_need(self) -> str:
        return "a specific force (ax, ay, az) that varies by at least 1 m/s² on two axes"
