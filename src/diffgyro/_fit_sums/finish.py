"""One device's results from its sums: solves, covariance, rank check, status."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._linalg import rank_check
from ..model import ErrorModel
from ..status import collinear_terms, fit_status, min_samples
from .layout import Layout, covariance_pairs, moving_columns
from .normal_equations import (
    cho_inverse,
    cho_solve,
    cholesky,
    projected_ss,
    residual_ss,
    unpack_sums,
)
from .types import DeviceSums


def finish(model: ErrorModel, layout: Layout, opts, raw: DeviceSums) -> dict:
    """One device's results from its sums (:func:`.device.device`): the full and the folds'
    solutions, residual and held-out errors, covariance, rank check and status.

    Small dense algebra on (3, p, p) systems, no samples: a program of its own
    (:func:`.programs.group_finish`), inlined in fused linear models' group programs.
    """
    p, nq = layout.p, model.n_nonlinear
    sums = raw.sums
    theta, converged = sums.theta, sums.converged
    a, cc, q, n_valid = unpack_sums(layout, sums.tot)
    af, cf, qf, nf = unpack_sums(layout, sums.held)
    at, ct, _, _ = unpack_sums(layout, sums.train)
    dtype = a.dtype

    # with every column shared by the axes the three Gram matrices are one: factor,
    # check and invert the first axis' only and broadcast
    n_gram = 1 if all(layout.shared) else 3

    def gram_factor(m):  # Cholesky factors and column scales of m (..., 3, p, p)
        chol_, d_ = cholesky(m[..., :n_gram, :, :])
        return jnp.broadcast_to(chol_, m.shape), jnp.broadcast_to(d_, m.shape[:-1])

    # the full fit and the folds' training fits, factored and solved together
    chol_all, d_all = gram_factor(jnp.concatenate([a[None], at]))
    beta_all = cho_solve(chol_all, d_all, jnp.concatenate([cc[None], ct]))
    chol, dsc, beta_s, beta_f = chol_all[0], d_all[0], beta_all[0], beta_all[1:]
    ratio, direction, rank_ok = (jnp.broadcast_to(v, (3,) + v.shape[1:])
                                 for v in rank_check(a[:n_gram], opts.rank_tol))
    sse = jnp.maximum(residual_ss(a, cc, q, beta_s), 0.0)
    # collinear columns: the residual at the least-squares minimum, formed without the
    # unbounded β (whose sums cancel to noise)
    sse = jnp.where(rank_ok, sse, jnp.maximum(projected_ss(a, cc, q, opts.rank_tol), 0.0))
    shift = jnp.zeros((3, p), dtype)
    if layout.const_col is not None:
        shift = shift.at[:, layout.const_col].set(raw.y0)
    beta = beta_s + shift
    rms = jnp.sqrt(jnp.sum(sse) / jnp.maximum(3 * n_valid, 1.0))

    # held-out folds: train on total − fold, score on the fold's own sums
    sse_f = jnp.sum(jnp.maximum(residual_ss(af, cf, qf, beta_f), 0.0), axis=-1)
    heldout_rms = jnp.sqrt(jnp.sum(sse_f) / jnp.maximum(3 * jnp.sum(nf), 1.0))
    fold_mse = sse_f / jnp.maximum(3 * nf, 1.0)

    dof = jnp.maximum(n_valid - p - nq, 1.0)
    sigma2 = jnp.maximum(sse / dof, 1e-300)
    if nq == 0:  # block diagonal: σ_i² (X_iᵀX_i)⁻¹ per axis
        inv = jnp.broadcast_to(cho_inverse(chol[:n_gram], dsc[:n_gram]), (3, p, p))
        cov = jax.scipy.linalg.block_diag(*[inv[i] * sigma2[i] for i in range(3)])
    else:  # g = ∂(Xβ)/∂θ = Σ_m β_m ∂x_m/∂θ over the moving columns m
        cols = moving_columns(model)
        b_m, n_m = beta_s[:, cols], len(cols)  # (3, M)
        _, cross_at, curvature_at = covariance_pairs(model, layout)
        cross = sums.covariance[cross_at].reshape(3, p, n_m, nq)  # Σ x_a ∂x_m/∂θ_k
        # Σ ∂x_m/∂θ_k ∂x_n/∂θ_r
        curvature = sums.covariance[curvature_at].reshape(3, n_m, nq, n_m, nq)
        xg = jnp.einsum("iamk,im->iak", cross, b_m)
        gg = jnp.einsum("imknr,im,in->ikr", curvature, b_m, b_m)
        cov = _covariance_separable(a, xg, gg, sigma2)

    collinear = collinear_terms(model, direction, rank_ok)
    finite = jnp.all(jnp.isfinite(beta)) & jnp.all(jnp.isfinite(theta)) & jnp.isfinite(rms)
    status = fit_status(n_valid, min_samples(p + nq), converged, finite, raw.range_flags,
                        rank_ok)
    out = dict(beta=beta, theta=theta, cov=cov, rms=rms,
               heldout_rms=heldout_rms, fold_mse=fold_mse,
               sigma=jnp.sqrt(sigma2), steps=sums.steps,
               status=jnp.asarray(status, jnp.int32), range_flags=raw.range_flags,
               collinear=collinear, rank_ratio=jnp.min(ratio), n_samples=n_valid)
    for k in ("temp_range", "norm_centre", "norm_scale"):
        if getattr(raw, k) is not None:
            out[k] = getattr(raw, k)
    return out


def _covariance_separable(a, xg, gg, sigma2):
    """Gauss–Newton covariance of (β per axis, θ), each axis weighted by 1/σ_i², as
    :func:`diffgyro._direct._covariance` forms it, from the Gram matrices ``a`` (3, p, p) and
    the sums ``xg`` = Σ X ∂(Xβ)/∂θ (3, p, q) and ``gg`` = Σ (∂(Xβ)/∂θ)² (3, q, q)."""
    p = a.shape[-1]
    i_bt = xg / sigma2[:, None, None]
    i_tt = jnp.sum(gg / sigma2[:, None, None], axis=0)
    zero = jnp.zeros((p, p), a.dtype)
    info = jnp.block([[*(a[i] / sigma2[i] if j == i else zero for j in range(3)), i_bt[i]]
                      for i in range(3)] + [[*(i_bt[i].T for i in range(3)), i_tt]])
    # positive definite where the fit is identified (NaN where not: the status says why)
    return cho_inverse(*cholesky(info))
