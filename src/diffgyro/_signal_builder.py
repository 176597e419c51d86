"""The one step from loaded data to the signals effect terms read.

:func:`batch_signals` turns a :class:`~diffgyro.data.Batch` into the stacked
:class:`~diffgyro.signals.Signals` of its devices (JAX arrays, temperature normalised);
:func:`stacked_signals` does the same from arrays already on the device (the streamed
fit's chunks), and :func:`input_signals` builds one device's signals inside the compiled
diagnose programs from the inputs :func:`batch_inputs` takes from a batch. Every one goes through
:func:`~diffgyro.signals.make_signals`, where each derived signal is computed; the signals
themselves are described in :mod:`diffgyro._signal_catalogue`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .data import Batch, sampling_intervals
from .signals import Signals, TempNorm, make_signals


def batch_signals(
    batch: Batch,
    norm: TempNorm | None = None,
    dtemp_window: float = 60.0,
    dtype=jnp.float64,
    aux: dict | None = None,
) -> Signals:
    """Derived signals of every device, stacked on the device axis (JAX arrays).

    ``norm`` fixes the temperature centring (scalars, or one per device, as a
    calibration stores them); by default each device uses its own range.
    ``aux`` holds the extra columns the model reads, centred and scaled
    (:func:`diffgyro._aux.scaled`, (devices, n) each).
    """
    return stacked_signals(*signal_inputs(batch, norm, dtype, aux), dtemp_window)


def signal_inputs(batch: Batch, norm: TempNorm | None = None, dtype=jnp.float64,
                  aux: dict | None = None, intervals: bool = True) -> tuple:
    """What :func:`stacked_signals` reads of ``batch`` (after ``dtemp_window``, its last
    argument), as :func:`batch_signals` describes them: a program that derives the
    signals inside (a prediction, a residual) takes the same inputs. ``intervals``: False
    leaves the sampling intervals out (None), for a program whose outputs do not read
    dT/dt (its trace then drops them): no median of every device's intervals."""

    def arr(x):
        return None if x is None else jnp.asarray(x, dtype)

    dt = jnp.asarray(sampling_intervals(batch), dtype) if intervals else None
    if norm is not None:
        norm = TempNorm(centre=jnp.broadcast_to(jnp.asarray(norm.centre, dtype), (batch.n_devices,)),
                        scale=jnp.broadcast_to(jnp.asarray(norm.scale, dtype), (batch.n_devices,)))
    return (arr(batch.t), arr(batch.gyro), jnp.asarray(batch.mask), arr(batch.rate),
            arr(batch.temp), arr(batch.temp_ext), arr(batch.accel), norm, dt,
            {k: arr(v) for k, v in (aux or {}).items()})


@eqx.filter_jit
def stacked_signals(t, gyro, mask, rate, temp, temp_ext, accel, norm, dt, aux, dtemp_window):
    """:func:`make_signals` vmapped over devices, compiled once per shape (eager, every
    primitive would be dispatched and compiled on its own)."""

    def one(t, gyro, mask, rate, temp, temp_ext, accel, norm, dt, aux):
        return make_signals(t, gyro, mask, rate=rate, temp=temp, temp_ext=temp_ext, accel=accel,
                            norm=norm, dtemp_window=dtemp_window, dt=dt, aux=aux)

    return jax.vmap(one)(t, gyro, mask, rate, temp, temp_ext, accel, norm, dt, aux)


def input_signals(inp: Mapping, dtemp_window) -> Signals:
    """One device's signals from its inputs (``t gyro mask rate temp temp_ext accel norm dt
    aux``, as :func:`batch_signals` reads them from a batch) and the dT/dt window (s)."""
    return make_signals(inp["t"], inp["gyro"], inp["mask"], rate=inp["rate"], temp=inp["temp"],
                        temp_ext=inp["temp_ext"], accel=inp["accel"], norm=inp["norm"],
                        dtemp_window=dtemp_window, dt=inp["dt"], aux=inp["aux"])


def batch_inputs(batch: Batch, take, norm: TempNorm | None, aux: Mapping[str, np.ndarray],
                 put: Callable = jnp.asarray) -> dict:
    """Devices ``take`` (indices or a slice) of ``batch`` as :func:`input_signals` reads
    them, each array float64 and placed by ``put``: the samples, the temperature norm
    ``norm`` (one for the batch or one per device; None: each device centres its own), the
    median sampling intervals and the extra columns ``aux`` ((devices, n) each, centred and
    scaled, :func:`diffgyro._aux.scaled`)."""

    def arr(x):
        return None if x is None else put(np.asarray(x, np.float64)[take])

    if norm is not None:
        n = batch.n_devices
        norm = TempNorm(centre=arr(np.broadcast_to(np.asarray(norm.centre), (n,))),
                        scale=arr(np.broadcast_to(np.asarray(norm.scale), (n,))))
    return dict(t=arr(batch.t), gyro=arr(batch.gyro), mask=put(np.asarray(batch.mask)[take]),
                rate=arr(batch.rate), temp=arr(batch.temp), temp_ext=arr(batch.temp_ext),
                accel=arr(batch.accel), norm=norm, dt=put(sampling_intervals(batch)[take]),
                aux={k: arr(v) for k, v in aux.items()})
