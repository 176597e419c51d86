"""A Kalman filter of the gyro bias that carries the identified noise model.

The measured rate of a static axis (or the residual of a deterministic model)
is ``y_k = b_k + v_k`` with the bias ``b`` the sum of the identified bias
processes, each a state:

* a first-order Gauss–Markov process (σ, T): ``x ← φx + w``, φ = exp(−dt/T),
  Var w = σ²(1 − φ²), started at its stationary variance σ²;
* a random walk K: ``x ← x + w``, Var w = K²·dt, started at ``p0``;

and ``v`` the white noise, variance N²/dt per sample (quantization, if
identified, adds the variance 2Q²/dt² of its rate error, treated as white).
With one random walk this is :mod:`diffgyro.kalman`'s model; with
Gauss–Markov states the filter's bias uncertainty settles at σ instead of
growing without bound, as a bias that returns to its mean does.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def state_space(components: list[dict], dt: float, p0_walk: float = 1.0):
    """(φ, q, p0, r) of the bias states (diagonal transition, noise, initial variances) and the
    white measurement variance per sample, from ``noise --json`` components (SI units).

    **Arguments:**

    - ``components``: the axis' noise components as ``noise --json`` gives them.
    - ``dt``: the sampling interval, s.
    - ``p0_walk``: the initial variance of a random-walk state.
    """
    phi, q, p0 = [], [], []
    r = 0.0
    for c in components:
        p = {k: v["value"] for k, v in c["params"].items()}
        if c["kind"] == "white":
            r += p["arw"] ** 2 / dt
        elif c["kind"] == "quantization":
            r += 2.0 * p["q"] ** 2 / dt**2
        elif c["kind"] == "gauss_markov":
            f = math.exp(-dt / p["tau"])
            phi.append(f)
            q.append(p["sigma"] ** 2 * (1.0 - f * f))
            p0.append(p["sigma"] ** 2)
        elif c["kind"] == "random_walk":
            phi.append(1.0)
            q.append(p["rrw"] ** 2 * dt)
            p0.append(p0_walk)
    if not phi:
        raise ValueError("the model holds no bias process (Gauss–Markov or random walk)")
    return jnp.asarray(phi), jnp.asarray(q), jnp.asarray(p0), jnp.asarray(r)


def bias_filter(y: Float[Array, " n"], phi, q, p0, r):
    """Filter the bias of one series: returns (bias mean, bias variance, innovation,
    innovation variance) per sample, the bias after the update with sample k.

    **Arguments:**

    - ``y``: one series (n,), rad/s.
    - ``phi``: the bias states' transition factors per sample (diagonal).
    - ``q``: their process-noise variances per sample.
    - ``p0``: their initial variances.
    - ``r``: the white measurement variance per sample.
    """
    s = phi.shape[0]

    def step(carry, yk):
        x, p = carry
        x = phi * x
        p = phi[:, None] * p * phi[None, :] + jnp.diag(q)
        f = jnp.sum(p) + r  # H = (1, …, 1)
        e = yk - jnp.sum(x)
        k = jnp.sum(p, axis=1) / f
        x = x + k * e
        p = p - jnp.outer(k, jnp.sum(p, axis=0))
        return (x, p), (jnp.sum(x), jnp.sum(p), e, f)

    init = (jnp.zeros((s,), y.dtype), jnp.diag(p0).astype(y.dtype))
    # the first sample starts from the initial state: undo its prediction step
    init = (init[0], (init[1] - jnp.diag(q)) / (phi[:, None] * phi[None, :]))
    _, (b, pb, e, f) = jax.lax.scan(step, init, y)
    return b, pb, e, f
