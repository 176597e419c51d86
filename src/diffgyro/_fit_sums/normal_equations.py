"""The normal equations from the sums: unpacking A, c, Q, scaled Cholesky solves and
the residual sum of squares."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._linalg import scale_gram
from .layout import Layout, varying_products
from .types import SplitSums

#: The normal equations' sums per gyro axis: A (3, p, p), c (3, p), Q (3,) and the count.
NormalSums = tuple[Float[Array, "... 3 p p"], Float[Array, "... 3 p"], Float[Array, "... 3"],
             Float[Array, "..."]]


def cholesky(a: Float[Array, "... p p"],
             ) -> tuple[Float[Array, "... p p"], Float[Array, "... p"]]:
    """Cholesky factors of the column-scaled Gram matrices (..., p, p) and the column scales.

    A matrix that is not finite gives NaN (one degenerate device never stops the batch).
    Finite is tested on the sum of the scaled entries (|g_ij| ≤ 1 where A is positive
    semidefinite): an all-reduction of isfinite compiled to 3× the code.
    """
    g, d = scale_gram(a)
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    ok = jnp.isfinite(jnp.sum(g, axis=(-2, -1)))[..., None, None]
    chol = jnp.linalg.cholesky(jnp.where(ok, g, eye))
    return jnp.where(ok, chol, jnp.nan), d


def cho_inverse(chol: Float[Array, "... p p"], d: Float[Array, "... p"],
                ) -> Float[Array, "... p p"]:
    """Inverse of the matrix whose :func:`cholesky` factors are ``chol`` and ``d``."""
    eye = jnp.broadcast_to(jnp.eye(chol.shape[-1], dtype=chol.dtype), chol.shape)
    return jax.scipy.linalg.cho_solve((chol, True), eye) / (d[..., :, None] * d[..., None, :])


def cho_solve(chol: Float[Array, "... p p"], d: Float[Array, "... p"],
              c: Float[Array, "... p"]) -> Float[Array, "... p"]:
    """The solution of ``A x = c`` from ``A``'s :func:`cholesky` factors ``chol`` and ``d``."""
    z = jax.scipy.linalg.cho_solve((chol, True), (c / d)[..., None])[..., 0]
    return z / d


def unpack(layout: Layout, s: Float[Array, "... P"]) -> NormalSums:
    """A, c, Q and the count from the product vector(s) ``s`` (..., P); c and Q by static
    slices (an index array is a gather, a kernel of its own)."""
    a_idx, c_idx, q_idx = layout.index()
    lead = s.shape[:-1]
    a = s[..., a_idx]
    c = s[..., int(c_idx[0, 0]):int(c_idx[-1, -1]) + 1].reshape(lead + c_idx.shape)
    return a, c, s[..., int(q_idx[0]):int(q_idx[-1]) + 1], s[..., 0]


def unpack_split(layout: Layout, fixed: Float[Array, "... f"] | None,
                 moving: Float[Array, "... m"]) -> NormalSums:
    """:func:`unpack` of the products whose fixed ones (:func:`varying_products`) are
    ``fixed`` and moving ones ``moving``, by one gather from the two side by side;
    ``fixed`` None: the fixed products are zero (derivatives)."""
    var_idx, fix_idx = varying_products(layout)
    src = np.zeros(layout.n_products, np.int32)
    src[var_idx] = np.arange(len(var_idx))
    if fixed is None:  # every fixed product reads the zero appended to the moving ones
        src[fix_idx] = len(var_idx)
        s = jnp.concatenate([moving, jnp.zeros(moving.shape[:-1] + (1,), moving.dtype)], axis=-1)
    else:
        src[var_idx] += len(fix_idx)
        src[fix_idx] = np.arange(len(fix_idx))
        fixed = jnp.broadcast_to(fixed, moving.shape[:-1] + fixed.shape[-1:])
        s = jnp.concatenate([fixed, moving], axis=-1)
    a_idx, c_idx, q_idx = layout.index()
    cuts = np.cumsum([a_idx.size, c_idx.size, q_idx.size])
    g = s[..., np.concatenate([src[a_idx].ravel(), src[c_idx].ravel(), src[q_idx], src[:1]])]
    lead = g.shape[:-1]
    return (g[..., :cuts[0]].reshape(lead + a_idx.shape), g[..., cuts[0]:cuts[1]].reshape(
        lead + c_idx.shape), g[..., cuts[1]:cuts[2]], g[..., cuts[2]])


def residual_ss(a: Float[Array, "... 3 p p"], c: Float[Array, "... 3 p"],
                q: Float[Array, "... 3"], beta: Float[Array, "... 3 p"]) -> Float[Array, "... 3"]:
    """Σ (y − xβ)² per axis from the sums A, c, Q."""
    return q - 2.0 * jnp.einsum("...ip,...ip->...i", beta, c) + jnp.einsum(
        "...ip,...ipq,...iq->...i", beta, a, beta)


def projected_ss(a, c, q, rank_tol):
    """Σ (y − xβ)² per axis at the least-squares minimum, formed stably: ``q`` less the
    squared projections of y on the scaled Gram matrix's eigenvectors, each non-negative,
    directions below ``rank_tol`` of the largest eigenvalue left out (the minimum-norm
    solution). Where the columns are collinear the solved β grows without bound and
    :func:`residual_ss` cancels to noise (it read 0.0 for a rank-deficient device)."""
    g, d = scale_gram(a)
    evals, evecs = jnp.linalg.eigh(g)
    proj = jnp.einsum("...pk,...p->...k", evecs, c / d)
    keep = evals > rank_tol * jnp.max(evals, axis=-1, keepdims=True)
    return q - jnp.sum(jnp.where(keep, proj**2 / jnp.where(keep, evals, 1.0), 0.0), axis=-1)


def unpack_sums(layout: Layout, s: Float[Array, "... P"] | SplitSums) -> NormalSums:
    """:func:`unpack` of a product vector, or of the fixed and moving sums apart (a model
    with time constants: :func:`unpack_split`)."""
    if isinstance(s, SplitSums):
        return unpack_split(layout, s.fixed, s.moving)
    return unpack(layout, s)
