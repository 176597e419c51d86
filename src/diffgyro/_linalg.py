"""Normal equations with their columns scaled to unit diagonal: Gram matrices,
Cholesky solves and the rank check of the fit paths.

Scaling first makes the conditioning independent of the columns' units (a
temperature cubed beside a constant), so one relative tolerance serves every
model.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float


def normal_equations(x: Float[Array, "n 3 p"], y: Float[Array, "n 3"], w: Float[Array, " n"]):
    """Per-axis weighted Gram matrix and right-hand side."""
    xw = x * w[:, None, None]
    return jnp.einsum("nip,niq->ipq", xw, x), jnp.einsum("nip,ni->ip", xw, y)


def scale_gram(a: Float[Array, "... p p"]):
    """``a`` scaled to unit diagonal, ``g = a / (d dᵀ)``, and the scales ``d`` (√diag;
    1 where the diagonal is not positive)."""
    diag = jnp.diagonal(a, axis1=-2, axis2=-1)
    d = jnp.sqrt(jnp.where(diag > 0, diag, 1.0))  # where before sqrt: finite derivative at 0
    return a / (d[..., :, None] * d[..., None, :]), d


def solve_normal(a: Float[Array, "3 p p"], c: Float[Array, "3 p"], ridge: float = 0.0):
    """Cholesky solve (lineax) of the column-scaled normal equations, per axis."""
    g, d = scale_gram(a)
    b = c / d
    eye = jnp.eye(g.shape[-1], dtype=g.dtype)
    if ridge:
        g = g + ridge * eye
    # A non-finite system (a degenerate device) is replaced by a harmless one and its
    # answer set to NaN: lineax stops the whole batch on non-finite input otherwise.
    bad = ~(jnp.all(jnp.isfinite(g), axis=(-2, -1)) & jnp.all(jnp.isfinite(b), axis=-1))
    g = jnp.where(bad[:, None, None], eye, g)
    b = jnp.where(bad[:, None], 0.0, b)

    import lineax as lx  # loaded when a solve is traced, not at every start

    def one(gi, bi):
        op = lx.MatrixLinearOperator(gi, lx.positive_semidefinite_tag)
        return lx.linear_solve(op, bi, solver=lx.Cholesky(), throw=False).value

    return jnp.where(bad[:, None], jnp.nan, jax.vmap(one)(g, b) / d)


def solve_normal_inner(a: Float[Array, "3 p p"], c: Float[Array, "3 p"], ridge: float = 1e-13):
    """Cholesky solve for the inner loop of variable projection.

    Plain ``jax.scipy`` Cholesky: differentiable in forward and reverse mode
    inside optimistix's Jacobian and adjoint, and it returns NaN rather than
    raising when a trial step of the time constants makes the system singular.
    """
    g, d = scale_gram(a)
    g = g + ridge * jnp.eye(g.shape[-1], dtype=g.dtype)
    factor = jax.scipy.linalg.cho_factor(g)
    return jax.scipy.linalg.cho_solve(factor, (c / d)[..., None])[..., 0] / d


def rank_check(a: Float[Array, "3 p p"], rank_tol):
    """Smallest/largest eigenvalue of the scaled Gram matrix per axis, the direction
    of the smallest (which columns are collinear), and whether the ratio passes
    ``rank_tol``."""
    g, _ = scale_gram(a)
    evals, evecs = jnp.linalg.eigh(g)
    ratio = evals[:, 0] / jnp.maximum(evals[:, -1], 1e-300)
    return ratio, evecs[:, :, 0], ratio > rank_tol
