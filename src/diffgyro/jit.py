"""``filter_jit`` that returns as soon as the call is dispatched, and compiles a
program once for all local devices.

``equinox.filter_jit`` waits for every call's result (so that its runtime
errors carry a traceback). A loop over groups of devices then runs one group
at a time: the host prepares the next group while the CPU is idle, and two
groups never share the cores. diffgyro raises no runtime errors from inside
compiled code (bad devices get a status), so it can let JAX dispatch
asynchronously, as ``jax.jit`` does. Arrays (JAX or numpy) are traced;
everything else is static, as in ``equinox.filter_jit``.

``jax.jit`` compiles a program again for every device its arguments sit on
(the device is part of the executable's options, and of the compilation
cache's key on CPU). With one CPU device per core
(:func:`diffgyro.use_cpu_cores`) that doubled every model spec's compile time
on two cores. XLA's object code does not depend on which CPU device runs it,
so the first device's executable is serialized and loaded on the others under
their own device assignment (about 0.06 s instead of a compile). Where that is
not possible each device compiles its own, as under ``jax.jit``: a JAX without
it; XLA cannot serialize its built-in sort comparators; and an executable that
came from the persistent compilation cache serializes without its kernels
(measured: "Function ... not found" when run), so only fresh compiles are copied.
"""
from __future__ import annotations

import functools
import io
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import numpy as np

#: executables kept per function (static configuration × shapes), oldest dropped first
MAX_EXECUTABLES = 64

#: how often each (function name, "compile" | "copy") happened on the per-device path
EVENTS: dict[tuple[str, str], int] = {}

_CACHE_HITS = [0]  # executables JAX loaded from the persistent compilation cache


def _on_event(event: str, **kwargs: Any) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _CACHE_HITS[0] += 1


jax.monitoring.register_event_listener(_on_event)


def filter_jit(fun: Callable[..., Any]) -> Callable[..., Any]:
    """Compile ``fun``: array leaves of its arguments traced, other leaves static
    (hashable); results are not waited for."""

    @functools.partial(jax.jit, static_argnums=(0, 1))
    def compiled(treedef, static, dynamic):
        leaves = [s if d is None else d for s, d in zip(static, dynamic)]
        args, kwargs = jax.tree.unflatten(treedef, leaves)
        return fun(*args, **kwargs)

    # (treedef, static leaves, shapes) -> {device: jax.stages.Compiled}; under None the
    # fresh compile that the other devices may load, if there is one
    executables: OrderedDict[Any, dict[Any, Any]] = OrderedDict()
    name = getattr(fun, "__name__", "fun")

    @functools.wraps(fun)
    def call(*args, **kwargs):
        treedef, static, dynamic = _split(args, kwargs)
        device = _single_device(dynamic)
        if device is None:  # numpy inputs, one local device, or arrays on several: jax.jit
            return compiled(treedef, static, dynamic)
        key = (treedef, static, _signature(dynamic))
        per_device = executables.get(key)
        if per_device is None:
            per_device = executables[key] = {}
            while len(executables) > MAX_EXECUTABLES:
                executables.popitem(last=False)
        executables.move_to_end(key)
        exe = per_device.get(device)
        if exe is None:
            source = per_device.get(None)
            exe = None if source is None else load_on(source, device)
            _count(name, "compile" if exe is None else "copy")
            if exe is None:
                hits = _CACHE_HITS[0]
                exe = compiled.lower(treedef, static, dynamic).compile()
                if _CACHE_HITS[0] == hits and None not in per_device:
                    per_device[None] = exe
            per_device[device] = exe
        return exe(_place(dynamic, device))

    call.lower = lambda *a, **k: compiled.lower(*_split(a, k))  # type: ignore[attr-defined]
    return call


def _count(name: str, event: str) -> None:
    EVENTS[(name, event)] = EVENTS.get((name, event), 0) + 1


def _split(args, kwargs):
    """(treedef, static leaves, array leaves) of the arguments; None marks the other kind."""
    leaves, treedef = jax.tree.flatten((args, kwargs))
    arrays = [eqx.is_array(x) for x in leaves]
    static = tuple(None if a else x for x, a in zip(leaves, arrays, strict=True))
    dynamic = [x if a else None for x, a in zip(leaves, arrays, strict=True)]
    return treedef, static, dynamic


def _committed(x) -> bool:
    return isinstance(x, jax.Array) and bool(getattr(x, "committed", False))


def _single_device(dynamic) -> Any:
    """The one device that the committed arrays sit on, when the process has several
    local devices of its kind; otherwise None. Uncommitted arrays follow the committed
    ones, as under ``jax.jit``."""
    device = None
    for x in dynamic:
        if not _committed(x):
            continue
        devices = x.devices()
        if len(devices) != 1:
            return None
        (d,) = devices
        if device is None:
            device = d
        elif d != device:
            return None
    if device is None or len(device.client.local_devices()) < 2:
        return None
    return device


def _place(dynamic, device) -> list:
    """Uncommitted arrays moved to ``device``: an executable loaded there takes its
    arguments there only."""
    return [x if x is None or _committed(x) else jax.device_put(x, device) for x in dynamic]


def _signature(dynamic) -> tuple:
    return tuple(None if x is None else
                 (np.shape(x), np.dtype(x.dtype), bool(getattr(x, "weak_type", False)))
                 for x in dynamic)


def load_on(compiled: Any, device: Any) -> Any:
    """``compiled`` (a single-device ``jax.stages.Compiled``) loaded on ``device`` of the
    same client without compiling: serialized, then deserialized with ``device`` as its
    device assignment. None where that is not possible (then compile instead)."""
    try:
        from jax._src import compiler
        from jax.experimental import serialize_executable as se

        payload, in_tree, out_tree = se.serialize(compiled)
        options = compiler.get_compile_options(num_replicas=1, num_partitions=1,
                                               device_assignment=np.array([[device]]))

        class _OnDevice(se._JaxPjrtUnpickler):  # every device named in the payload is `device`
            def __init__(self, file):
                super().__init__(file, device.client, [device])
                self.devices_by_id = {d.id: device for d in device.client.devices()}

            def persistent_load(self, pid):
                if pid[0] == "exec":
                    return self.backend.deserialize_executable(
                        pid[1], executable_devices=self.execution_devices,
                        compile_options=options)
                return super().persistent_load(pid)

        unloaded, args_info, no_kwargs = _OnDevice(io.BytesIO(payload)).load()
        return jax.stages.Compiled(unloaded.load(), [], in_tree.unflatten(args_info), out_tree,
                                   no_kwargs=no_kwargs)
    except Exception:  # noqa: BLE001 - not serializable, or another JAX: compile instead
        return None
