"""The components of a gyro's stochastic model and their theoretical Allan / Haar wavelet variance.

A rate series ``y`` sampled every ``dt`` seconds is the sum of independent
discrete-time processes (SI units; ``τ = m·dt`` with ``m`` whole samples):

=================  ============================  ==================================================
kind               parameter                     Allan variance σ²(τ) (exact for the sampled model)
=================  ============================  ==================================================
``white``          N, rad/s/√Hz (ARW)            N²/τ            (iid, variance N²/dt per sample)
``quantization``   Q, rad                        3Q²/τ²          (iid angle error of variance Q²)
``gauss_markov``   σ rad/s, T s                  AR(1) formula below, φ = exp(−dt/T)
``random_walk``    K, rad/s/√s (RRW)             K²τ/3 + K²dt²/(6τ)  (steps of variance K²·dt)
``rate_ramp``      R, rad/s²                     R²τ²/2          (the drift R·t)
=================  ============================  ==================================================

The Haar wavelet variance at the same scale is half the Allan variance
(``ν²(τ) = σ²(τ)/2``, the MODWT Haar coefficient being half the difference of
two adjacent means of length m). The Gauss–Markov process is the first-order
autoregression ``b[k] = φ b[k−1] + w[k]`` of stationary variance σ², the exact
sampling of a continuous first-order Markov process of correlation time T; its
Allan variance follows from the autocovariance σ²φ^|k| as the variance of a
mean of m samples minus the covariance of two adjacent means::

    σ²(τ) = σ²/m² · [ m + 2φ(m(1−φ) − (1−φ^m))/(1−φ)² − φ(1−φ^m)²/(1−φ)² ]

(``T ≫ dt``: the IEEE Std 952 continuous form ``σ²T/τ·(2 − T/τ(3 − 4e^{−τ/T} + e^{−2τ/T}))``).

Parameters live in one vector of unconstrained logarithms of powers (the
:data:`LAYOUT`), so every structure of the catalogue is the same function with
some components switched off by a mask: one compiled program serves them all.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

#: Parameter vector: log N², log Q², log σ₁², log T₁, log σ₂², log T₂, log K², log R².
LAYOUT = ("white", "quantization", "gm1_var", "gm1_tau", "gm2_var", "gm2_tau", "random_walk",
          "rate_ramp")
N_PARAMS = len(LAYOUT)
#: Indices of the powers whose Allan variance is linear in them (everything but the two T).
POWER_INDEX = (0, 1, 2, 4, 6, 7)
TAU_INDEX = (3, 5)


def avar_white(n2, tau):
    """White rate noise of density N (N² in rad²/s): σ²(τ) = N²/τ."""
    return n2 / tau


def avar_quantization(q2, tau):
    """Angle quantization of RMS Q (Q² in rad²): σ²(τ) = 3Q²/τ²."""
    return 3.0 * q2 / tau**2


def avar_random_walk(k2, tau, dt):
    """Rate random walk K (K² in rad²/s³), sampled every dt: K²τ/3 + K²dt²/(6τ)."""
    return k2 * (tau / 3.0 + dt**2 / (6.0 * tau))


def avar_rate_ramp(r2, tau):
    """Rate ramp R (R² in rad²/s⁴): σ²(τ) = R²τ²/2."""
    return 0.5 * r2 * tau**2


@jax.jit
def avar_gauss_markov(s2, t_corr, tau, dt):
    """First-order Gauss–Markov rate of stationary variance σ² and correlation time T (module
    docstring); written with expm1 so that T ≫ dt keeps its digits. Traced once per
    shape (:mod:`.identify`'s note)."""
    m = tau / dt
    a = dt / t_corr
    one_phi = -jnp.expm1(-a)  # 1 − φ
    phi = 1.0 - one_phi
    one_phim = -jnp.expm1(-a * m)  # 1 − φ^m
    inner = m * one_phi - one_phim  # ≥ 0, ~ m²a²/2 for small m·a
    # small m·a: the series (m²−m)a²/2 − (m³−m)a³/6 + (m⁴−m)a⁴/24 avoids the cancellation
    x = a * m
    series = ((m * m - m) * a**2 / 2.0 - (m**3 - m) * a**3 / 6.0 + (m**4 - m) * a**4 / 24.0)
    inner = jnp.where(x < 1e-3, series, inner)
    bracket = m + (2.0 * phi * inner - phi * one_phim**2) / one_phi**2
    return s2 * bracket / m**2


def component_avar(theta: Float[Array, " 8"], tau: Float[Array, " J"], dt) -> Float[Array, "6 J"]:
    """Allan variance of each component (rows: white, quantization, GM₁, GM₂, random walk,
    ramp) at the τ given, for the log-parameter vector ``theta`` (:data:`LAYOUT`)."""
    p = jnp.exp(theta)
    return jnp.stack([
        avar_white(p[0], tau),
        avar_quantization(p[1], tau),
        avar_gauss_markov(p[2], p[3], tau, dt),
        avar_gauss_markov(p[4], p[5], tau, dt),
        avar_random_walk(p[6], tau, dt),
        avar_rate_ramp(p[7], tau),
    ])


def row_mask(mask: Bool[Array, " 8"]) -> Bool[Array, " 6"]:
    """The component rows a parameter mask switches on."""
    return jnp.array([mask[0], mask[1], mask[2], mask[4], mask[6], mask[7]])


def model_avar(theta: Float[Array, " 8"], mask: Bool[Array, " 8"], tau: Float[Array, " J"],
               dt) -> Float[Array, " J"]:
    """Allan variance of the composite model: the sum of its switched-on components."""
    rows = component_avar(theta, tau, dt)
    return jnp.sum(jnp.where(row_mask(mask)[:, None], rows, 0.0), axis=0)


def model_wv(theta, mask, tau, dt):
    """Haar wavelet variance of the composite model: half its Allan variance."""
    return 0.5 * model_avar(theta, mask, tau, dt)


def model_wv_jac(theta: Float[Array, " 8"], mask: Bool[Array, " 8"], tau: Float[Array, " J"],
                 dt) -> tuple[Float[Array, " J"], Float[Array, "J 8"]]:
    """The model's Haar wavelet variance and its derivative in the log-parameters
    (switched-off columns zero). A component's variance is proportional to its power, so
    the derivative in a log-power is the component itself; only the correlation times
    need a derivative (one forward tangent each): the fit's Jacobian at a fraction of the
    cost of pushing eight tangents through every component."""
    p = jnp.exp(theta)
    # both processes in one (2, J) evaluation: one copy of the formula in a program
    s2, log_t = p[jnp.array([2, 4])][:, None], theta[jnp.array([3, 5])][:, None]
    (g1, g2), (dg1, dg2) = jax.jvp(lambda lt: avar_gauss_markov(s2, jnp.exp(lt), tau, dt),
                                   (log_t,), (jnp.ones_like(log_t),))
    rows = jnp.stack([avar_white(p[0], tau), avar_quantization(p[1], tau), g1, g2,
                      avar_random_walk(p[6], tau, dt), avar_rate_ramp(p[7], tau)])
    rows = 0.5 * jnp.where(row_mask(mask)[:, None], rows, 0.0)
    nu = jnp.sum(rows, axis=0)
    on = mask.astype(theta.dtype)
    d_tau = 0.5 * jnp.stack([dg1 * on[2], dg2 * on[4]])
    jac = jnp.stack([rows[0], rows[1], rows[2], d_tau[0], rows[3], d_tau[1], rows[4], rows[5]],
                    axis=1)
    return nu, jac * on[None, :]
