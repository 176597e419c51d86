"""thermal_lag: the bias polynomial sees temperature through a first-order lag."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals
from ._base import AbstractEffect, register
from ._common import (
    LOG_TAU_RANGE,
    MIN_SPAN_PER_ORDER,
    duration,
    log_grid,
    powers,
    span_problem,
    time_constant,
)


def first_order_lag(t: Float[Array, " n"], x: Float[Array, " n"],
                    tau: Float[Array, ""] | float) -> Float[Array, " n"]:
    """``x`` seen through ``τ·dy/dt = x − y``, starting settled (``y[0] = x[0]``).

    Exact for ``x`` held constant between samples; ``t`` may be irregular.

    **Arguments:**

    - ``t``: sample times (n,), s.
    - ``x``: the input (n,).
    - ``tau``: the time constant τ, s.
    """
    u = jnp.diff(t) / tau
    return _recursion(_lag_sequential, _lag_parallel, u, x)


def _recursion(sequential, parallel, *args):
    """One of two forms of a linear recursion over the samples, by the platform diffgyro
    computes on: a CPU runs the sequential loop fastest, while an accelerator runs each
    of its steps as a kernel launch, so there the recursion is a parallel prefix
    (log₂ n levels of the composed affine maps). The two agree to rounding. Chosen while
    tracing (``jax.lax.platform_dependent`` would trace and lower both forms, and their
    derivatives, into every program: a third more compile time on a CPU)."""
    return (sequential if jax.default_backend() == "cpu" else parallel)(*args)


def _lag_sequential(u, x):
    alpha = -jnp.expm1(-u)

    def step(y, ax):
        a, xk = ax
        y = y + a * (xk - y)
        return y, y

    _, ys = jax.lax.scan(step, x[0], (alpha, x[1:]))
    return jnp.concatenate([x[:1], ys])


def _lag_parallel(u, x):
    # y_k = e_k·y_(k−1) + a_k·x_k: the affine maps (e, c) compose as (e₂e₁, e₂c₁ + c₂)
    def compose(first, then):
        return first[0] * then[0], then[0] * first[1] + then[1]

    e = jnp.concatenate([jnp.zeros_like(x[:1]), jnp.exp(-u)])
    c = jnp.concatenate([x[:1], -jnp.expm1(-u) * x[1:]])
    return jax.lax.associative_scan(compose, (e, c))[1]


def first_order_lag_jet(t, x, log_tau):
    """:func:`first_order_lag` at ``τ = time_constant(log_tau)`` and its first and second
    derivatives in ``log_tau``, from one recursion.

    With ``u = Δt/τ`` and ``a = 1 − e^(−u)``, ``∂a = −u e^(−u)`` and ``∂²a = u e^(−u)(1 − u)``
    (zero outside the clip of log τ), and ``y_k = y_(k−1) + a_k (x_k − y_(k−1))`` gives
    ``y′_k = (1 − a_k) y′_(k−1) + a′_k (x_k − y_(k−1))`` and
    ``y″_k = (1 − a_k) y″_(k−1) − 2a′_k y′_(k−1) + a″_k (x_k − y_(k−1))``.
    """
    lo, hi = LOG_TAU_RANGE
    inside = ((log_tau >= lo) & (log_tau <= hi)).astype(x.dtype)
    rate = 1.0 / time_constant(log_tau)
    # every step's coefficients at once, and the three streams as one state vector: XLA
    # on CPU runs a loop body as small kernels at a few µs each, so the body is kept to
    # one fused update and one write (3.5× faster than three scalar states)
    u = jnp.diff(t) * rate
    e = jnp.exp(-u)
    a, a1 = -jnp.expm1(-u), -u * e * inside
    a2 = -a1 * (1.0 - u)

    ys = _recursion(_jet_sequential, _jet_parallel, a, a1, a2, e, x)
    return ys[:, 0], ys[:, 1], ys[:, 2]


def _jet_sequential(a, a1, a2, e, x):
    # the update as one expression over the state vector (no stack of three results:
    # XLA emits a concatenation element by element, 3× the code of the body)
    decays = jnp.asarray([0.0, 1.0, 1.0], x.dtype)  # y′ and y″ decay by (1 − a_k)
    last = jnp.asarray([0.0, 0.0, 1.0], x.dtype)

    def step(s, z):
        new = s - (z[0] * s) * decays + (z[3] - s[0]) * z[:3] - (2.0 * z[1] * s[1]) * last
        return new, new

    first = x[0] * jnp.asarray([1.0, 0.0, 0.0], x.dtype)
    _, ys = jax.lax.scan(step, first, jnp.stack([a, a1, a2, x[1:]], axis=-1))
    return jnp.concatenate([first[None], ys])


def _jet_parallel(a, a1, a2, e, x):
    # s_k = M_k s_(k−1) + x_k (a, a′, a″)_k, M_k = [[e, 0, 0], [p, e, 0], [q, r, e]] with
    # p = −a′, q = −a″, r = −2a′: such maps compose into the same shape, elementwise
    def compose(first, then):
        d1, p1, q1, r1, c0, c1, c2 = first
        d2, p2, q2, r2, v0, v1, v2 = then
        return (d2 * d1, p2 * d1 + d2 * p1, q2 * d1 + r2 * p1 + d2 * q1, r2 * d1 + d2 * r1,
                d2 * c0 + v0, p2 * c0 + d2 * c1 + v1, q2 * c0 + r2 * c1 + d2 * c2 + v2)

    def start(v, at_first):
        return jnp.concatenate([jnp.full_like(x[:1], at_first), v])

    out = jax.lax.associative_scan(compose, (
        start(e, 0.0), start(-a1, 0.0), start(-a2, 0.0), start(-2.0 * a1, 0.0),
        jnp.concatenate([x[:1], a * x[1:]]), start(a1 * x[1:], 0.0), start(a2 * x[1:], 0.0)))
    return jnp.stack(out[4:], axis=-1)


@register
class ThermalLag(AbstractEffect):
    """``Δω_i = Σ_{j=1..k} l_ij · (T_lag,s^j − T_s^j)``, ``T_lag`` lagged by a fitted τ.

    Added to ``bias_poly(k)`` this moves the polynomial onto the lagged
    temperature (exactly for k = 1): the die warms after the sensor that
    reports its temperature. τ is shared by the three axes.
    """

    order: int = eqx.field(static=True, default=1)
    name = "thermal_lag"
    follows = "dtemp"
    evidence_phrase = "lags the temperature (follows dT/dt with a delay)"
    family = "thermal transient"
    tau_from_dtemp_window = True
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

    def columns(self, sig: Signals, theta: Float[Array, " q"]) -> Float[Array, "n 3 p"]:
        lag = first_order_lag(sig.t, sig.temp, time_constant(theta[0]))
        lag_s = (lag - sig.norm.centre) / sig.norm.scale
        d = powers(lag_s, 1, self.order) - powers(sig.temp_s, 1, self.order)
        return d[:, None, :].repeat(3, axis=1)

    def columns_jet(self, sig: Signals, theta: Float[Array, " q"]
                    ) -> tuple[Float[Array, "n 3 p"], Float[Array, "q n 3 p"],
                               Float[Array, "q q n 3 p"]]:
        """Exact, one recursion for the lag and its two derivatives in log τ."""
        lag, d1, d2 = first_order_lag_jet(sig.t, sig.temp, theta[0])
        ls = (lag - sig.norm.centre) / sig.norm.scale
        l1, l2 = d1 / sig.norm.scale, d2 / sig.norm.scale
        j = jnp.arange(1, self.order + 1, dtype=lag.dtype)
        x = powers(ls, 1, self.order) - powers(sig.temp_s, 1, self.order)
        p0 = powers(ls, 0, self.order - 1)  # ls^(j-1)
        pm = jnp.concatenate([jnp.zeros_like(ls)[:, None], p0[:, :-1]], axis=1)  # ls^(j-2)
        d = j * p0 * l1[:, None]
        dd = j * (j - 1.0) * pm * (l1**2)[:, None] + j * p0 * l2[:, None]

        def axes(v):
            return v[:, None, :].repeat(3, axis=1)

        return axes(x), axes(d)[None], axes(dd)[None, None]

    def range_problem(self, sig):
        return span_problem(sig, 1)

    @property
    def min_temp_span(self) -> float:
        return MIN_SPAN_PER_ORDER * 1

    def range_need(self) -> str:
        return f"a temperature span of at least {self.min_temp_span:g} °C"

    def nonlinear_values(self, theta):
        return time_constant(theta)
