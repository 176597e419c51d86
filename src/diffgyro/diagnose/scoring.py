"""Scoring from block sums: held-out errors of the base model and of base + every candidate.

Every number the decision reads is a sum over samples of products of the base
design ``X``, a candidate's columns ``Z`` and the base residual ``e``. The
valid samples of each time block of the folds (the blocks of
:func:`diffgyro.core.fold_ids`) are gathered once into a window of
``ceil(length / B)`` samples (``B × w``, the rest masked), so the sums of a
column set over every block are a few batched contractions over the window
axis, and no column set of every sample outlives its own sums:

* a block's sums are ``XᵀX``, ``Xᵀe``, ``eᵀe`` (once) and ``ZᵀX``, ``ZᵀZ``,
  ``Zᵀe`` (per column set);
* a fold's sums are those of its blocks (block ``b`` is in fold ``b mod K``, as
  in :mod:`diffgyro.fit_sums`), a fold's training system is the total minus
  its own, and its held-out error ``Q − 2βᵀc + βᵀAβ`` comes from its own sums;
  the same formula on one block's sums gives that block's held-out error;
* a time constant's grid is walked one point at a time (``lax.map``): only
  the per-block sums of each point are kept, each fold picks its point on its
  training blocks (so the held-out number pays for the search), and a
  parabola through the neighbours refines it.

Memory is that of a few per-sample arrays of one device (its signals, the base
design, one column set), whatever the number of candidates and grid points.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..model import ErrorModel
from ..signals import Signals
from .candidates import CandidateSpec
from .thresholds import GRID_POINTS


def block_windows(mask: np.ndarray, n_blocks: int) -> tuple[np.ndarray, np.ndarray]:
    """Sample index (B, w) and inside flag (B, w) of every fold block's window.

    Block b holds the valid samples of rank ceil(b·n/B) .. ceil((b+1)·n/B) − 1
    (n valid samples); its window lists their positions and repeats the last one
    past its end (flagged outside). ``w = ceil(length / B)`` depends only on the
    padded length, so the devices of a batch share one compiled shape.
    """
    length = mask.shape[0]
    w = max(-(-length // n_blocks), 1)
    pos = np.flatnonzero(mask)
    nv = pos.size
    b = np.arange(n_blocks + 1, dtype=np.int64)
    rank = (b * nv + n_blocks - 1) // n_blocks
    j = rank[:-1, None] + np.arange(w)[None, :]
    inside = j < rank[1:, None]
    idx = pos[np.minimum(j, nv - 1)] if nv else np.zeros(j.shape, np.int64)
    return idx.astype(np.int32), inside


def window(a: Array, idx: Int[Array, "B w"], inside: Bool[Array, "B w"]) -> Array:
    """(n, ...) -> (B, w, ...): the samples of every block's window, zero outside it."""
    g = a[idx]
    return jnp.where(inside.reshape(inside.shape + (1,) * (a.ndim - 1)), g, 0.0)


def fold_of_blocks(blocks: Array, n_folds: int) -> Array:
    """Per-fold sums (K, ...) from per-block sums (B, ...); block b is in fold b mod K."""
    b = np.arange(blocks.shape[0])
    own = (b[None, :] % n_folds == np.arange(n_folds)[:, None]).astype(np.float64)
    return jnp.tensordot(jnp.asarray(own, blocks.dtype), blocks, axes=1)


def block_folds(n_blocks: int, n_folds: int) -> np.ndarray:
    return np.arange(n_blocks) % n_folds


def solve_scaled(g, c, d):
    """Solve ``g b = c`` per leading index after scaling columns by ``d`` (tiny ridge), by
    Cholesky: a Gram matrix, and a small program to trace once per candidate."""
    gs = g / (d[..., :, None] * d[..., None, :])
    eye = jnp.eye(g.shape[-1], dtype=g.dtype)
    gs = gs + 1e-11 * eye
    cs = c / d
    bad = ~jnp.all(jnp.isfinite(gs), axis=(-2, -1))
    gs = jnp.where(bad[..., None, None], eye, gs)
    lower = jnp.linalg.cholesky(gs)
    u = jax.lax.linalg.triangular_solve(lower, cs[..., None], left_side=True, lower=True)
    b = jax.lax.linalg.triangular_solve(lower, u, left_side=True, lower=True, transpose_a=True)
    return jnp.where(bad[..., None], jnp.nan, b[..., 0] / d)


def held_sse(b, g, c, q):
    """Σ (e − xβ)² per axis from the sums A = ``g``, c, Q = ``q``."""
    return q - 2.0 * jnp.sum(b * c, -1) + jnp.einsum("...p,...pq,...q->...", b, g, b)


def _train(s):
    return jnp.sum(s, axis=0, keepdims=True) - s


# --------------------------------------------------------------------------- the base model


class BaseScores(eqx.Module):
    """The base model's block sums (``a_b`` XᵀX (B, 3, p, p), ``c_b`` Xᵀe (B, 3, p), ``q_b``
    eᵀe (B, 3)), its fold sums ``ee`` (K, 3) and counts ``cnt`` (K,), the blocks' counts
    ``blk_cnt`` (B,), each fold's training solution ``b_base`` (K, 3, p), its held-out SSE
    ``base_sse`` (K, 3) and every block's held-out SSE ``base_blk`` (B,)."""

    a_b: Array
    c_b: Array
    q_b: Array
    ee: Array
    cnt: Array
    blk_cnt: Array
    b_base: Array
    base_sse: Array
    base_blk: Array


class CandidateScores(eqx.Module):
    """Base + one candidate: held-out SSE per fold ``held`` (K, 3), full-fit SSE ``full``
    (3,), the time constant ``theta`` (q,; NaN without one), every block's held-out SSE
    ``blk`` (B,) and ``edge``: the time constant at the slow end of its grid."""

    held: Array
    full: Array
    theta: Array
    blk: Array
    edge: Array


def base_scores(xb_w, e_w, inside, n_folds: int) -> BaseScores:
    """Block and fold sums of the base design and residual; each fold's training solution,
    its held-out SSE per axis and every block's held-out SSE."""
    a_b = jnp.einsum("bwip,bwiq->bipq", xb_w, xb_w)  # (B, 3, p, p)
    c_b = jnp.einsum("bwip,bwi->bip", xb_w, e_w)
    q_b = jnp.sum(e_w * e_w, axis=1)  # (B, 3)
    blk_cnt = jnp.sum(inside, axis=1).astype(e_w.dtype)
    xx, xe, ee = (fold_of_blocks(s, n_folds) for s in (a_b, c_b, q_b))
    cnt = fold_of_blocks(blk_cnt, n_folds)
    p = xb_w.shape[-1]
    fb = block_folds(a_b.shape[0], n_folds)
    if p:
        dx = jnp.sqrt(jnp.maximum(jnp.diagonal(jnp.sum(xx, 0), axis1=-2, axis2=-1), 1e-300))
        b_base = solve_scaled(_train(xx), _train(xe), dx)  # (K, 3, p)
        base_sse = held_sse(b_base, xx, xe, ee)
        base_blk = jnp.sum(held_sse(b_base[fb], a_b, c_b, q_b), -1)
    else:
        b_base = jnp.zeros((n_folds, 3, 0), e_w.dtype)
        base_sse, base_blk = ee, jnp.sum(q_b, -1)
    return BaseScores(a_b, c_b, q_b, ee, cnt, blk_cnt, b_base, base_sse, base_blk)


# --------------------------------------------------------------------------- candidates


def candidate_grid(c: CandidateSpec, base: ErrorModel, sig: Signals, theta_b, log_min_lag):
    """The nonlinear-parameter grid (g, q) of a candidate and its columns at one grid point
    (n, 3, k): the columns it adds to the base design. ``log_min_lag``: log of the shortest
    time constant (s) a lag term's grid starts at (the dT/dt window; −inf: none), an array,
    so that a new window does not compile the scoring again."""
    term = c.term
    dtype = sig.gyro.dtype
    if c.old is not None:  # an order raised: the new columns at the base's time constants
        k_old = c.old.n_params
        q_slice = [qs for t, _, qs in base.slices() if t == c.old]
        th = theta_b[q_slice[0]] if q_slice else jnp.zeros((0,), dtype)
        return th[None], lambda th_: term.columns(sig, th_)[..., k_old:]
    if term.n_nonlinear == 0:
        return jnp.zeros((1, 0), dtype), lambda th_: term.columns(sig, th_)
    grid = term.nonlinear_grid(sig)
    if grid.shape[1] == 1:
        lo, hi = jnp.min(grid[:, 0]), jnp.max(grid[:, 0])
        if term.tau_from_dtemp_window:
            floored = log_min_lag > -jnp.inf
            lo = jnp.where(floored, jnp.maximum(lo, log_min_lag), lo)
            hi = jnp.where(floored, jnp.maximum(hi, lo + math.log(4.0)), hi)
        grid = jnp.linspace(lo, hi, GRID_POINTS)[:, None]
    return grid, lambda th_: term.columns(sig, th_)


def column_sums(z, xb_w, e_w, idx, inside):
    """Per-block sums ZᵀX (B, 3, k, p), ZᵀZ (B, 3, k, k), Zᵀe (B, 3, k) of one column set."""
    zw = window(jnp.where(jnp.isfinite(z), z, 0.0), idx, inside)
    return (jnp.einsum("bwik,bwip->bikp", zw, xb_w), jnp.einsum("bwik,bwil->bikl", zw, zw),
            jnp.einsum("bwik,bwi->bik", zw, e_w))


def score_set(base: BaseScores, sums, n_folds: int):
    """Scores of base + one column set from its block sums: per-fold training SSE (K,),
    held-out SSE (K, 3), full-fit SSE (3,), its total and every block's held-out SSE (B,)."""
    zx, zz, ze = sums
    top = jnp.concatenate([base.a_b, jnp.swapaxes(zx, -1, -2)], axis=-1)
    gb = jnp.concatenate([top, jnp.concatenate([zx, zz], axis=-1)], axis=-2)  # (B, 3, P, P)
    cb = jnp.concatenate([base.c_b, ze], axis=-1)
    gm, cv = fold_of_blocks(gb, n_folds), fold_of_blocks(cb, n_folds)
    gtot, ctot = jnp.sum(gm, 0), jnp.sum(cv, 0)
    d = jnp.sqrt(jnp.maximum(jnp.diagonal(gtot, axis1=-2, axis2=-1), 1e-300))  # (3, P)
    ee = base.ee
    b = solve_scaled(gtot[None] - gm, ctot[None] - cv, d[None])  # (K, 3, P)
    sse_tr = jnp.sum(_train(ee) - jnp.sum(b * (ctot[None] - cv), -1), -1)
    sse_h = held_sse(b, gm, cv, ee)
    b_all = solve_scaled(gtot, ctot, d)
    sse_all = jnp.sum(ee, 0) - jnp.sum(b_all * ctot, -1)
    blk = jnp.sum(held_sse(b[block_folds(gb.shape[0], n_folds)], gb, cb, base.q_b), -1)
    clean = lambda a: jnp.where(jnp.isfinite(a), a, jnp.inf)  # noqa: E731
    return clean(sse_tr), sse_h, sse_all, clean(jnp.sum(sse_all)), blk


def _scores_on(thetas, columns, base, xb_w, e_w, idx, inside, n_folds):
    """Scores of every θ row of ``thetas``, the columns formed one θ at a time."""
    sums = jax.lax.map(lambda th: column_sums(columns(th), xb_w, e_w, idx, inside), thetas)
    return jax.vmap(lambda s: score_set(base, s, n_folds))(sums)


def _vertex(costs, i, grid):
    """Parabola vertex through grid points i−1, i, i+1 (one time constant)."""
    i = jnp.clip(i, 1, grid.shape[0] - 2)
    c0, c1, c2 = costs[i - 1], costs[i], costs[i + 1]
    den = c0 - 2.0 * c1 + c2
    off = jnp.where((den > 0) & jnp.isfinite(den), 0.5 * (c0 - c2) / jnp.where(den > 0, den, 1.0), 0.0)
    return grid[i, 0] + jnp.clip(off, -1.0, 1.0) * (grid[1, 0] - grid[0, 0])


def candidate_scores(c, base_model, sig, theta_b, log_min_lag, base, xb_w, e_w, idx, inside,
                     n_folds: int) -> CandidateScores:
    """The :class:`CandidateScores` of base + one candidate."""
    grid, columns = candidate_grid(c, base_model, sig, theta_b, log_min_lag)
    folds = jnp.arange(n_folds)
    fb = block_folds(base.a_b.shape[0], n_folds)
    tr, sh, sall, tot, blk = _scores_on(grid, columns, base, xb_w, e_w, idx, inside, n_folds)
    pick = jnp.argmin(tr, axis=0)  # (K,) the grid point each fold's training blocks choose
    best = jnp.argmin(tot)
    tr_pick, held = tr[pick, folds], sh[pick, folds]
    blk_pick = blk[pick[fb], jnp.arange(fb.size)]
    full, tot_best = sall[best], tot[best]
    theta = grid[best] if grid.shape[1] else jnp.full((1,), jnp.nan, sig.gyro.dtype)
    if grid.shape[0] >= 3 and grid.shape[1] == 1:  # refine between grid points, again per fold
        th2 = jnp.concatenate([jax.vmap(_vertex, in_axes=(1, 0, None))(tr, pick, grid),
                               _vertex(tot, best, grid)[None]])  # (K + 1,)
        tr2, sh2, sall2, tot2, blk2 = _scores_on(th2[:, None], columns, base, xb_w, e_w, idx,
                                                 inside, n_folds)
        better = tr2[folds, folds] < tr_pick  # keep the refinement only where it helps
        held = jnp.where(better[:, None], sh2[folds, folds], held)
        blk_pick = jnp.where(better[fb], blk2[fb, jnp.arange(fb.size)], blk_pick)
        full_better = tot2[n_folds] < tot_best
        full = jnp.where(full_better, sall2[n_folds], full)
        theta = jnp.where(full_better, th2[n_folds:], theta)
    if grid.shape[0] >= 2 and grid.shape[1] == 1:
        edge = theta[0] >= grid[-1, 0] - 0.5 * (grid[1, 0] - grid[0, 0])
    else:
        edge = jnp.asarray(False)
    return CandidateScores(held, full, theta, blk_pick, edge)


_ = (Float,)  # jaxtyping names used in annotations only
