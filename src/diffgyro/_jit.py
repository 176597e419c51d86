"""``filter_jit`` that returns as soon as the call is dispatched.

``equinox.filter_jit`` waits for every call's result (so that its runtime
errors carry a traceback). A loop over groups of devices then runs one group
at a time: the host prepares the next group while the CPU is idle, and two
groups never share the cores. diffgyro raises no runtime errors from inside
compiled code (bad devices get a status), so it can let JAX dispatch
asynchronously, as ``jax.jit`` does. Arrays (JAX or numpy) are traced;
everything else is static, as in ``equinox.filter_jit``. XLA options can be
given per program (``filter_jit(compiler_options=...)``), ``eval_shape``
gives a call's result shapes from its cached trace, and ``compile_ahead``
compiles a call on another thread.

:func:`release_compiled_if_crowded` drops compiled programs before a process
runs out of memory mappings (XLA's CPU JIT maps every kernel separately).
"""
from __future__ import annotations

import collections
import contextlib
import functools
import gc
import logging
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import equinox as eqx
import jax

from . import _jax_setup
from ._program_cache import program
from ._xla_options import ONCE, SMALL_WORK, accepted, refuse


def filter_jit(fun: Callable[..., Any] | None = None, *,
               compiler_options: dict[str, Any] | None = None,
               persistent: bool | None = None) -> Callable[..., Any]:
    """Compile ``fun``: array leaves of its arguments traced, other leaves static
    (hashable); results are not waited for. ``compiler_options`` go to XLA for this
    program only (``filter_jit(compiler_options=...)`` decorates). ``persistent``: the
    traced program is kept on disk for later processes (:mod:`diffgyro._program_cache`;
    results must be dicts, lists and tuples of arrays, else it is traced as usual); None:
    when :data:`diffgyro._jax_setup.store_programs` says so (the command line) and the
    backend is the CPU."""
    if fun is None:
        return functools.partial(filter_jit, compiler_options=compiler_options,
                                 persistent=persistent)

    def body(treedef, static, dynamic):
        return _unsplit(fun, treedef, static, dynamic)

    # the options are XLA:CPU's (diffgyro._xla_options): another backend
    # refuses an option it does not know, so there the program compiles with defaults (and
    # so does a call inside another trace); on the CPU, without those this XLA refused
    elsewhere = jax.jit(body, static_argnums=(0, 1))
    by_options: dict = {}

    def on_cpu():
        options = accepted(compiler_options)
        if options is None:
            return elsewhere
        key = tuple(sorted(options.items()))
        if key not in by_options:
            by_options[key] = jax.jit(body, static_argnums=(0, 1), compiler_options=options)
        return by_options[key]

    def program_for(args, kwargs):
        """(program, its arguments) for this call: the one kept on disk
        (:mod:`diffgyro._program_cache`) where there is one, else the traced one."""
        treedef, static, dynamic = _split(args, kwargs)
        cpu = jax.default_backend() == "cpu"
        inside = any(isinstance(d, jax.core.Tracer) for d in dynamic)  # part of another trace
        if not inside and (persistent or (persistent is None and _jax_setup.store_programs
                                          and cpu)):
            with collector_paused():  # a new program is traced and exported here
                kept = program(fun, treedef, static, dynamic,
                               functools.partial(_unsplit, fun, treedef, static),
                               options=accepted(compiler_options) if cpu else None)
            if kept is not None:
                return kept, (dynamic,)
        # inside another trace the program is part of that one, whose options hold (JAX
        # refuses options on a nested jit)
        return (on_cpu() if cpu and not inside else elsewhere), (treedef, static, dynamic)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        while True:
            jitted, parts = program_for(args, kwargs)
            try:
                return jitted(*parts)
            except jax.errors.JaxRuntimeError as error:
                if not refuse(error):  # an option this XLA does not know: again without it
                    raise

    def lower(*args, **kwargs):
        jitted, parts = program_for(args, kwargs)
        return jitted.lower(*parts)

    def eval_shape(*args, **kwargs):
        """Shapes and dtypes of the results, from the same (cached) trace as a call, or
        from a kept program's signature (no trace)."""
        jitted, parts = program_for(args, kwargs)
        return jitted.eval_shape(*parts)

    call.lower = lower  # type: ignore[attr-defined]
    call.compile_ahead = _compile_ahead(fun.__name__, lower)  # type: ignore[attr-defined]
    call.eval_shape = eval_shape  # type: ignore[attr-defined]
    return call


def by_work(fun: Callable[..., Any], *, compiler_options: dict[str, Any] | None = None,
            persistent: bool | None = None, small_options: dict[str, Any] | None = None
            ) -> Callable[[int], Callable[..., Any]]:
    """``fun`` compiled (:func:`filter_jit`) for the size of the batch it runs: a function of
    the batch's samples (devices × samples, or series × samples) that gives the program
    compiled with ``compiler_options``, or for a batch of at most
    :data:`~diffgyro._xla_options.SMALL_WORK` the one compiled without optimisation
    (:data:`~diffgyro._xla_options.ONCE`): it compiles in a fraction of the time, and at
    that size runs in milliseconds either way.

    **Arguments:**

    - ``fun``: the function to compile.
    - ``compiler_options``: XLA's options for a larger batch (:func:`filter_jit`).
    - ``persistent``: whether the traced programs are kept on disk (:func:`filter_jit`).
    - ``small_options``: XLA's options added for the small batch's program.
    """
    large = filter_jit(fun, compiler_options=compiler_options, persistent=persistent)
    small = filter_jit(fun, compiler_options={**(compiler_options or {}), **ONCE,
                                              **(small_options or {})},
                       persistent=persistent)

    def for_work(samples: int) -> Callable[..., Any]:
        return small if samples <= SMALL_WORK else large

    return for_work


def signature(*args, **kwargs) -> tuple:
    """What a call of a :func:`filter_jit` program is compiled for: the argument tree, the
    static leaves and every array's shape and dtype (a ``jax.ShapeDtypeStruct`` counts as
    the array it stands for). Two calls with equal signatures run one compiled program."""
    treedef, static, dynamic = _split(args, kwargs)
    return treedef, static, tuple(None if x is None else (tuple(x.shape), str(x.dtype))
                                  for x in dynamic)


def _compile_ahead(name: str, lower: Callable) -> Callable[..., threading.Thread]:
    """A program's ``compile_ahead`` (``lower``: its arguments to a lowered program)."""
    ahead: dict = {}  # signature -> the thread that compiled (or compiles) it, this process

    def compile_ahead(*a, **k) -> threading.Thread:
        """Lower the call for these arguments here and compile it on a thread of its own;
        join the thread before the call (which then finds the program compiled). XLA
        compiles without the GIL, so this overlaps with Python tracing another program
        (lowering is Python: done on the thread it would hold the GIL the other needs).
        A signature compiled ahead before is not lowered again: its thread is returned,
        so a second caller waits for the compilation the first started instead of
        compiling the program a second time. An error is left for the call itself to
        raise."""
        log = logging.getLogger("diffgyro")
        key = (signature(*a, **k), jax.default_backend())
        if key in ahead:
            return ahead[key]
        try:
            lowered = lower(*a, **k)
        except Exception:  # noqa: BLE001 - the call lowers again and raises it
            log.debug("compile_ahead of %s failed", name, exc_info=True)
            lowered = None

        def work():
            try:
                if lowered is not None:
                    lowered.compile()
            except Exception:  # noqa: BLE001 - the call compiles again and raises it
                log.debug("compile_ahead of %s failed", name, exc_info=True)

        thread = threading.Thread(target=work, name=f"compile {name}", daemon=True)
        ahead[key] = thread
        thread.start()
        return thread

    return compile_ahead


@contextlib.contextmanager
def collector_paused():
    """Pause Python's cyclic garbage collector while programs are traced and compiled.

    Tracing allocates objects by the hundred thousand, so the collector runs
    over and over and walks the whole heap each time it reaches the oldest
    generation: 0.14 s of a 2.3 s first fit of bias_poly(1)+thermal_lag
    (154 collections). Reference counting still frees what is not in a cycle;
    the rest waits for the next collection after the block. Process-wide while
    it lasts, so keep the block to the compile.
    """
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def parallel_devices() -> list:
    """The local JAX devices that compiled calls may run on side by side: every
    accelerator, but one CPU device. Programs running side by side on two XLA CPU
    devices deadlocked (jaxlib 0.10.2: fog-one-run's regression, 256 devices × 2000 samples,
    every run, both as fit()'s groups taking turns and as one program sharded over a
    mesh; all worker threads idle, the caller waiting on a result; also with
    transfers finished before dispatch, without the thunk runtime and with
    single-threaded Eigen)."""
    devices = jax.local_devices()
    return devices[:1] if devices[0].platform == "cpu" else devices


def available_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS tells it)."""
    cores = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
    return max(1, len(cores) if cores else (os.cpu_count() or 1))


#: The host's worker threads kept for the process, by (name, size): :func:`host_pool`.
_POOLS: dict[tuple[str, int], ThreadPoolExecutor] = {}
_POOLS_LOCK = threading.Lock()


def host_pool(name: str, workers: int | None = None) -> ThreadPoolExecutor:
    """Worker threads for the host's compiled passes (numba, numpy: they hold no GIL), kept
    for the process: one pool per ``name`` and size (default: a thread per core this
    process may run on). A fit reads its samples in several passes, each split over the
    cores; a pool started for each one cost its start-up, and on busy cores the caller
    waited for every new thread to be scheduled before it could hand out work. A forked
    child starts its own pools.

    **Arguments:**

    - ``name``: what the pool runs (its threads are named ``diffgyro-NAME``); work of
      different names never waits behind each other's.
    - ``workers``: the number of threads (default: :func:`available_cores`).
    """
    key = (name, workers or available_cores())
    with _POOLS_LOCK:
        pool = _POOLS.get(key)
        if pool is None:
            pool = _POOLS[key] = ThreadPoolExecutor(key[1], thread_name_prefix=f"diffgyro-{name}")
    return pool


def on_threads(rows: int, work: int, run: Callable[[int, int], Any], name: str,
               minimum: int) -> None:
    """``run(a, b)`` over chunks of ``rows`` side by side on the threads of
    :func:`host_pool` ``name`` (a compiled pass that holds no GIL), one chunk per core, or
    on the caller's thread where ``rows × work`` is below ``minimum`` (starting threads
    costs about what that much work does).

    **Arguments:**

    - ``rows``: the devices (or rows) to split.
    - ``work``: the work per row, in the unit of ``minimum`` (samples, windows).
    - ``run``: the pass over rows ``a`` to ``b``.
    - ``name``: the pool's name.
    - ``minimum``: the work below which no thread is started.
    """
    parts = min(available_cores(), rows) if rows * work >= minimum else 1
    if parts <= 1:
        run(0, rows)
        return
    cuts = [rows * i // parts for i in range(parts + 1)]
    pool = host_pool(name)
    for job in [pool.submit(run, a, b) for a, b in zip(cuts[:-1], cuts[1:])]:
        job.result()


def shutdown_pools() -> None:
    """End the kept pools' threads (each waits for its work): a process that ends without
    the interpreter's teardown joins its threads first, and an idle pool's never end."""
    with _POOLS_LOCK:
        pools = list(_POOLS.values())
        _POOLS.clear()
    for pool in pools:
        pool.shutdown(wait=True)


_jax_setup.before_exit.append(shutdown_pools)


def _forget_pools() -> None:
    """In a forked child: the parent's threads are not there (nor may its lock be free)."""
    global _POOLS_LOCK
    _POOLS.clear()
    _POOLS_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pools)


#: How often each compiled batch function was traced (tests check that a new batch
#: size within a bucket does not compile again).
TRACE_COUNTS: collections.Counter = collections.Counter()
MAP_HEADROOM = 0.5  # share of vm.max_map_count past which compiled programs are dropped


@functools.cache
def map_limit() -> int | None:
    """The kernel's limit on a process's memory mappings (``vm.max_map_count``), or None
    where it can not be read (not Linux)."""
    try:
        with open("/proc/sys/vm/max_map_count") as f:
            return int(f.read())
    except (OSError, ValueError):
        return None


def mapped_regions() -> int | None:
    """How many memory mappings this process holds now (None where it can not be read)."""
    try:
        with open("/proc/self/maps", "rb") as f:
            return f.read().count(b"\n")
    except OSError:
        return None


_last_check = [-float("inf")]


def release_compiled_if_crowded(fraction: float = MAP_HEADROOM, limit: int | None = None,
                                interval: float = 0.0) -> bool:
    """Drop JAX's compiled programs if this process holds more than ``fraction`` of the
    mappings the kernel allows (``limit``, default ``vm.max_map_count``); True if it did.
    With ``interval`` (s), a check within that time of the last one returns at once
    (counting 30 000 mappings takes about 30 ms; compiling 1000 more takes seconds).

    XLA's CPU JIT maps each compiled kernel's sections on their own: the programs
    of one thermal_lag fit hold about 1000 mappings, bias_poly(3)'s about 270, and
    they stay while the program is cached. A process that compiles a few hundred
    programs (a test worker, a service calibrating many model specs) reaches the
    limit (65530 by default); the JIT then can not load new kernels ("Failed to
    materialize symbols") and jaxlib 0.10.2 segfaulted unwinding that error.
    Clearing JAX's caches unmaps them; later calls compile again, or load from the
    persistent compilation cache.

    **Arguments:**

    - ``fraction``: the share of the kernel's mapping limit above which the programs are
      dropped.
    - ``limit``: the limit (default: ``vm.max_map_count``).
    - ``interval``: seconds within which a second check returns at once.
    """
    now = time.monotonic()
    if now - _last_check[0] < interval:
        return False
    _last_check[0] = now
    limit = map_limit() if limit is None else limit
    held = mapped_regions()
    if limit is None or held is None or held <= fraction * limit:
        return False
    jax.clear_caches()
    gc.collect()
    logging.getLogger("diffgyro").info(
        "released compiled programs: %d memory mappings of %d allowed, now %s",
        held, limit, mapped_regions())
    return True


def _unsplit(fun, treedef, static, dynamic):
    """``fun`` called on the arguments :func:`_split` took apart."""
    leaves = [s if d is None else d for s, d in zip(static, dynamic, strict=True)]
    args, kwargs = jax.tree.unflatten(treedef, leaves)
    return fun(*args, **kwargs)


def _split(args, kwargs):
    """(treedef, static leaves, array leaves) of the arguments; None marks the other kind.
    A ``jax.ShapeDtypeStruct`` stands for an array (``lower``, ``compile_ahead``)."""
    leaves, treedef = jax.tree.flatten((args, kwargs))
    arrays = [eqx.is_array(x) or isinstance(x, jax.ShapeDtypeStruct) for x in leaves]
    static = tuple(None if a else x for x, a in zip(leaves, arrays, strict=True))
    dynamic = [x if a else None for x, a in zip(leaves, arrays, strict=True)]
    return treedef, static, dynamic
