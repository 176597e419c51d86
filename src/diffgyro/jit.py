"""``filter_jit`` that returns as soon as the call is dispatched.

``equinox.filter_jit`` waits for every call's result (so that its runtime
errors carry a traceback). A loop over groups of devices then runs one group
at a time: the host prepares the next group while the CPU is idle, and two
groups never share the cores. diffgyro raises no runtime errors from inside
compiled code (bad devices get a status), so it can let JAX dispatch
asynchronously, as ``jax.jit`` does. Arrays (JAX or numpy) are traced;
everything else is static, as in ``equinox.filter_jit``.

``call.on_devices(arg_sets)`` gives one callable per argument set, compiled for
the JAX devices its arrays are on, the compilations side by side in threads
(XLA releases the GIL while it compiles): a program placed on N CPU devices is
N compilations, which would otherwise run one after the other.
"""
from __future__ import annotations

import functools
import threading
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import equinox as eqx
import jax

_MAX_EXECUTABLES = 64


def filter_jit(fun: Callable[..., Any]) -> Callable[..., Any]:
    """Compile ``fun``: array leaves of its arguments traced, other leaves static
    (hashable); results are not waited for."""

    @functools.partial(jax.jit, static_argnums=(0, 1))
    def compiled(treedef, static, dynamic):
        leaves = [s if d is None else d for s, d in zip(static, dynamic)]
        args, kwargs = jax.tree.unflatten(treedef, leaves)
        return fun(*args, **kwargs)

    executables: OrderedDict = OrderedDict()
    lock = threading.Lock()

    @functools.wraps(fun)
    def call(*args, **kwargs):
        return compiled(*_split(args, kwargs))

    def on_devices(arg_sets: list[tuple[tuple, dict]]) -> list[Callable[[], Any]]:
        """For each (args, kwargs) whose arrays are already on their JAX devices, a
        callable running ``fun`` on them; the missing executables compile in parallel."""
        split = [_split(a, k) for a, k in arg_sets]
        keys = [_key(s) for s in split]
        with lock:
            todo = {k: s for k, s in zip(keys, split) if k not in executables}
        if todo:
            with ThreadPoolExecutor(len(todo)) as pool:
                done = dict(zip(todo, pool.map(lambda s: compiled.lower(*s).compile(),
                                               todo.values())))
            with lock:
                executables.update(done)
                while len(executables) > _MAX_EXECUTABLES:
                    executables.popitem(last=False)
        with lock:
            exes = [executables[k] for k in keys]
        return [functools.partial(exe, s[2]) for exe, s in zip(exes, split)]

    call.lower = lambda *a, **k: compiled.lower(*_split(a, k))  # type: ignore[attr-defined]
    call.on_devices = on_devices  # type: ignore[attr-defined]
    return call


def _split(args, kwargs):
    """(treedef, static leaves, array leaves) of the arguments; None marks the other kind."""
    leaves, treedef = jax.tree.flatten((args, kwargs))
    arrays = [eqx.is_array(x) for x in leaves]
    static = tuple(None if a else x for x, a in zip(leaves, arrays, strict=True))
    dynamic = [x if a else None for x, a in zip(leaves, arrays, strict=True)]
    return treedef, static, dynamic


def _key(split) -> tuple:
    """What an executable depends on: structure, static leaves, and each array's shape,
    dtype and placement."""
    treedef, static, dynamic = split
    avals = tuple(None if x is None else
                  (x.shape, str(x.dtype), getattr(x, "sharding", None)) for x in dynamic)
    return treedef, static, avals
