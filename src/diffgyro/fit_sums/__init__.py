"""The sums path of linear fits: one blocked pass over the samples, no design matrix.

For a model linear in all its parameters everything :func:`diffgyro.fit.fit`
reports — the normal equations of every axis, those of every held-out fold,
the residual and held-out sums of squares — is a sum over samples of products
of regressor columns and rates. This path reads each device's samples once:

* one XLA *variadic* reduction over short sample chunks forms all products'
  chunk sums in a single loop (XLA on CPU does not fuse sibling reductions;
  separate ``jnp.sum`` calls read the data once per product);
* a time block of the held-out folds starts inside at most one chunk when the
  chunk is no longer than the shortest block, so each chunk also sums the
  part after that boundary; chunk and part sums land exactly in their blocks'
  folds;
* a fold's training system is the total minus its held-out sums, and its
  held-out error ``Σ(y − xβ)² = Q − 2βᵀc + βᵀAβ`` comes from the held-out
  sums alone.

Columns equal on the three axes (bias polynomial, gradient, temp_diff, ...)
share their products, so ``bias_poly(k)`` needs (k+1)(k+2)/2 column products
and 3(k+2) rate products per sample, in one pass, instead of a (n, 3, p)
design matrix read once per fold. ``Q − 2βᵀc + βᵀAβ`` cancels when the fit
is good; each axis' first valid sample is subtracted before summing when the
model has a constant bias column, which leaves the cancellation to the scale
of the rate's variation rather than of its offset.

Time constants (variable projection): the linear coefficients are solved from
the sums for every trial, Newton moves the log time constants alone. Products
that do not move with them are summed once (total and per fold); a trial forms
only the moving columns with their two derivatives (one recursion for
thermal_lag, forward mode otherwise) and sums the moving products and their
derivatives in one reduction, which gives the projected cost's value, gradient
and Hessian from one pass. The held-out folds refit from the full optimum; the
full fit and the folds are problems of one Newton loop, solved in turn, so the
evaluation is compiled once.

Devices are processed in groups of a fixed size on the host (and spread over
every local accelerator), so only the group size — not the number of devices —
is part of the compiled shape. Models with time constants take smaller groups:
their batched Newton loops step in lockstep with the group's slowest device.
The group program may reassociate its sums (:data:`.compile_options.REASSOCIATE`), is compiled for
compile time unless it is a fused linear model's (:data:`.compile_options.FAST_COMPILE`), and returns
its results packed in one array per group; the model-free noise floor is computed on
the host's threads meanwhile (:mod:`diffgyro.noise`). Unless the model is fused linear,
the group program stops at the sums and the finish (:func:`.finish.finish`: solves,
covariance, rank check, status; small dense algebra) is a program of its own,
compiled without optimisation on a thread while the group program compiles: the
model-discovery loop compiles a program per spec, and each kernel costs compile time.

The package, one part per file: :mod:`.layout` (which columns and products a model
needs), :mod:`.sums` (blocked per-fold sums), :mod:`.normal_equations` (solves from
the sums), :mod:`.projection` and :mod:`.newton` (variable projection, Newton on the
time constants), :mod:`.separable` (a device's sums with time constants),
:mod:`.device` (the per-device program), :mod:`.finish` (solves, covariance, rank
check, status), :mod:`.programs` (the compiled group programs and their packed
results), :mod:`.groups` (group and chunk sizes), :mod:`.compile_options` (XLA
options); :func:`solve_sums` here runs them over a batch.
"""

from __future__ import annotations

import jax
import numpy as np

from ..core import sampling_intervals
from ..data import Batch, aux_key
from ..jit import collector_paused, parallel_devices
from ..model import ErrorModel
from ..noise import start as host_noise
from ..signals import TempNorm
from . import groups
from .compile_options import FAST_COMPILE, ONCE, REASSOCIATE
from .groups import (
    CHUNK,
    FUSED_GROUP_FACTOR,
    GROUP_SAMPLES,
    MAX_GROUP_DEVICES,
    NONLINEAR_GROUP_DIVISOR,
    chunk_size,
    group_size,
    valid_counts,
)
from .layout import INPUTS, Layout, covariance_pairs, layout_of, moving_columns, varying_products
from .newton import newton
from .programs import group_compact, group_finish, group_for, group_fused, pack, unpack_results
from .sums import ALIGNED, block_starts, fold_sums

__all__ = ["ALIGNED", "CHUNK", "FAST_COMPILE", "FUSED_GROUP_FACTOR", "GROUP_SAMPLES", "INPUTS",
           "Layout", "MAX_GROUP_DEVICES", "NONLINEAR_GROUP_DIVISOR", "ONCE", "REASSOCIATE",
           "block_starts", "chunk_size", "covariance_pairs", "fold_sums", "group_compact",
           "group_finish", "group_for", "group_fused", "group_size", "groups", "layout_of",
           "moving_columns", "newton", "pack", "solve_sums", "unpack_results", "valid_counts",
           "varying_products"]

#: Per-device inputs of the group program, in the order it takes them.
ORDER = ("t", "gyro", "mask", "rate", "temp", "temp_ext", "accel", "aux", "centre", "scale", "dt")


def _host_arrays(model: ErrorModel, batch: Batch, norm, need, theta0, dtype, aux: dict) -> dict:
    """The batch's arrays the model reads (None where it reads none), by name."""
    d = batch.n_devices
    # dT/dt (and the heating state) only for a model that reads them
    dt = sampling_intervals(batch) if "dt" in need else None
    centre = scale = None
    if norm is not None and batch.temp is not None:
        centre = np.broadcast_to(np.asarray(norm.centre, dtype), (d,))
        scale = np.broadcast_to(np.asarray(norm.scale, dtype), (d,))
    arrays = {"gyro": batch.gyro, "mask": batch.mask, "centre": centre, "scale": scale, "dt": dt,
              "theta0": None if theta0 is None else np.broadcast_to(
                  np.asarray(theta0, dtype), (d, model.n_nonlinear))}
    for k in INPUTS:
        arr = getattr(batch, k)
        # the reference rate is always read: the fit is of gyro − rate
        arrays[k] = arr if (arr is not None and (k in need or k in ("temp", "rate"))) else None
    if "t" not in need:
        arrays["t"] = None
    arrays["aux"] = {k: v for k, v in aux.items() if aux_key(k) in need}
    return arrays


def _group_inputs(arrays: dict, mask, counts, n_blocks: int, j: int, g: int, dtype):
    """Group j's host arrays (the last group padded by repeating its last device), its
    device count, whether every device's valid samples come first, its chunk and block
    starts (:data:`.sums.ALIGNED`, in the arrays as ``pos``, or None)."""
    nv_all, prefix_all = counts
    d, n = mask.shape
    start = j * g
    stop = min(start + g, d)
    sl = slice(start, stop) if stop - start == g else np.minimum(np.arange(start, start + g),
                                                                stop - 1)
    nv = nv_all[sl]
    prefix = bool(np.all(prefix_all[sl]))
    c = chunk_size(int(nv.min()), n_blocks, n)
    host = {k: (np.asarray(mask[sl], bool) if k == "mask"
                else np.ascontiguousarray(np.asarray(arrays[k][sl], dtype)))
            for k in ORDER if arrays[k] is not None and k != "aux"}
    host["aux"] = {k: np.ascontiguousarray(np.asarray(v[sl], dtype))
                   for k, v in arrays["aux"].items()}
    host["nv"] = nv.astype(np.int32)
    if arrays["theta0"] is not None:
        host["theta0"] = np.ascontiguousarray(arrays["theta0"][sl])
    if prefix and nv.min() == n and n % n_blocks == 0:
        pos = ALIGNED
    elif prefix:
        host["pos"] = block_starts(nv, n_blocks)
        pos = None
    else:
        pos = None
    return stop - start, prefix, c, host, pos


def _compile_first(group, apart: bool, args, finish: tuple, device):
    """Trace and compile every program on the first group's arguments (the collector
    paused); the packed results' shapes (:func:`.programs.pack`)."""
    with collector_paused():
        # the results' shapes, from the trace the call makes anyway
        shapes = group.eval_shape(*args)
        # the group program compiles while this thread traces the finish
        ahead = [group.compile_ahead(*args)]
        if apart:
            on = jax.sharding.SingleDeviceSharding(device)
            raw = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=on),
                               shapes)
            shapes = group_finish.eval_shape(*finish, raw)
            ahead.append(group_finish.compile_ahead(*finish, raw))
        for thread in ahead:
            thread.join()
    return shapes[1]


def solve_sums(model: ErrorModel, batch: Batch, norm: TempNorm | None, opts, theta0=None,
               dtype=np.float64, aux: dict | None = None):
    """Fit every device of ``batch`` with the sums path; numpy arrays with a device axis.

    ``theta0`` (devices × time constants, log s) replaces the grid start; ``aux`` holds
    the extra columns the model reads, centred and scaled ((devices, n) each).
    """
    aux = dict(aux or {})
    present = frozenset(batch.signals) | {aux_key(k) for k in aux}
    layout, need = layout_of(model, present)
    d, n = batch.n_devices, batch.length
    fused = layout.pointwise and all(layout.shared)
    g = groups.devices_per_call(d, n, bool(model.n_nonlinear), fused)
    arrays = _host_arrays(model, batch, norm, need, theta0, dtype, aux)
    # groups take turns on the accelerators; on a CPU one device runs every group, the
    # host preparing the next group while XLA runs the last
    devices = parallel_devices()
    group = group_for(model, fused)
    # a program compiled for compile time finishes in a program of its own, compiled
    # without optimisation beside it; a fused linear model's finishes inline
    apart = group is group_compact
    finish = (model, layout, opts)
    counts = valid_counts(batch.mask)

    def run(j: int):
        m, prefix, c, host, pos = _group_inputs(arrays, batch.mask, counts, opts.n_blocks, j, g,
                                                dtype)
        put = jax.device_put(host, devices[j % len(devices)])  # one call for the whole group
        args = (model, layout, opts, c, prefix, *[put.get(k) for k in (*ORDER, "nv", "theta0")],
                put.get("pos", pos), apart)
        if j == 0:  # the first group traces and compiles every program
            specs.append(_compile_first(group, apart, args, finish, devices[0]))
        out = group(*args)
        if apart:
            out = group_finish(*finish, out)
        return m, out[0]  # the packed results (:func:`.programs.pack`)

    # the model-free noise floor on threads of the host, beside the compiled programs
    noise = (host_noise(batch.gyro, batch.rate, batch.mask, dtype) if opts.noise_floor
             else None)
    # dispatch every group, then collect (concurrent calls from several Python threads
    # deadlocked XLA's CPU client: keep to one caller)
    specs: list = []
    outs = [run(j) for j in range(-(-d // g))]
    got = jax.device_get([o for _, o in outs])  # one transfer call for every group
    got = [unpack_results(o, specs[0]) for o in got]
    out = {k: np.concatenate([o[k][:m] for (m, _), o in zip(outs, got)], axis=0)
           for k in got[0]}
    if noise is None:
        out["noise_floor"] = np.full(d, np.nan, dtype)
        out["noise_axes"] = np.full((d, 3), np.nan, dtype)
    else:
        out["noise_floor"], out["noise_axes"] = noise()
    return out
