"""Simulated gyro rate noise with known components (the truth the tests and benchmarks check).

Each component is drawn exactly as :mod:`.components` defines it, so that the
theoretical wavelet variance is the expectation of the empirical one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def _ar1(phi, w):
    """b[k] = φ b[k−1] + w[k] by an associative scan (O(n log n) work, parallel)."""
    def comb(a, b):
        return a[0] * b[0], b[0] * a[1] + b[1]
    _, b = jax.lax.associative_scan(comb, (jnp.full_like(w, phi), w))
    return b


def simulate_noise(key, n: int, dt: float, *, arw: float = 0.0, q: float = 0.0,
                   gm: tuple[tuple[float, float], ...] = (), rrw: float = 0.0,
                   ramp: float = 0.0) -> Float[Array, " n"]:
    """One rate series of n samples (rad/s): white noise of density ``arw`` (rad/s/√Hz),
    angle quantization of RMS ``q`` (rad; uniform angle error, step q·√12), first-order
    Gauss–Markov processes ``gm = ((sigma, tau), …)`` started stationary, a rate random
    walk ``rrw`` (rad/s/√s) and a ramp ``ramp`` (rad/s²).

    **Arguments:**

    - ``key``: the JAX random key.
    - ``n``: the number of samples.
    - ``dt``: the sampling interval, s.
    - ``arw``: white-noise density, rad/s/√Hz.
    - ``q``: angle quantization RMS, rad.
    - ``gm``: Gauss–Markov processes ``((sigma, tau), …)``, rad/s and s.
    - ``rrw``: rate random walk, rad/s/√s.
    - ``ramp``: rate ramp, rad/s².
    """
    keys = jax.random.split(key, 4 + len(gm))
    y = arw / jnp.sqrt(dt) * jax.random.normal(keys[0], (n,))
    if q:
        step = q * jnp.sqrt(12.0)
        e = step * (jax.random.uniform(keys[1], (n + 1,)) - 0.5)
        y = y + jnp.diff(e) / dt
    for i, (sigma, tau) in enumerate(gm):
        phi = jnp.exp(-dt / tau)
        w = jax.random.normal(keys[4 + i], (n,)) * sigma * jnp.sqrt(-jnp.expm1(-2.0 * dt / tau))
        w = w.at[0].set(sigma * jax.random.normal(jax.random.fold_in(keys[4 + i], 1)))
        y = y + _ar1(phi, w)
    if rrw:
        y = y + jnp.cumsum(rrw * jnp.sqrt(dt) * jax.random.normal(keys[2], (n,)))
    if ramp:
        y = y + ramp * dt * jnp.arange(n)
    return y
