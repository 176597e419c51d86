"""The overlapping Allan deviation of every device's base-fit residual.

Its program's shapes follow from the batch alone, so it can be compiled (or read from the
caches) before the residuals exist (:func:`allan_args` with shapes only); the curves feed
the decision's slope and floor.
"""

from __future__ import annotations

import jax
import numpy as np

from .. import allan as allan_mod
from .._jit import by_work
from .._xla_options import ONE_PART
from ..data import Batch, device_bucket
from ._chunks import put
from ._results import AllanCurves

#: The residuals' Allan deviation (:func:`diffgyro.allan.oadev`, with its options)
#: compiled for a batch's size (:func:`~diffgyro._jit.by_work`): a small batch's without
#: optimisation, as one part, compiles in about a fifth of the time, with the same bits
#: (its differences and sums run in the program's order either way).
_oadev = by_work(allan_mod.oadev.__wrapped__, compiler_options=allan_mod.OADEV_OPTIONS,
                 small_options=ONE_PART)


def allan_args(resid: np.ndarray | None, batch: Batch, put=put):
    """The Allan deviation's arguments (``resid`` None: shapes only, the residual's as the
    scoring returns it) and every device's sample interval and the cluster sizes."""
    n_dev = batch.n_devices
    pick = np.minimum(np.arange(device_bucket(n_dev, minimum=1)), n_dev - 1)  # few compiled shapes
    dts = np.array([allan_mod.sample_interval(batch.t[i], batch.n_valid[i]) for i in range(n_dev)])
    m = allan_mod.default_m(int(np.max(batch.n_valid)), per_decade=8)
    nv = np.repeat(np.asarray(batch.n_valid)[pick, None], 3, axis=1)
    y = (jax.ShapeDtypeStruct((pick.size, 3, batch.t.shape[1]),
                              jax.dtypes.canonicalize_dtype(np.float64))
         if resid is None else put(np.moveaxis(resid, -1, 1)[pick]))
    return (y, put(dts[pick, None]), put(np.asarray(m)), put(nv)), dts, m


def allan_program(batch: Batch):
    """The Allan deviation's program for ``batch``'s residuals (:data:`_oadev`)."""
    return _oadev(device_bucket(batch.n_devices, minimum=1) * 3 * batch.t.shape[1])


def allan(resid: np.ndarray, batch: Batch, ahead=None) -> AllanCurves:
    """Overlapping Allan deviation of every device's residual (devices, 3, k) (``ahead``:
    the thread compiling its program, joined first)."""
    n_dev = batch.n_devices
    args, dts, m = allan_args(resid, batch)
    if ahead is not None:
        ahead.join()
    adev, _ = allan_program(batch)(*args)
    adev = np.asarray(adev)[:n_dev]
    tau = dts[:, None, None] * np.asarray(m)[None, None, :] * np.ones((1, 3, 1))
    return AllanCurves(tau=tau, adev=adev)
