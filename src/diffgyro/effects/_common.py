"""Small helpers shared by several effect terms."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..signals import Signals, masked_range

#: Temperature span (°C) needed per polynomial order before a fit is trusted.
MIN_SPAN_PER_ORDER = 1.0
#: Largest |true rate| (rad/s) below which rate-dependent terms cannot be seen.
MIN_RATE = 1e-3


def per_axis(col: Float[Array, " n"]) -> Float[Array, "n 3 1"]:
    """The same regressor on all three axes."""
    return jnp.broadcast_to(col[:, None, None], (col.shape[0], 3, 1))


def powers(x: Float[Array, "..."], lo: int, hi: int) -> Float[Array, "... k"]:
    """``x**lo, ..., x**hi`` stacked on a new last axis."""
    return jnp.stack([x**j for j in range(lo, hi + 1)], axis=-1)


def temp_span(sig: Signals) -> Float[Array, ""]:
    """Span of the valid temperature samples (°C)."""
    lo, hi = masked_range(sig.temp, sig.mask)
    return hi - lo


def span_problem(sig: Signals, order: int) -> Float[Array, ""]:
    """Positive when the temperature span is too small for a polynomial of ``order``."""
    if order < 1 or sig.temp is None:
        return jnp.zeros(())
    return jnp.maximum(MIN_SPAN_PER_ORDER * order - temp_span(sig), 0.0)


def rate_problem(sig: Signals) -> Float[Array, ""]:
    """Positive when some axis never sees a true rate above ``MIN_RATE``."""
    peak = jnp.max(jnp.where(sig.mask[:, None], jnp.abs(sig.rate), 0.0), axis=0)
    return jnp.sum(jnp.maximum(MIN_RATE - peak, 0.0))


def duration(sig: Signals) -> Float[Array, ""]:
    return jnp.max(jnp.where(sig.mask, sig.t, 0.0))


def log_grid(lo, hi, n: int) -> Float[Array, "n 1"]:
    """``n`` log-spaced values between ``lo`` and ``hi`` as solver-space (log) starts."""
    return jnp.linspace(jnp.log(lo), jnp.log(hi), n)[:, None]


#: Time constants live in log space, clipped to [1 ms, ~116 days] so that a wild
#: solver step gives a finite design (and a finite derivative) instead of NaN.
LOG_TAU_RANGE = (-6.9, 16.1)


def time_constant(log_tau: Float[Array, ""]) -> Float[Array, ""]:
    """τ (s) from its solver-space value."""
    return jnp.exp(jnp.clip(log_tau, *LOG_TAU_RANGE))
