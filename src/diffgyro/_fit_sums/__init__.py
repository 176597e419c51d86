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
The group program may reassociate its sums (:data:`diffgyro._xla_options.REASSOCIATE`), is compiled for
compile time unless it is a fused linear model's (:data:`diffgyro._xla_options.FAST_COMPILE`), and returns
its results packed in one array per group; the model-free noise floor is computed on
the host's threads meanwhile (:mod:`diffgyro._noise`). Unless the model is fused linear,
the group program stops at the sums and the finish (:func:`.finish.finish`: solves,
covariance, rank check, status; small dense algebra) is a program of its own,
compiled without optimisation on a thread while the group program compiles: the
model-discovery loop compiles a program per spec, and each kernel costs compile time.
A small batch (:data:`diffgyro._xla_options.SMALL_WORK`) takes one program, its finish
inline, compiled without optimisation (:data:`.programs.group_small`).

The package, one part per file: :mod:`.layout` (which columns and products a model
needs), :mod:`.sums` (blocked per-fold sums), :mod:`.normal_equations` (solves from
the sums), :mod:`.projection` and :mod:`.newton` (variable projection, Newton on the
time constants), :mod:`.separable` (a device's sums with time constants),
:mod:`.device` (the per-device program), :mod:`.finish` (solves, covariance, rank
check, status), :mod:`.programs` (the compiled group programs and their packed
results), :mod:`.inputs` (their per-device inputs on the host), :mod:`.groups`
(group and chunk sizes), :mod:`.transfer` (groups sent to an accelerator ahead),
:mod:`diffgyro._xla_options` (XLA options); :func:`solve_sums` here runs them over a batch.
"""

from __future__ import annotations

import jax
import numpy as np

from .._jit import collector_paused, parallel_devices
from .._noise import start as host_noise
from .._xla_options import FAST_COMPILE, ONCE, REASSOCIATE
from ..data import Batch, aux_key
from ..model import ErrorModel
from ..signals import TempNorm
from . import groups, transfer
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
from .inputs import GroupInputs, group_inputs, host_arrays
from .layout import INPUTS, Layout, covariance_pairs, layout_of, moving_columns, varying_products
from .newton import newton
from .programs import (
    group_compact,
    group_finish,
    group_for,
    group_fused,
    group_small,
    pack,
    unpack_results,
)
from .sums import ALIGNED, block_starts, fold_sums

__all__ = ["ALIGNED", "CHUNK", "FAST_COMPILE", "FUSED_GROUP_FACTOR", "GROUP_SAMPLES", "INPUTS",
           "GroupInputs", "Layout", "MAX_GROUP_DEVICES", "NONLINEAR_GROUP_DIVISOR", "ONCE", "REASSOCIATE",
           "block_starts", "chunk_size", "covariance_pairs", "fold_sums", "group_compact",
           "group_finish", "group_for", "group_fused", "group_size", "group_small", "groups",
           "layout_of", "moving_columns", "newton", "pack", "solve_sums", "unpack_results", "valid_counts",
           "varying_products"]

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
               dtype=np.float64, aux: dict | None = None, floor: list | None = None,
               floor_after=None):
    """Fit every device of ``batch`` with the sums path; numpy arrays with a device axis.

    ``theta0`` (devices × time constants, log s) replaces the grid start; ``aux`` holds
    the extra columns the model reads, centred and scaled ((devices, n) each). ``floor``:
    where given, the model-free noise floor (computed on the host's threads) is not waited
    for; the function that waits and gives it (``noise_floor``, ``noise_axes``) is appended
    to ``floor``, and the results leave both out (the caller's motion check runs meanwhile).
    ``floor_after``: a future whose work the floor's threads wait for before they start
    (:func:`diffgyro._noise.start`).
    """
    aux = dict(aux or {})
    present = frozenset(batch.signals) | {aux_key(k) for k in aux}
    layout, need = layout_of(model, present)
    d, n = batch.n_devices, batch.length
    fused = layout.pointwise and all(layout.shared)
    # groups take turns on the accelerators; on a CPU one device runs every group, the
    # host preparing the next group while XLA runs the last
    devices = parallel_devices()
    g = groups.devices_per_call(d, n, bool(model.n_nonlinear), fused, devices[0].platform,
                                transfer.TRANSFER_THREADS)
    arrays = host_arrays(model, batch, norm, need, theta0, dtype, aux)
    group = group_for(model, fused, d * n)
    # a program compiled for compile time finishes in a program of its own, compiled
    # without optimisation beside it; a fused linear model's finishes inline
    apart = group is group_compact
    finish = (model, layout, opts)
    counts = valid_counts(batch.mask)

    def send(j: int):
        m, prefix, c, inputs, shared = group_inputs(arrays, counts, opts.n_blocks, j, g, dtype)
        put = jax.device_put(inputs, devices[j % len(devices)])  # one call for the whole group
        return m, prefix, c, put, shared

    def run(j: int, sent):
        m, prefix, c, put, shared = sent
        args = (model, layout, opts, c, prefix, *put.program_args(),
                shared if put.pos is None else put.pos, apart)
        if j == 0:  # the first group traces and compiles every program
            specs.append(_compile_first(group, apart, args, finish, devices[0]))
        out = group(*args)
        if apart:
            out = group_finish(*finish, out)
        return m, out[0]  # the packed results (:func:`.programs.pack`)

    # the model-free noise floor on threads of the host, beside the compiled programs
    noise = (host_noise(batch.gyro, batch.rate, batch.mask, dtype, after=floor_after)
             if opts.noise_floor else None)
    # dispatch every group, then collect (concurrent calls from several Python threads
    # deadlocked XLA's CPU client: keep to one caller); an accelerator's groups are sent
    # ahead from host threads (:mod:`.transfer`)
    specs: list = []
    outs = [run(j, sent) for j, sent in
            enumerate(transfer.in_order(send, -(-d // g), devices[0].platform))]
    got = jax.device_get([o for _, o in outs])  # one transfer call for every group
    got = [unpack_results(o, specs[0]) for o in got]
    out = {k: np.concatenate([o[k][:m] for (m, _), o in zip(outs, got)], axis=0)
           for k in got[0]}
    if noise is None:
        out["noise_floor"] = np.full(d, np.nan, dtype)
        out["noise_axes"] = np.full((d, 3), np.nan, dtype)
    elif floor is not None:
        floor.append(noise)
    else:
        out["noise_floor"], out["noise_axes"] = noise()
    return out
