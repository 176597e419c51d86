"""thermal_lag: the bias polynomial sees temperature through a first-order lag."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._common import duration, log_grid, powers, span_problem, time_constant
from .base import AbstractEffect, register


def first_order_lag(t, x, tau):
    """``x`` seen through ``τ·dy/dt = x − y``, starting settled (``y[0] = x[0]``).

    Exact for ``x`` held constant between samples; ``t`` may be irregular.
    """
    alpha = -jnp.expm1(-jnp.diff(t) / tau)

    def step(y, ax):
        a, xk = ax
        y = y + a * (xk - y)
        return y, y

    _, ys = jax.lax.scan(step, x[0], (alpha, x[1:]))
    return jnp.concatenate([x[:1], ys])


@register
class ThermalLag(AbstractEffect):
    """``Δω_i = Σ_{j=1..k} l_ij · (T_lag,s^j − T_s^j)``, ``T_lag`` lagged by a fitted τ.

    Added to ``bias_poly(k)`` this moves the polynomial onto the lagged
    temperature (exactly for k = 1): the die warms after the sensor that
    reports its temperature. τ is shared by the three axes.
    """

    order: int = eqx.field(static=True, default=1)
    name = "thermal_lag"
    description = "the bias polynomial sees temperature through a first-order lag with fitted time constant"
    needs = frozenset({"temp"})
    unit = "rad/s per T_s^j"
    order_arg = True
    default_order = 1

    @property
    def spec(self):
        return self.name if self.order == 1 else f"{self.name}({self.order})"

    def param_names(self):
        return tuple(f"l{j}" for j in range(1, self.order + 1))

    def nonlinear_names(self):
        return ("tau",)

    def nonlinear_init(self, sig):
        return jnp.log(jnp.clip(duration(sig) / 30.0, 10.0, 3600.0))[None]

    def nonlinear_grid(self, sig):
        return log_grid(5.0 * (sig.t[1] - sig.t[0]) + 1.0, jnp.maximum(duration(sig) / 3.0, 60.0), 12)

    def columns(self, sig, theta):
        lag = first_order_lag(sig.t, sig.temp, time_constant(theta[0]))
        lag_s = (lag - sig.norm.centre) / sig.norm.scale
        d = powers(lag_s, 1, self.order) - powers(sig.temp_s, 1, self.order)
        return d[:, None, :].repeat(3, axis=1)

    def range_problem(self, sig):
        return span_problem(sig, 1)

    def nonlinear_values(self, theta):
        return time_constant(theta)
