"""diffgyro: gyroscope and IMU calibration with differentiable, composable error models.

Calibration needs float64. diffgyro does not flip JAX's global switch on
import; call :func:`enable_x64` once (the command line does) or set
``JAX_ENABLE_X64=1`` before importing JAX.
"""

from __future__ import annotations

import importlib
import os
from importlib.metadata import PackageNotFoundError, version

from ._jax_setup import FLOAT64, cache_settings

try:
    __version__ = version("diffgyro")
except PackageNotFoundError:  # running from a source tree
    __version__ = "0.0.0+unknown"


def enable_x64() -> None:
    """Turn on JAX float64 (a process-wide setting; calibration needs it)."""
    import jax

    for name, value in FLOAT64.items():
        jax.config.update(name, value)


def enable_compilation_cache(path: str | None = None) -> None:
    """Keep compiled functions on disk between processes (on for the CLI and tests).

    **Arguments:**

    - ``path``: the cache's folder (default: ``$DIFFGYRO_CACHE_DIR``, else
      ``~/.cache/diffgyro/jax``).
    """

    import jax

    try:
        for name, value in cache_settings(path).items():
            jax.config.update(name, value)
    except Exception:  # a read-only home must not stop a calibration
        pass


def use_cpu_cores(n: int | None = None) -> int:
    """One XLA CPU device per core (``n``, default the cores this process may run on,
    at most 16), for user code that maps over devices. diffgyro itself keeps to one
    CPU device: programs running side by side on two XLA CPU devices deadlocked
    (fit()'s groups, and the streaming path's sharded chunks; the latter shard over
    CPU devices only with ``shard=True``). Process-wide, and only possible before
    JAX's first operation; a device count the user set (``XLA_FLAGS`` or
    ``jax_num_cpu_devices``) is kept. Returns the number of CPU devices.

    **Arguments:**

    - ``n``: CPU devices to make (default: the cores this process may run on, at most 16).
    """

    import jax

    if "xla_force_host_platform_device_count" not in os.environ.get("XLA_FLAGS", "") and \
            getattr(jax.config, "jax_num_cpu_devices", 0) in (-1, None):  # 0: an older JAX
        if n is None:
            from ._jit import available_cores

            n = min(available_cores(), 16)
        try:
            jax.config.update("jax_num_cpu_devices", max(int(n), 1))
        except RuntimeError:  # JAX already started: its devices stay
            pass
    return len(jax.devices("cpu"))


from .errors import DataError, SpecError  # noqa: E402  (no JAX: the CLI's errors)

#: The public modules, each listing its names in ``__all__`` (the API reference shows
#: these names, in that order; tests/test_architecture.py checks the list against the
#: source tree). Every other module is private: a leading underscore, or inside one.
PUBLIC_MODULES = (
    "diffgyro", "diffgyro.allan", "diffgyro.apply", "diffgyro.calibration", "diffgyro.carry",
    "diffgyro.channel", "diffgyro.data", "diffgyro.detect", "diffgyro.diagnose", "diffgyro.effects",
    "diffgyro.errors", "diffgyro.export", "diffgyro.export.ardupilot", "diffgyro.export.c_header",
    "diffgyro.export.ekf_noise", "diffgyro.export.kalibr", "diffgyro.export.px4", "diffgyro.fit",
    "diffgyro.io", "diffgyro.kalman", "diffgyro.limits", "diffgyro.logs", "diffgyro.model",
    "diffgyro.motion", "diffgyro.pipeline", "diffgyro.plan_design", "diffgyro.recipes",
    "diffgyro.report", "diffgyro.sensitivity", "diffgyro.signals", "diffgyro.simulate",
    "diffgyro.status", "diffgyro.stochastic",
)

#: Public names loaded on first use, so that ``import diffgyro`` (and the command
#: line's ``--help``) does not start JAX.
_LAZY = {"Batch": "data", "Recording": "data", "ErrorModel": "model", "Params": "model",
         "effects": None, "release_compiled_if_crowded": "_jit"}


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module 'diffgyro' has no attribute {name!r}")

    module = importlib.import_module(f".{_LAZY[name] or name}", __name__)
    value = module if _LAZY[name] is None else getattr(module, name)
    globals()[name] = value
    return value


__all__ = ["Batch", "DataError", "ErrorModel", "Params", "Recording", "SpecError",
           "__version__", "effects", "enable_compilation_cache", "enable_x64",
           "release_compiled_if_crowded", "use_cpu_cores"]
