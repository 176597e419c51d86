"""The random-walk check: a local-level smoother of the base residual, scored on held-out folds.

The walk is fitted to each fold's training residual (the base model fitted
without that fold) with the white variance fixed at the noise floor and the
walk variance chosen by maximum likelihood on the training blocks; the
smoothed level is the prediction on the held-out fold.

**Block-averaged residual.** A record longer than :data:`RW_POINTS` samples is
smoothed on the means of segments of ``m`` consecutive valid samples, each
inside one fold block (``m`` is the smallest that keeps the series within
``RW_POINTS``; ``m = 1``, the sample-level smoother, below it). A segment mean
of ``n_s`` samples is one observation of the level with white variance
``r / n_s``; the level is taken as constant over the segment, which holds when
the walk moves little in ``m`` samples against the white noise — the regime
where a walk can be told from white noise at all. The held-out SSE splits
exactly into the scatter inside each segment (from the base fit's held-out
sums) and ``n_s`` times the squared distance of the segment mean from the
level: ``Σ_i (e_i − μ_s)² = Σ_i (e_i − ē_s)² + n_s (ē_s − μ_s)²``. So memory
and time are bounded whatever the record length.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array

from ._scoring import block_folds, segment_sums
from ._scoring import segment_length as scoring_segment_length
from ._thresholds import RW_GRID

#: Longest series (segments of every block) the smoother runs on.
RW_POINTS = 1 << 12


def segment_length(length: int, n_blocks: int, points: int | None = None) -> int:
    """Samples per segment mean: 1 when the record fits in ``points`` (:data:`RW_POINTS`)."""
    return scoring_segment_length(length, n_blocks, RW_POINTS if points is None else points)


def local_level(e, obs, cnt, t, r, q_rel, p0, dt0, keep: bool = True):
    """Local-level (random-walk + white) filter on ``e`` (n, s), one series per column.

    Each step is the mean of ``cnt`` (n,) samples (white variance ``r / cnt``);
    ``r`` (s,) is the white variance of one sample, ``q_rel`` (s,) or (grid, s) the
    walk variance per sample interval ``dt0`` as a fraction of r (a grid runs every
    value at once without copying the data). Returns filtered mean, variance,
    predicted variance (n, s) and the log-likelihood of the observed steps.
    """
    q = q_rel * r / dt0

    def step(carry, inp):
        a, p, t_prev, ll = carry
        ek, ok, nk, tk = inp
        pp = p + q * jnp.maximum(tk - t_prev, 0.0)
        rk = r / jnp.maximum(nk, 1.0)
        f = pp + rk
        k = pp / f
        innov = ek - a
        a = jnp.where(ok, a + k * innov, a)
        p = jnp.where(ok, pp * rk / f, pp)
        ll = ll + jnp.where(ok, -0.5 * (jnp.log(f) + innov**2 / f), 0.0)
        return (a, p, tk, ll), ((a, p, pp) if keep else None)

    shape = jnp.broadcast_shapes(jnp.shape(q), (e.shape[1],))  # (s,) or (grid, s)
    init = (jnp.zeros(shape, e.dtype), jnp.full(shape, p0, e.dtype), t[0], jnp.zeros(shape, e.dtype))
    (_, _, _, ll), outs = jax.lax.scan(step, init, (e, obs, cnt, t))
    if not keep:
        return None, None, None, ll
    mf, pf, pp = outs
    return mf, pf, pp, ll


def rts(mf, pf, pp):
    """Rauch–Tung–Striebel smoother for the local level (n, s)."""

    def back(carry, inp):
        ms_next = carry
        m_k, p_k, pp_next = inp
        g = p_k / jnp.maximum(pp_next, 1e-300)
        ms = m_k + g * (ms_next - m_k)
        return ms, ms

    _, ms = jax.lax.scan(back, mf[-1], (mf[:-1], pf[:-1], pp[1:]), reverse=True)
    return jnp.concatenate([ms, mf[-1:]], axis=0)


def _series(xe_w, t_w, inside, b_base, m: int):
    """Segment means of each fold's training residual and of the full-fit residual
    (K + 1, N, 3), the segment counts (N,), times (N,) and folds (N,)."""
    n_blocks = xe_w.shape[0]
    n_folds, _, p = b_base.shape
    cnt = segment_sums(inside.astype(xe_w.dtype), m)  # (B, S)
    den = jnp.maximum(cnt, 1.0)
    xe_s = segment_sums(xe_w, m) / den[..., None]
    x_s = xe_s[..., : 3 * p].reshape(xe_s.shape[:2] + (3, p))
    e_s = xe_s[..., 3 * p:]
    t_s = segment_sums(jnp.where(inside, t_w, 0.0), m) / den
    fold_s = jnp.broadcast_to(jnp.asarray(block_folds(n_blocks, n_folds))[:, None], cnt.shape)
    flat = lambda a: a.reshape((-1,) + a.shape[2:])  # noqa: E731
    e_s, x_s, cnt, fold_s, t_s = flat(e_s), flat(x_s), flat(cnt), flat(fold_s), flat(t_s)
    # an empty segment keeps the time of the last observed one (no walk across it)
    t_s = jax.lax.cummax(jnp.where(cnt > 0, t_s, -jnp.inf))
    t_s = jnp.where(jnp.isfinite(t_s), t_s, 0.0)
    e_f = e_s[None] - jnp.einsum("nip,fip->fni", x_s, b_base)  # (K, N, 3)
    return jnp.concatenate([e_f, e_s[None]], axis=0), cnt, t_s, fold_s


class RandomWalkScores(eqx.Module):
    """The local-level smoother on the base residual: held-out SSE per fold, smoothed
    ``rw_interp`` and forecast ``rw_fore`` (K, 3), the full-record SSE ``rw_full`` (3,), the
    walk variance ``rw_q`` (3,, (rad/s)²/s) and every block's held-out SSE ``rw_blk`` (B,)."""

    rw_interp: Array
    rw_fore: Array
    rw_full: Array
    rw_q: Array
    rw_blk: Array


def random_walk_scores(xe_w, t_w, inside, b_base, base_sse, base_blk, base_full,
                       floor_axes, dt0, m: int) -> RandomWalkScores:
    """Held-out (smoothed and forecast) SSE per fold (K, 3), the full-record SSE (3,), the
    walk variance (3,) and every block's held-out SSE (B,) of the local-level smoother."""
    n_folds = b_base.shape[0]
    dtype = xe_w.dtype
    e_all, cnt, t_s, fold_s = _series(xe_w, t_w, inside, b_base, m)
    n, s_f = cnt.shape[0], n_folds + 1
    r = jnp.maximum(floor_axes**2, 1e-300)
    obs = jnp.concatenate([(fold_s[None, :] != jnp.arange(n_folds)[:, None]) & (cnt[None] > 0),
                           (cnt > 0)[None]], axis=0)  # (K + 1, N)
    qg = jnp.asarray(RW_GRID, dtype)
    n_q = qg.shape[0]
    e2 = e_all.transpose(1, 0, 2).reshape(n, -1)  # (N, (K + 1)·3)
    o2 = jnp.broadcast_to(obs.T[:, :, None], (n, s_f, 3)).reshape(n, -1)
    r2 = jnp.broadcast_to(r, (s_f, 3)).reshape(-1)
    n_valid = jnp.maximum(jnp.sum(inside), 1)
    p0 = 10.0 * jnp.maximum(jnp.sum(base_full) / (3 * n_valid), jnp.max(r))
    _, _, _, ll = local_level(e2, o2, cnt, t_s, r2, jnp.broadcast_to(qg[:, None], (n_q, r2.shape[0])),
                              p0, dt0, keep=False)
    qi = jnp.argmax(ll.reshape(n_q, s_f, 3), axis=0)  # (K + 1, 3)
    mf, pf, pp, _ = local_level(e2, o2, cnt, t_s, r2, qg[qi].reshape(-1), p0, dt0)
    ms = rts(mf, pf, pp)
    ms3 = ms.reshape(n, s_f, 3).transpose(1, 0, 2)
    mf3 = mf.reshape(n, s_f, 3).transpose(1, 0, 2)
    held = (fold_s[None, :] == jnp.arange(n_folds)[:, None])[..., None] * cnt[None, :, None]  # (K, N, 1)
    e_f = e_all[:n_folds]
    # held-out SSE = the scatter inside each segment (base SSE − Σ n ē²) + Σ n (ē − level)²
    inner = base_sse - jnp.sum(held * e_f**2, axis=1)  # (K, 3)
    rw_interp = inner + jnp.sum(held * (e_f - ms3[:n_folds]) ** 2, axis=1)
    rw_fore = inner + jnp.sum(held * (e_f - mf3[:n_folds]) ** 2, axis=1)
    full_inner = base_full - jnp.sum(cnt[:, None] * e_all[n_folds] ** 2, axis=0)
    rw_full = full_inner + jnp.sum(cnt[:, None] * (e_all[n_folds] - ms3[n_folds]) ** 2, axis=0)
    # per block: its fold's series, segments grouped by block
    n_blocks = base_blk.shape[0]
    own = jnp.sum(held * ((e_f - ms3[:n_folds]) ** 2 - e_f**2), axis=(0, 2))  # (N,)
    rw_blk = base_blk + own.reshape(n_blocks, -1).sum(-1)
    rw_q = qg[qi[n_folds]] * r / dt0  # (3,) (rad/s)²/s
    return RandomWalkScores(rw_interp, rw_fore, rw_full, rw_q, rw_blk)

