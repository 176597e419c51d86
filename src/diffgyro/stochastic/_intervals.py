"""Asymptotic confidence intervals of the GMWM estimate (delta method, sandwich form).

With weight Ω, Jacobian D = ∂ν/∂θ and Σ the covariance of ν̂, the estimate's
covariance is ``(DᵀΩD)⁻¹ DᵀΩ Σ Ω D (DᵀΩD)⁻¹`` (Ω = Σ⁻¹: ``(DᵀΣ⁻¹D)⁻¹``). θ are
logarithms of powers and times, so an interval ``exp(θ ± 1.96·se)`` stays
positive and is asymmetric as the likelihood of a variance is; an amplitude
(N, σ, K …) is the square root of its power, its log-interval half as wide.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

#: Two-sided 95 % normal quantile.
Z95 = 1.959963984540054


def sandwich(d, chol_w, cov_scaled, mask):
    """Covariance of the log-parameters (switched-off rows and columns zero). ``d``: the scaled
    Jacobian (J, 8); ``chol_w``: Cholesky factor of the Σ that defined the weight; ``cov_scaled``:
    Σ at the estimate (both relative to ν̂)."""
    on = mask.astype(d.dtype)
    dw = jax.scipy.linalg.solve_triangular(chol_w, d, lower=True)  # L⁻¹D
    b = dw.T @ dw + jnp.diag(1.0 - on)
    # pseudo-inverse: a direction the data do not determine gets a huge, not a NaN, variance
    w, v = jnp.linalg.eigh(b)
    inv_w = jnp.where(w > 1e-12 * jnp.max(w), 1.0 / w, 1e12 / jnp.max(w))
    b_inv = (v * inv_w) @ v.T
    # DᵀΩ Σ Ω D with Ω = (LLᵀ)⁻¹
    u = jax.scipy.linalg.solve_triangular(chol_w, d, lower=True)
    u = jax.scipy.linalg.solve_triangular(chol_w.T, u, lower=False)  # Ω D
    meat = u.T @ cov_scaled @ u
    cov = b_inv @ meat @ b_inv
    return cov * on[:, None] * on[None, :]


def log_interval(log_value, log_se, z=Z95):
    """(lo, hi) of ``exp(log_value ± z·log_se)``."""
    return jnp.exp(log_value - z * log_se), jnp.exp(log_value + z * log_se)
