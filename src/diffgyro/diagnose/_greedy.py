"""A greedy forward step before a random walk wins: the best term, then the best second term.

A smoother follows any slowly varying residual, so when two physical effects
are missing at once, neither closes enough of the gap alone and the random walk
would be named (a calibration that cannot compensate future data). Before the
walk wins, the device is diagnosed again with its best physical term added
(the same folds: the nested :func:`~diffgyro.diagnose.diagnose` cuts the
blocks from the same valid samples); when that diagnosis names a deterministic
second term, the pair's per-fold held-out errors go back to the first decision,
which prefers the pair to the walk when it closes ``rw_prefer`` of the base
model's gap (:func:`diffgyro.diagnose._decision.decide`; the ``rw_ratio``
alternative a single term has is not offered to a pair, which has twice the
freedom to follow a wandering residual). The verdict then names the first
term, and ``next`` the second one the next round is expected to add.

A term with a time constant as the first term keeps the base fit's time
constant in the pair (chosen on every fold), so the pair is very slightly
favoured there; a linear first term gives the pair exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._decision import SLOW_EDGE
from ._results import Candidate, DeviceDiagnosis


@dataclass(frozen=True)
class Pair:
    """Base + ``first`` + ``second``: per-fold held-out SSE (K, 3), full-fit SSE (3,)."""

    first: str          # spec of base + first term
    second: Candidate   # the nested diagnosis's best (relative to base + first)
    fold_sse: np.ndarray
    full_sse: np.ndarray


def walk_wins(d: DeviceDiagnosis) -> Candidate | None:
    """The best physical term of a device whose verdict names the random walk, else None."""
    if d.best is None or not d.best.stochastic:
        return None
    physical = [c for c in d.candidates if c.significant and not c.stochastic
                and c.note != SLOW_EDGE]
    return min(physical, key=lambda c: c.heldout_rms) if physical else None


def pairs(devices: list[DeviceDiagnosis], batch, candidates, thresholds, fit_options: dict,
          diagnose_fn) -> dict[int, Pair]:
    """Per device index where the walk wins: the pair (first term, best second term), from one
    nested diagnosis per distinct first term on the sub-batch of its devices."""
    groups: dict[str, list[int]] = {}
    for i, d in enumerate(devices):
        first = walk_wins(d)
        if first is not None:
            groups.setdefault(first.spec, []).append(i)
    out: dict[int, Pair] = {}
    for spec, idx in groups.items():
        nested = diagnose_fn(spec, batch.select(idx), candidates, thresholds=thresholds,
                             greedy=False, **fit_options)
        specs = [c.spec for c in nested.raw["candidates"]]
        for k, i in enumerate(idx):
            second = nested.devices[k].best
            if second is None or second.stochastic or second.spec not in specs:
                continue
            j = specs.index(second.spec)
            out[i] = Pair(first=spec, second=second, fold_sse=nested.raw["cand_sse"][k, j],
                          full_sse=nested.raw["cand_full"][k, j])
    return out
