"""Blocked per-fold sums: every product's total and held-out-fold sums in one pass over
the samples (an XLA variadic reduction)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax


@jax.custom_jvp
def _vsum_stacked(ops):
    zero = (jnp.zeros((), ops[0].dtype),) * len(ops)
    out = lax.reduce(tuple(ops), zero, lambda u, v: tuple(a + b for a, b in zip(u, v)),
                     (ops[0].ndim - 1,))
    return jnp.stack(out, axis=-1)


@_vsum_stacked.defjvp
def _vsum_jvp(primals, tangents):
    (ops,), (dops,) = primals, tangents
    return _vsum_stacked(ops), _vsum_stacked(dops)


def vsum(ops):
    """Sums of many arrays along their last axis in a single loop (an XLA variadic reduce),
    stacked on a new last axis."""
    return _vsum_stacked(list(ops))


def _block_positions(mask, nv, n_blocks: int):
    """First sample index of every time block of the folds (n_blocks + 1 values).

    Block b holds the valid samples of rank ceil(b·n/B) .. ceil((b+1)·n/B) − 1,
    the blocks of :func:`diffgyro._folds.fold_ids`; ranks come from a cumulative count
    (devices whose valid samples come first get the starts from the host instead).
    """
    b = jnp.arange(n_blocks + 1, dtype=jnp.int32)
    rank = (b * nv + n_blocks - 1) // n_blocks
    cm = jnp.cumsum(mask.astype(jnp.int32))
    return jnp.searchsorted(cm, rank + 1, side="left").astype(jnp.int32)


def block_starts(nv, n_blocks: int) -> np.ndarray:
    """First sample of every fold block (and the end), (devices, B + 1), when each
    device's valid samples come first: block b starts at rank ceil(b·n/B)."""
    b = np.arange(n_blocks + 1, dtype=np.int64)
    nv = np.asarray(nv, np.int64)[:, None]
    return ((b * nv + n_blocks - 1) // n_blocks).astype(np.int32)


ALIGNED = "aligned"
"""``pos`` for a group whose devices are all valid to the end of a length that the
blocks divide: block b is the samples b·w .. (b + 1)·w − 1, a reshape (no gather,
no mask)."""


def _window_sums(products, src, pos, n_blocks: int, n_folds: int):
    """Total and per-fold sums when the valid samples come first (``prefix``).

    Block b is then the samples ceil(b·n/B) .. ceil((b+1)·n/B) − 1: a window of
    ceil(length/B) samples from its start, masked past its end, covers it. One
    variadic reduction over the (B, window) gathered samples gives every block's
    sums exactly; a fold's sums are those of its blocks. The window depends only
    on the padded length, so recordings of any length in a bucket share the
    compiled function. ``pos`` (the B + 1 block starts, :func:`block_starts`) comes
    from the host: computed in the graph, XLA would recompute it for every sample.
    """
    n = jax.tree.leaves(src)[0].shape[0]
    if isinstance(pos, str):  # ALIGNED
        blocks = vsum([o.reshape(n_blocks, n // n_blocks)
                        for o in products(src, jnp.ones((n,), bool))])
        return _fold_of_blocks(blocks, n_blocks, n_folds)
    w = -(-n // n_blocks)
    start = jnp.minimum(pos[:-1], n - w)  # a window never runs past the recording
    j = start[:, None] + jnp.arange(w, dtype=jnp.int32)[None, :]
    inside = ((j >= pos[:-1, None]) & (j < pos[1:, None])).reshape(-1)

    def windows(a):
        if a.ndim >= 1 and a.shape[0] == n:
            cut = jax.vmap(lambda s_: lax.dynamic_slice_in_dim(a, s_, w, axis=0))(start)
            return cut.reshape(n_blocks * w, *a.shape[1:])
        return a

    blocks = vsum([o.reshape(n_blocks, w) for o in products(jax.tree.map(windows, src), inside)])
    return _fold_of_blocks(blocks, n_blocks, n_folds)


def _fold_of_blocks(blocks, n_blocks: int, n_folds: int):
    """Total and per-fold sums from the sums of every block (B, F); block b is in fold b mod K."""
    b = jnp.arange(n_blocks, dtype=jnp.int32)
    own = ((b % n_folds)[None, :] == jnp.arange(n_folds, dtype=jnp.int32)[:, None])
    return jnp.sum(blocks, axis=0), own.astype(blocks.dtype) @ blocks


def fold_sums(products, src, mask, nv, n_blocks: int, n_folds: int, c: int, pos=None):
    """Total and per-fold sums of every product, reading the samples once.

    ``products(src, mask)`` gives the per-sample products of ``src`` (a pytree
    of arrays with the sample axis first). Chunks of ``c`` samples (no longer
    than the shortest block) are summed in one variadic reduction and credited
    to the fold of their first sample. The chunks a block boundary cuts are
    summed again up to the boundary (a second, small reduction over just those
    chunks, gathered from ``src``) and the rest is moved to the next block's fold.
    Given the block starts ``pos`` (valid samples first), the blocks are summed in
    windows instead (:func:`_window_sums`).
    """
    if pos is not None:
        return _window_sums(products, src, pos, n_blocks, n_folds)
    n = mask.shape[0]
    nc = n // c
    ops = products(src, mask)
    tot = vsum([o.reshape(nc, c) for o in ops])  # (nc, F)
    pos = _block_positions(mask, nv, n_blocks)
    starts = jnp.arange(nc, dtype=jnp.int32) * c
    blk = jnp.searchsorted(pos, starts, side="right").astype(jnp.int32) - 1
    folds = jnp.arange(n_folds, dtype=jnp.int32)
    per_fold = ((blk % n_folds)[None, :] == folds[:, None]).astype(tot.dtype) @ tot
    # chunks cut by a block's start: sum the part before it once more
    p = pos[:-1]
    ch = jnp.minimum(p // c, nc - 1)
    cut = (p % c != 0) & (p < n)
    idx = (ch[:, None] * c + jnp.arange(c, dtype=jnp.int32)[None, :]).reshape(-1)
    head_mask = (idx.reshape(-1, c) < p[:, None]).reshape(-1) & mask[idx]
    src_h = jax.tree.map(lambda a: a[idx] if (a.ndim >= 1 and a.shape[0] == n) else a, src)
    head = vsum([o.reshape(-1, c) for o in products(src_h, head_mask)])
    late = jnp.where(cut[:, None], tot[ch] - head, 0.0)  # belongs to the next block
    b = jnp.arange(n_blocks, dtype=jnp.int32)  # block -1 (before the first valid sample) is fold -1
    move = (((b % n_folds)[None, :] == folds[:, None]).astype(late.dtype)
            - (((b - 1) % n_folds)[None, :] == folds[:, None]).astype(late.dtype))
    return jnp.sum(tot, axis=0), per_fold + move @ late



def chunked_sum(ops, c: int):
    """Sums of the (n,) arrays ``ops`` in one loop, by chunks of ``c`` then over chunks
    (a short sum per chunk keeps the rounding of a long sum down)."""
    n = ops[0].shape[0]
    return jnp.sum(vsum([o.reshape(n // c, c) for o in ops]), axis=0)
