"""Fit one chunk of devices with a compiled function reused across chunks, sharded
over the local JAX devices.

With one JAX device a chunk goes through :func:`diffgyro.fit.fit` itself
(which keeps compiled shapes fixed: device groups, device buckets), one
device group at a time. With several JAX devices it takes the sharded direct
path of this module (:func:`diffgyro.fit.solve_device` per device):

Each chunk is padded on the device axis to a fixed size (copies of its last
device, whose results are dropped) and on the sample axis to a bucket length,
so every chunk of a run reuses one compiled function. With several local JAX
devices (GPUs; CPU devices, forced with
``XLA_FLAGS=--xla_force_host_platform_device_count=N``, only with ``shard=True``:
see :func:`local_mesh`) the device axis is
laid out as (blocks, shards × block), each shard's devices a contiguous slice,
with the second axis placed on a one-axis mesh (``NamedSharding``): XLA
partitions the vmap, so each JAX device fits its own slice. Linear models
compile to a program without any collective operation (nothing to wait on,
nothing to deadlock); models with
time constants add one all-reduce per solver step, where the shards agree on
when every device has converged. The numbers are those of the single-device
run to rounding (tests/test_sharding.py). ``jax.shard_map`` would be the
natural tool, but lineax rejects the manual-axis avals it creates.
"""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .._direct import solve_device
from .._fit_sums import group_size
from .._jit import parallel_devices
from .._motion_judge import judge_motion
from .._options import FitOptions
from .._signal_builder import stacked_signals
from ..data import Batch, sampling_intervals
from ..errors import SpecError
from ..fit import FitResult, fit
from ..model import ErrorModel, Params
from ..signals import TempNorm

AXIS = "devices"


def _solve_one(model: ErrorModel, opts: FitOptions):
    return lambda s: solve_device(model, s, opts, None)


@eqx.filter_jit
def _solve(model: ErrorModel, sig, opts: FitOptions, block: int, mesh: Mesh | None):
    """Fit every device of ``sig``: ``lax.map`` over blocks of devices (bounded memory for
    the per-device design matrices), vmap within a block. Each shard's devices are a
    contiguous slice of the device axis, so the blocks are laid out (blocks, shards ×
    block) with the second axis placed on ``mesh``: one vmap, each JAX device fitting its
    own columns (a vmap over the shards as well would batch every operation twice)."""
    n = sig.t.shape[0]
    shards = 1 if mesh is None else mesh.size
    k = n // (shards * block)

    def blocks(a):
        a = a.reshape((shards, k, block) + a.shape[1:]).swapaxes(0, 1)
        return a.reshape((k, shards * block) + a.shape[3:])

    def devices(a):
        a = a.reshape((k, shards, block) + a.shape[2:]).swapaxes(0, 1)
        return a.reshape((n,) + a.shape[3:])

    xs = jax.tree.map(blocks, sig)
    on_mesh = None if mesh is None else NamedSharding(mesh, PartitionSpec(None, AXIS))
    if mesh is not None:
        xs = jax.lax.with_sharding_constraint(xs, on_mesh)
    out = jax.lax.map(jax.vmap(_solve_one(model, opts)), xs)
    if mesh is not None:
        out = jax.lax.with_sharding_constraint(out, on_mesh)
    return jax.tree.map(devices, out)


def local_mesh(shard: bool | None = None) -> Mesh | None:
    """A one-axis mesh over the devices that may run side by side
    (:func:`diffgyro._jit.parallel_devices`: one CPU device, so no mesh on a CPU), or
    over every local device with ``shard=True`` (the tests do, on models that
    finish); None for one device or ``shard=False``."""
    devices = jax.local_devices() if shard else parallel_devices()
    if shard is False or len(devices) < 2:
        return None
    return Mesh(np.asarray(devices), (AXIS,))


def concat_results(parts: list[FitResult]) -> FitResult:
    """FitResults of consecutive device groups as one (host arrays)."""

    first = parts[0]
    kw = {}
    for f in dataclasses.fields(FitResult):
        vals = [getattr(p, f.name) for p in parts]
        if f.name == "devices":
            kw[f.name] = tuple(d for v in vals for d in v)
        elif f.name in ("model", "options", "static_only"):
            kw[f.name] = vals[0]
        elif vals[0] is None:
            kw[f.name] = None
        else:
            kw[f.name] = jax.tree.map(lambda *xs: np.concatenate(xs, axis=0), *vals)
    return type(first)(**kw)


class ChunkFitter:
    """Fits chunks of up to ``chunk_devices`` devices with ``spec``.

    ``options`` are :class:`~diffgyro.fit.FitOptions` fields (``dtemp_window``,
    ``n_folds``, ...). Results are :class:`~diffgyro.fit.FitResult` of the real
    devices only, with host (numpy) arrays.
    """

    def __init__(self, spec: str, chunk_devices: int, options: dict | None = None,
                 shard: bool | None = None):
        self.model = ErrorModel.from_spec(spec)
        if self.model.noise is not None:
            raise SpecError(f"streaming fits do not support {self.model.noise.spec} models yet",
                            hint="fit them without --chunk-devices/--dask")
        options = dict(options or {})
        tol = {k: jnp.asarray(options.pop(k)) for k in ("rtol", "atol", "rank_tol") if k in options}
        try:
            self.opts = FitOptions(**options, **tol)
        except TypeError as err:
            raise SpecError(f"unknown fit option: {err}") from None
        self.mesh = local_mesh(shard)
        n_shards = 1 if self.mesh is None else self.mesh.size
        per_shard = math.ceil(max(int(chunk_devices), 1) / n_shards)
        self.block = max(1, min(self.opts.chunk, per_shard))
        per_shard = math.ceil(per_shard / self.block) * self.block
        self.padded = per_shard * n_shards

    @property
    def n_shards(self) -> int:
        return 1 if self.mesh is None else self.mesh.size

    def fit(self, batch: Batch) -> FitResult:
        """Fit a batch of at most ``padded`` devices; FitResult of exactly these devices.

        On one JAX device: :func:`diffgyro.fit.fit` itself (whichever path it takes),
        one device group at a time. On several: the sharded direct path of this module.
        """

        if self.mesh is not None:
            return self.fit_direct(batch)
        # fit() runs a batch of several sums-path device groups on a pool of threads, and
        # that deadlocked (XLA on CPU, jax 0.10) from the second call of a process on: hand
        # it one group at a time. Same groups, so the same numbers, one compiled shape.
        try:

            g = group_size(batch.n_devices, batch.length)
        except ImportError:
            g = batch.n_devices
        parts = [jax.tree.map(np.asarray, fit(self.model, batch.select(
            np.arange(lo, min(lo + g, batch.n_devices))), options=self.opts))
            for lo in range(0, batch.n_devices, g)]
        return parts[0] if len(parts) == 1 else concat_results(parts)

    def fit_direct(self, batch: Batch) -> FitResult:
        """The direct path of this module (sharded when the fitter has a mesh)."""
        n = batch.n_devices
        if n > self.padded:
            raise ValueError(f"chunk of {n} devices is larger than the planned {self.padded}")
        idx = np.minimum(np.arange(self.padded), n - 1)   # pad with copies of the last device
        full = batch.select(idx)
        dtype = jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32

        def arr(x):
            return None if x is None else jnp.asarray(x, dtype)

        sig = stacked_signals(arr(full.t), arr(full.gyro), jnp.asarray(full.mask), arr(full.rate),
                              arr(full.temp), arr(full.temp_ext), arr(full.accel), None,
                              jnp.asarray(sampling_intervals(full), dtype), {},
                              self.opts.dtemp_window)
        if self.mesh is not None:
            sig = jax.device_put(sig, NamedSharding(self.mesh, PartitionSpec(AXIS)))
        out = _solve(self.model, sig, self.opts, self.block, self.mesh)
        out = jax.tree.map(lambda a: np.asarray(a)[:n], out)
        norm = sig.norm
        if norm is None:
            norm = TempNorm(centre=np.zeros(n), scale=np.ones(n))
        else:
            norm = TempNorm(centre=np.asarray(norm.centre)[:n], scale=np.asarray(norm.scale)[:n])
        temp_range = None
        if batch.temp is not None:
            tmask = np.where(batch.mask, batch.temp, np.nan)
            temp_range = np.stack([np.nanmin(tmask, axis=1), np.nanmax(tmask, axis=1)], axis=1)
        return judge_motion(FitResult(
            model=self.model, devices=batch.devices,
            params=Params(beta=out["beta"], theta=out["theta"]), norm=norm,
            temp_range=temp_range, cov=out["cov"], rms=out["rms"],
            heldout_rms=out["heldout_rms"], fold_mse=out["fold_mse"],
            noise_floor=out["noise_floor"], noise_axes=out["noise_axes"], sigma=out["sigma"],
            steps=out["steps"], status=out["status"], range_flags=out["range_flags"],
            collinear=out["collinear"], n_samples=out["n_samples"], options=self.opts), batch)
