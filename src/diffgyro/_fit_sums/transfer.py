"""Groups' inputs sent to an accelerator ahead of their programs, from host threads.

A transfer from pageable host memory is staged through pinned memory by the thread that
asks for it, and one thread stages far below the link's rate; several threads sending the
next groups while the accelerator fits the current one keep the link busy. A CPU reads
the host's arrays where they are: there the groups are prepared in turn, in the caller.
"""

from __future__ import annotations

import collections
from collections.abc import Callable, Iterator
from typing import Any

from .._jit import host_pool

#: Host threads sending groups to an accelerator (each keeps two groups in flight).
TRANSFER_THREADS = 4


def in_order(send: Callable[[int], Any], count: int, platform: str,
             threads: int | None = None) -> Iterator[Any]:
    """``send(j)`` for j = 0 … count − 1, in order; on an accelerator computed ahead on
    ``threads`` host threads (:data:`TRANSFER_THREADS`, a kept pool:
    :func:`diffgyro._jit.host_pool`), at most twice as many ahead."""
    threads = TRANSFER_THREADS if threads is None else threads
    if platform == "cpu" or threads <= 1 or count <= 1:
        for j in range(count):
            yield send(j)
        return
    pool = host_pool("send", threads)
    ahead = collections.deque(pool.submit(send, j) for j in range(min(count, 2 * threads)))
    following = len(ahead)
    while ahead:
        sent = ahead.popleft().result()
        if following < count:
            ahead.append(pool.submit(send, following))
            following += 1
        yield sent
