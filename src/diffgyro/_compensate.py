"""Compensation with a calibration in JAX: the error model solved for the true rate.

:func:`diffgyro.calibration.compensate` runs this; the calibration file itself
(:mod:`diffgyro.calibration`) is read and checked without JAX.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _aux as aux_cols
from ._signal_builder import batch_signals
from .data import Batch
from .model import ErrorModel, Params
from .signals import TempNorm

__all__ = ["compensate_batch"]


def compensate_batch(cal, batch: Batch, devs: list) -> tuple[Batch, dict]:
    """:func:`diffgyro.calibration.compensate` in JAX (``cal`` a
    :class:`~diffgyro.calibration.Calibration`, ``devs`` its entries of ``batch``'s
    devices, checked there)."""
    model = cal.error_model
    params = Params(beta=jnp.asarray([d.beta for d in devs], jnp.float64).reshape(len(devs), 3, -1),
                    theta=jnp.asarray([d.theta for d in devs], jnp.float64).reshape(len(devs), -1))
    clamped: dict[str, int] = {}
    aux = _aux_scaled(batch, model, devs)
    if batch.temp is not None and "temp" in model.requires():
        temp = np.array(batch.temp, dtype=np.float64)
        for i, d in enumerate(devs):
            if d.temp_range is None:
                continue
            lo, hi = d.temp_range
            n = int(batch.n_valid[i])
            outside = (temp[i, :n] < lo) | (temp[i, :n] > hi)
            if outside.any():
                clamped[d.device] = int(outside.sum())
            temp[i] = np.clip(temp[i], lo, hi)
        batch_for_model = Batch(**{**{s: getattr(batch, s) for s in
                                      ("t", "gyro", "mask", "n_valid", "temp_ext", "accel", "mag",
                                       "rate", "quat")}, "temp": temp},
                                devices=batch.devices, sources=batch.sources)
        # dT/dt is taken from the measured temperature, not the clamped one
        sig = batch_signals(batch_for_model, norm=_norm(devs), dtemp_window=cal.dtemp_window,
                            aux=aux)
        sig_raw = batch_signals(batch, norm=_norm(devs), dtemp_window=cal.dtemp_window)
        sig = eqx.tree_at(lambda s: (s.dtemp, s.heating), sig, (sig_raw.dtemp, sig_raw.heating))
    else:
        sig = batch_signals(batch, norm=_norm(devs), dtemp_window=cal.dtemp_window, aux=aux)
    if clamped:
        warnings.warn("temperature outside the calibrated range was clamped for "
                      + ", ".join(f"{k} ({v} samples)" for k, v in clamped.items()), stacklevel=3)
    omega = _compensate_batch(model, params, sig)
    omega = np.where(np.asarray(batch.mask)[..., None], np.asarray(omega), 0.0)
    out = Batch(**{**{s: getattr(batch, s) for s in ("t", "mask", "n_valid", "temp", "temp_ext",
                                                      "accel", "mag", "rate", "quat")},
                   "gyro": omega}, devices=batch.devices, sources=batch.sources, aux=batch.aux)
    return out, clamped


def _aux_scaled(batch: Batch, model: ErrorModel, devs) -> dict:
    """The extra columns the model reads, clamped to the calibrated range and centred as
    calibrated; DataError naming the column when the data lack one."""

    names = aux_cols.aux_names(model.requires())
    aux_cols.check_columns(batch, names, vary=False)
    norm = {k: TempNorm(centre=np.asarray([d.aux[k]["centre"] for d in devs]),
                        scale=np.asarray([d.aux[k]["scale"] for d in devs])) for k in names}
    clamp = {k: np.asarray([d.aux[k]["range"] for d in devs]) for k in names}
    return aux_cols.scaled(batch, norm, clamp)


def _norm(devs) -> TempNorm:
    return TempNorm(centre=jnp.asarray([d.temp_centre for d in devs]),
                    scale=jnp.asarray([d.temp_scale for d in devs]))


@eqx.filter_jit
def _compensate_batch(model: ErrorModel, params: Params, sig):
    return jax.vmap(model.compensate)(params, sig)
