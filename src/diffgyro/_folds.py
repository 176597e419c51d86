"""The held-out fold partition every fit path scores with.

Contiguous time blocks dealt round-robin to folds: each fold sees every part of
the recording (so a trend is never extrapolated), and neighbouring samples, whose
noise is correlated, stay in one block. The direct path (:mod:`diffgyro.fit`),
the sums path (:mod:`diffgyro._fit_sums`), the random-walk fit
(:mod:`diffgyro.kalman`) and diagnose's window sums read the same partition, so
their held-out numbers mean the same thing.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Int


def fold_ids(mask: Bool[Array, " n"], n_blocks: int, n_folds: int) -> Int[Array, " n"]:
    """Fold of every valid sample: contiguous time blocks dealt round-robin to folds
    (-1 where not valid)."""
    k = jnp.cumsum(mask) - 1
    n_valid = jnp.maximum(jnp.sum(mask), 1)
    block = (k * n_blocks) // n_valid
    return jnp.where(mask, block % n_folds, -1)
