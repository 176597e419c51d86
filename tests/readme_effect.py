"""A new effect added as docs/effects.md shows (``@register`` at import), loaded as a pytest
plugin (``-p readme_effect``) by tests/test_custom_effect.py to show that the registry-driven
fit, calibration-file and apply-parity tests cover it without being edited. A second term
declares its numpy form (``numpy_columns``), so apply-parity compares it too.

Not imported by the suite itself: importing it registers the terms for the whole process."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from diffgyro.effects import AbstractEffect, register


@register
class TempRateProduct(AbstractEffect):
    """Bias ∝ T_s · dT/dt: a gradient sensitivity that changes with temperature."""
    name = "temp_rate_product"
    description = "bias proportional to temperature times dT/dt"
    needs = frozenset({"temp"})
    unit = "rad/s per °C/s"

    def param_names(self):
        return ("k",)

    def columns(self, sig, theta):
        col = sig.temp_s * sig.dtemp
        return jnp.broadcast_to(col[:, None, None], (col.shape[0], 3, 1))


def temp_rate_columns(order, dev, rate, env, theta):
    """The same column in numpy, as ``diffgyro.apply`` computes it: no time constant."""
    col = env["temp_s"] * env["dtemp"]
    return np.repeat(col[:, None, None], 3, axis=1), 0


@register
class TempRateFirmware(AbstractEffect):
    """T_s · dT/dt again, with its numpy form declared for the firmware reference."""
    name = "temp_rate_firmware"
    description = "bias proportional to temperature times dT/dt (with a numpy form)"
    needs = frozenset({"temp"})
    unit = "rad/s per °C/s"
    numpy_columns = staticmethod(temp_rate_columns)

    def param_names(self):
        return ("k",)

    def columns(self, sig, theta):
        col = sig.temp_s * sig.dtemp
        return jnp.broadcast_to(col[:, None, None], (col.shape[0], 3, 1))
