"""Scoring from block sums: held-out errors of the base model and of base + every candidate.

Every number the decision reads is a sum over samples of products of the base
design ``X``, a candidate's columns ``Z`` and the base residual ``e``. The
valid samples of each time block of the folds (the blocks of
:func:`diffgyro._folds.fold_ids`) are gathered once into a window of
``ceil(length / B)`` samples (``B × w``, the rest masked), so the sums of a
column set over every block are a few batched contractions over the window
axis, and no column set of every sample outlives its own sums:

* a block's sums are ``XᵀX``, ``Xᵀe``, ``eᵀe`` (once) and ``ZᵀX``, ``ZᵀZ``,
  ``Zᵀe`` (per column set);
* a fold's sums are those of its blocks (block ``b`` is in fold ``b mod K``, as
  in :mod:`diffgyro._fit_sums`), a fold's training system is the total minus
  its own, and its held-out error ``Q − 2βᵀc + βᵀAβ`` comes from its own sums;
  the same formula on one block's sums gives that block's held-out error;
* a time constant is searched on the record's segment means (:class:`Segments`:
  means of ``m`` consecutive valid samples inside one block, weighted by their
  counts, ``m = 1`` below :data:`SEARCH_POINTS` samples): its grid is walked
  one point at a time (``lax.map``), each fold picks its point on its training
  blocks (so the held-out number pays for the search) and a parabola through
  the neighbours refines it; the held-out and full-record numbers are then
  computed from the samples at each fold's pick and at the full record's, so
  the search alone sees the coarser series.

Memory is that of a few per-sample arrays of one device (its signals, the base
design, one column set), whatever the number of candidates and grid points.

The segment sums stand in for the sample sums when the columns barely change
over ``m`` samples: ``Σ_i z_i x_i = Σ_s n_s z̄_s x̄_s`` up to the covariance of
``z`` and ``x`` inside a segment. The lag and warm-up columns have time
constants of seconds and up (the dT/dt window is the floor), the segments last
``m / fs`` (0.1 s for 200 Hz × 1 h), so the search picks the same point; the
numbers the decision reads never come from segments.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..model import ErrorModel
from ..signals import Signals
from ._candidates import CandidateSpec
from ._thresholds import GRID_POINTS

#: Longest series (segment means of every block) a time constant's grid is searched on.
SEARCH_POINTS = 1 << 15


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


def segment_length(length: int, n_blocks: int, points: int | None = None) -> int:
    """Samples per segment so that every block's segments total at most ``points``
    (default :data:`SEARCH_POINTS`; 1 when the record fits)."""
    points = SEARCH_POINTS if points is None else points
    w = max(-(-length // n_blocks), 1)
    per_block = max(points // n_blocks, 1)
    return max(1, -(-w // per_block))


def segment_sums(a_w: Array, m: int) -> Array:
    """(B, w, ...) -> (B, S, ...): sums over segments of ``m`` samples (S = ceil(w / m))."""
    b, w = a_w.shape[:2]
    s = -(-w // m)
    pad = [(0, 0), (0, s * m - w)] + [(0, 0)] * (a_w.ndim - 2)
    return jnp.pad(a_w, pad).reshape((b, s, m) + a_w.shape[2:]).sum(axis=2)


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


def base_scores(xe_w, inside, n_folds: int) -> BaseScores:
    """Block and fold sums of the base design and residual ``xe_w`` (B, w, 3p + 3, the
    layout of :func:`design_and_residual`); each fold's training solution, its held-out SSE
    per axis and every block's held-out SSE."""
    b, _, pe = xe_w.shape
    p = (pe - 3) // 3
    g = jax.lax.dot_general(xe_w, xe_w, (((1,), (1,)), ((0,), (0,))))  # (B, 3p + 3, 3p + 3)
    a_b = own_axis(g[:, :3 * p, :3 * p].reshape(b, 3, p, 3, p))  # (B, 3, p, p)
    c_b = own_axis(g[:, :3 * p, 3 * p:].reshape(b, 3, p, 3))  # (B, 3, p)
    q_b = jnp.diagonal(g[:, 3 * p:, 3 * p:], axis1=1, axis2=2)  # (B, 3)
    dtype = xe_w.dtype
    blk_cnt = jnp.sum(inside, axis=1).astype(dtype)
    xx, xe, ee = (fold_of_blocks(s, n_folds) for s in (a_b, c_b, q_b))
    cnt = fold_of_blocks(blk_cnt, n_folds)
    fb = block_folds(a_b.shape[0], n_folds)
    if p:
        dx = jnp.sqrt(jnp.maximum(jnp.diagonal(jnp.sum(xx, 0), axis1=-2, axis2=-1), 1e-300))
        b_base = solve_scaled(_train(xx), _train(xe), dx)  # (K, 3, p)
        base_sse = held_sse(b_base, xx, xe, ee)
        base_blk = jnp.sum(held_sse(b_base[fb], a_b, c_b, q_b), -1)
    else:
        b_base = jnp.zeros((n_folds, 3, 0), dtype)
        base_sse, base_blk = ee, jnp.sum(q_b, -1)
    return BaseScores(a_b, c_b, q_b, ee, cnt, blk_cnt, b_base, base_sse, base_blk)


# --------------------------------------------------------------------------- candidates


class Segments(eqx.Module):
    """The record as segment means, for the time-constant search: the signals (B·S,), the
    base design and residual scaled by √count (B, S, 3p + 3) (so their products sum to
    count-weighted ones), √count ``root`` (B, S) and the base model's sums on them."""

    sig: Signals
    xe: Array
    root: Array
    base: BaseScores


def segments(sig: Signals, xe_w, idx, inside, m: int, n_folds: int) -> Segments:
    """The :class:`Segments` of one device: means of ``m`` consecutive valid samples of every
    block (an empty segment keeps the time of the last one before it: no time passes)."""
    dtype = xe_w.dtype
    n = sig.t.shape[0]
    cnt = segment_sums(inside.astype(dtype), m)  # (B, S)
    den = jnp.maximum(cnt, 1.0)

    def mean(a):
        if not (eqx.is_array(a) and a.ndim >= 1 and a.shape[0] == n):
            return a
        sums = segment_sums(window(a.astype(dtype), idx, inside), m)
        return (sums / den.reshape(den.shape + (1,) * (a.ndim - 1))).reshape((-1,) + a.shape[1:])

    seg = jax.tree_util.tree_map(mean, sig)
    ok = cnt.reshape(-1) > 0
    t = jax.lax.cummax(jnp.where(ok, seg.t, -jnp.inf))
    seg = eqx.tree_at(lambda s: (s.t, s.mask), seg, (jnp.where(jnp.isfinite(t), t, 0.0), ok))
    xe = segment_sums(xe_w, m) / jnp.sqrt(den)[..., None]
    return Segments(seg, xe, jnp.sqrt(cnt), base_scores(xe, cnt > 0, n_folds))


def candidate_grid(c: CandidateSpec, base: ErrorModel, sig: Signals, theta_b, log_min_lag):
    """The nonlinear-parameter grid (g, q) of a candidate and its columns ``(signals, θ) ->
    (n, 3, k)``: the columns it adds to the base design. ``log_min_lag``: log of the
    shortest time constant (s) a lag term's grid starts at (the dT/dt window; −inf: none),
    an array, so that a new window does not compile the scoring again."""
    term = c.term
    dtype = sig.gyro.dtype
    if c.old is not None:  # an order raised: the new columns at the base's time constants
        k_old = c.old.n_params
        q_slice = [qs for t, _, qs in base.slices() if t == c.old]
        th = theta_b[q_slice[0]] if q_slice else jnp.zeros((0,), dtype)
        return th[None], lambda s, th_: term.columns(s, th_)[..., k_old:]
    if term.n_nonlinear == 0:
        return jnp.zeros((1, 0), dtype), term.columns
    grid = term.nonlinear_grid(sig)
    if grid.shape[1] == 1:
        lo, hi = jnp.min(grid[:, 0]), jnp.max(grid[:, 0])
        if term.tau_from_dtemp_window:
            floored = log_min_lag > -jnp.inf
            lo = jnp.where(floored, jnp.maximum(lo, log_min_lag), lo)
            hi = jnp.where(floored, jnp.maximum(hi, lo + math.log(4.0)), hi)
        grid = jnp.linspace(lo, hi, GRID_POINTS)[:, None]
    return grid, term.columns


@jax.jit  # traced once per shape, not once per candidate and grid (likewise score_set)
def column_sums(zw, xe_w):
    """Per-block sums ZᵀX (B, 3, k, p), ZᵀZ (B, 3, k, k), Zᵀe (B, 3, k) of one windowed
    column set ``zw`` (B, w, 3, k); ``xe_w`` (B, w, 3p + 3) is the base design and residual
    with the axes flattened. Two batched matrix products over every pair of axes, the
    cross-axis blocks dropped: XLA's CPU dot runs them faster than per-axis contractions
    over the window."""
    b, w, _, k = zw.shape
    p = (xe_w.shape[-1] - 3) // 3
    zf = zw.reshape(b, w, 3 * k)
    dims = (((1,), (1,)), ((0,), (0,)))
    zz = jax.lax.dot_general(zf, zf, dims).reshape(b, 3, k, 3, k)
    zxe = jax.lax.dot_general(zf, xe_w, dims)  # (B, 3k, 3p + 3)
    zx = zxe[..., : 3 * p].reshape(b, 3, k, 3, p)
    ze = zxe[..., 3 * p:].reshape(b, 3, k, 3)
    return own_axis(zx), own_axis(zz), own_axis(ze)


def own_axis(a):
    """(B, 3, k, 3, ...) -> (B, 3, k, ...): the products of axis i with axis i."""
    return jnp.moveaxis(jnp.diagonal(a, axis1=1, axis2=3), -1, 1)


def design_and_residual(xb, e, idx, inside):
    """The base design (n, 3, p) and residual (n, 3) as every block sum reads them: one
    window layout (B, w, 3p + 3), the axes flattened, zero outside the blocks."""
    xb = jnp.where(jnp.isfinite(xb), xb, 0.0)
    return window(jnp.concatenate([xb.reshape(xb.shape[0], -1), e], axis=-1), idx, inside)


@functools.partial(jax.jit, static_argnums=2)
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


def _scores_on(thetas, windowed, base, xe_w, n_folds):
    """Scores of every θ row of ``thetas``; ``windowed(θ)``: the column set in the window
    layout (B, w, 3, k), formed one θ at a time."""
    sums = jax.lax.map(lambda th: column_sums(windowed(th), xe_w), thetas)
    return jax.vmap(lambda s: score_set(base, s, n_folds))(sums)


def _vertex(costs, i, grid):
    """Parabola vertex through grid points i−1, i, i+1 (one time constant)."""
    i = jnp.clip(i, 1, grid.shape[0] - 2)
    c0, c1, c2 = costs[i - 1], costs[i], costs[i + 1]
    den = c0 - 2.0 * c1 + c2
    off = jnp.where((den > 0) & jnp.isfinite(den), 0.5 * (c0 - c2) / jnp.where(den > 0, den, 1.0), 0.0)
    return grid[i, 0] + jnp.clip(off, -1.0, 1.0) * (grid[1, 0] - grid[0, 0])


def _search(grid, columns, seg: Segments, n_folds: int):
    """Each fold's time constant chosen on its training segments and the full record's
    (K + 1, q): the best grid point, then (one time constant) the parabola vertex through
    its neighbours where that scores better still."""
    b, s = seg.root.shape

    def windowed(th):
        z = columns(seg.sig, th)
        z = jnp.where(jnp.isfinite(z), z, 0.0).reshape((b, s) + z.shape[1:])
        return z * seg.root[..., None, None]

    tr, _, _, tot, _ = _scores_on(grid, windowed, seg.base, seg.xe, n_folds)
    pick = jnp.concatenate([jnp.argmin(tr, axis=0), jnp.argmin(tot)[None]])  # (K + 1,)
    cost = jnp.concatenate([tr, tot[:, None]], axis=1)  # (g, K + 1)
    chosen = grid[pick]
    if grid.shape[0] >= 3 and grid.shape[1] == 1:
        th2 = jax.vmap(_vertex, in_axes=(1, 0, None))(cost, pick, grid)[:, None]
        tr2, _, _, tot2, _ = _scores_on(th2, windowed, seg.base, seg.xe, n_folds)
        cost2 = jnp.concatenate([tr2, tot2[:, None]], axis=1)  # (K + 1, K + 1)
        own = jnp.arange(n_folds + 1)
        better = cost2[own, own] < cost[pick, own]  # keep the refinement only where it helps
        chosen = jnp.where(better[:, None], th2, chosen)
    return chosen


def candidate_scores(c, base_model, sig, theta_b, log_min_lag, base, xe_w, idx, inside,
                     seg: Segments | None, n_folds: int) -> CandidateScores:
    """The :class:`CandidateScores` of base + one candidate (``seg``: the record's
    :class:`Segments`, needed when the candidate has a time-constant grid)."""
    grid, columns = candidate_grid(c, base_model, sig, theta_b, log_min_lag)
    folds = jnp.arange(n_folds)
    fb = block_folds(base.a_b.shape[0], n_folds)

    def windowed(th):
        z = columns(sig, th)
        return window(jnp.where(jnp.isfinite(z), z, 0.0), idx, inside)

    if grid.shape[0] == 1:
        _, sh, sall, _, blk = _scores_on(grid, windowed, base, xe_w, n_folds)
        theta = grid[0] if grid.shape[1] else jnp.full((1,), jnp.nan, sig.gyro.dtype)
        return CandidateScores(sh[0], sall[0], theta, blk[0], jnp.asarray(False))
    chosen = _search(grid, columns, seg, n_folds)  # (K + 1, q)
    _, sh, sall, _, blk = _scores_on(chosen, windowed, base, xe_w, n_folds)
    theta = chosen[n_folds]
    if grid.shape[1] == 1:
        edge = theta[0] >= grid[-1, 0] - 0.5 * (grid[1, 0] - grid[0, 0])
    else:
        edge = jnp.asarray(False)
    return CandidateScores(sh[folds, folds], sall[n_folds], theta, blk[fb, jnp.arange(fb.size)], edge)


_ = (Float,)  # jaxtyping names used in annotations only
