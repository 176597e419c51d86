"""The k-th smallest of a few hundred to a few thousand values, compiled (numba): the
order statistics of the motion check's rest noise (:mod:`diffgyro._window_pass`) and the
window of the host noise floor (:mod:`diffgyro._noise_passes`).

A quickselect whose partition has no branch per value: each round copies every value
to both scratch arrays and advances the one it belongs to by the comparison's result.
On noise a compare-and-branch mispredicts about half the time, and numpy's introselect
(``ndarray.partition``) costs about 9 ns a value on 1023 differences against about 3 ns
here. The value selected is an order statistic, so any exact selection gives the same
number (equal values of either sign of zero aside, which no caller tells apart).

Compiled on first use and cached on disk (``cache=True``).
"""

from __future__ import annotations

from numba import njit


@njit(cache=True, nogil=True)
def select(v, n, k, low, high):  # pragma: no cover - compiled
    """The ``k``-th smallest of ``v[:n]`` (quickselect about a median of three), ``v``
    unchanged: each round copies the values below the pivot to ``low`` and those above it
    to ``high`` (scratch of ``n`` each) without a branch per value. A NaN is neither below
    nor above any pivot: the selection still ends (with a NaN or a value of the others)."""
    src = v
    m = n
    while True:
        a, b, c = src[0], src[m // 2], src[m - 1]
        pivot = max(min(a, b), min(max(a, b), c))
        below = above = 0
        for i in range(m):  # (a write never passes the read: the pass may run in place)
            x = src[i]
            low[below] = x
            below += x < pivot
            high[above] = x
            above += x > pivot
        if k < below:
            src, m = low, below
        elif k < m - above:
            return pivot
        else:
            src, m, k = high, above, k - (m - above)


__all__ = ["select"]
