"""The per-device inputs of the group programs, on the host: the batch's arrays the model
reads, and one group's slice of them (the last group padded by repeating its last device)."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import numpy as np

from ..data import Batch, aux_key, sampling_intervals
from ..model import ErrorModel
from .groups import chunk_size
from .layout import INPUTS
from .sums import ALIGNED, block_starts


class GroupInputs(eqx.Module):
    """Per-device arrays (leading device axis), None where the model reads none: the
    samples and the model's signals, the extra columns ``aux`` by name, the temperature
    normalisation (``centre``, ``scale``), the sampling intervals ``dt``, the start
    ``theta0``; for a group also its valid counts ``nv`` and block starts ``pos``."""

    t: np.ndarray | None
    gyro: np.ndarray
    mask: np.ndarray
    rate: np.ndarray | None
    temp: np.ndarray | None
    temp_ext: np.ndarray | None
    accel: np.ndarray | None
    aux: dict
    centre: np.ndarray | None
    scale: np.ndarray | None
    dt: np.ndarray | None
    nv: np.ndarray | None = None
    theta0: np.ndarray | None = None
    pos: np.ndarray | None = None

    def program_args(self) -> tuple:
        """The per-device arguments of :func:`.programs.group_program`, in its order."""
        return (self.t, self.gyro, self.mask, self.rate, self.temp, self.temp_ext, self.accel,
                self.aux, self.centre, self.scale, self.dt, self.nv, self.theta0)


def host_arrays(model: ErrorModel, batch: Batch, norm, need, theta0, dtype,
                aux: dict) -> GroupInputs:
    """The batch's arrays the model reads (None where it reads none)."""
    d = batch.n_devices
    # dT/dt (and the heating state) only for a model that reads them
    dt = sampling_intervals(batch) if "dt" in need else None
    centre = scale = None
    if norm is not None and batch.temp is not None:
        centre = np.broadcast_to(np.asarray(norm.centre, dtype), (d,))
        scale = np.broadcast_to(np.asarray(norm.scale, dtype), (d,))
    read = {}
    for k in INPUTS:
        arr = getattr(batch, k)
        # the reference rate is always read: the fit is of gyro − rate
        read[k] = arr if (arr is not None and (k in need or k in ("temp", "rate"))) else None
    if "t" not in need:
        read["t"] = None
    return GroupInputs(
        **read, gyro=batch.gyro, mask=batch.mask, centre=centre, scale=scale, dt=dt,
        aux={k: v for k, v in aux.items() if aux_key(k) in need},
        theta0=None if theta0 is None else np.broadcast_to(np.asarray(theta0, dtype),
                                                           (d, model.n_nonlinear)))


def group_inputs(arrays: GroupInputs, counts, n_blocks: int, j: int, g: int, dtype):
    """Group j's inputs, its device count, whether every device's valid samples come
    first, its chunk, and its block starts when every group shares them (:data:`.sums.ALIGNED`;
    else they are the inputs' ``pos``, or None)."""
    nv_all, prefix_all = counts
    d, n = arrays.mask.shape
    start = j * g
    stop = min(start + g, d)
    sl = slice(start, stop) if stop - start == g else np.minimum(np.arange(start, start + g),
                                                                stop - 1)
    nv = nv_all[sl]
    prefix = bool(np.all(prefix_all[sl]))
    c = chunk_size(int(nv.min()), n_blocks, n)

    def take(x):
        return None if x is None else np.ascontiguousarray(np.asarray(x[sl], dtype))

    fields = {f.name: take(getattr(arrays, f.name)) for f in dataclasses.fields(arrays)
              if f.name not in ("mask", "aux", "nv", "theta0", "pos")}
    theta0 = None if arrays.theta0 is None else np.ascontiguousarray(arrays.theta0[sl])
    pos = None
    if prefix and nv.min() == n and n % n_blocks == 0:
        shared = ALIGNED
    else:
        shared = None
        if prefix:
            pos = block_starts(nv, n_blocks)
    group = GroupInputs(**fields, mask=np.asarray(arrays.mask[sl], bool),
                        aux={k: take(v) for k, v in arrays.aux.items()},
                        nv=nv.astype(np.int32), theta0=theta0, pos=pos)
    return stop - start, prefix, c, group, shared
