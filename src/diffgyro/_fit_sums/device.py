"""The per-device program: one device's signals, its sums (total, held-out folds and
training folds) and what the finish needs, for a linear model or one with time
constants (:mod:`.separable`)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..model import ErrorModel
from ..signals import TempNorm, make_signals, masked_range, temp_norm_from
from .layout import Layout, design_products, signal_products
from .separable import separable_sums
from .sums import fold_sums
from .types import DeviceSums, FoldSums


def device_signals(opts, t, gyro, mask, rate, temp, temp_ext, accel, aux, centre, scale, dt):
    """The device's signals; its temperature normalised by ``centre``/``scale`` when given,
    else by its own range."""
    dtype = gyro.dtype
    norm = None
    if temp is not None:
        norm = temp_norm_from(temp, mask) if centre is None else TempNorm(centre=centre, scale=scale)
    t = jnp.zeros(mask.shape, dtype) if t is None else t
    sig = make_signals(t, gyro, mask, rate=rate, temp=temp, temp_ext=temp_ext, accel=accel,
                       norm=norm, dtemp_window=opts.dtemp_window, dt=dt, slopes=dt is not None,
                       aux=aux)
    if temp is not None:  # the same T_s with a multiply instead of a divide per sample
        inv = 1.0 / norm.scale
        sig = eqx.tree_at(lambda s_: s_.temp_s, sig, temp * inv - norm.centre * inv)
    return sig


def linear_sums(model: ErrorModel, layout: Layout, opts, c: int, sig, mask, nv, y, y0, pos):
    """Sums of a model without time constants: total, held-out and training folds."""
    dtype = y.dtype
    n_folds = opts.n_folds
    theta = jnp.zeros((0,), dtype)
    if layout.pointwise:
        tot, per_fold = fold_sums(signal_products(layout, model, theta, y0), sig, mask, nv,
                                  opts.n_blocks, n_folds, c, pos)
    else:
        x = model.design(sig, theta)  # a column that reads other samples is formed once
        tot, per_fold = fold_sums(design_products(layout), (x, y - y0), mask, nv, opts.n_blocks,
                                  n_folds, c, pos)
    held, train = per_fold, tot[None] - per_fold
    steps, converged = jnp.asarray(1, jnp.int32), jnp.asarray(True)
    return FoldSums(tot, held, train, theta, steps, converged)


def device(model: ErrorModel, layout: Layout, opts, c: int, prefix: bool, t, gyro, mask, rate,
           temp, temp_ext, accel, aux, centre, scale, dt, nv, theta0, pos=None):
    """One device's sums and what its finish (:func:`.finish.finish`) reads."""
    nq = model.n_nonlinear
    dtype = gyro.dtype
    if isinstance(pos, str):  # ALIGNED: every sample valid; a constant mask folds away
        mask = jnp.ones(mask.shape, bool)
    sig = device_signals(opts, t, gyro, mask, rate, temp, temp_ext, accel, aux, centre, scale, dt)
    y = sig.gyro - sig.rate
    if layout.const_col is not None:
        y0 = y[0] if prefix else y[jnp.argmax(mask)]
    else:
        y0 = jnp.zeros((3,), dtype)
    if nq == 0:
        sums = linear_sums(model, layout, opts, c, sig, mask, nv, y, y0, pos)
    else:
        sums = separable_sums(model, layout, opts, c, sig, mask, nv, y, y0, theta0, pos)
    sums = eqx.tree_at(lambda s: (s.steps, s.converged), sums,
                       (jnp.asarray(sums.steps, jnp.int32), jnp.asarray(sums.converged)))
    terms = model.terms
    flags = model.range_problems(sig) > 0 if terms else jnp.zeros((0,), bool)
    temp_range = jnp.stack(masked_range(temp, mask)) if temp is not None else None
    norm = sig.norm
    return DeviceSums(sums, y0, flags, temp_range, None if norm is None else norm.centre,
                      None if norm is None else norm.scale)
