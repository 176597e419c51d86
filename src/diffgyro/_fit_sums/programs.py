"""The compiled group programs: every device of a group through :func:`.device.device`, the
finish, and the results packed in one array per group."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._jit import TRACE_COUNTS, filter_jit
from .._xla_options import FAST_COMPILE, ONCE, ONE_PART, REASSOCIATE, SMALL_WORK
from ..model import ErrorModel
from .device import device
from .finish import finish


def group_program(model, layout, opts, c, prefix, t, gyro, mask, rate, temp, temp_ext, accel,
                   aux, centre, scale, dt, nv, theta0, pos=None, apart=False):
    """Every device of a group through :func:`.device.device`: its results finished and packed
    (:func:`pack`), or with ``apart`` its sums as they are (finished by
    :func:`group_finish`)."""
    TRACE_COUNTS["sums"] += 1
    aligned = isinstance(pos, str)  # ALIGNED: the same for every device, not an array

    def one(*args):
        if aligned:
            return device(model, layout, opts, c, prefix, *args, pos=pos)
        return device(model, layout, opts, c, prefix, *args)

    args = (t, gyro, mask, rate, temp, temp_ext, accel, aux, centre, scale, dt, nv, theta0)
    raw = jax.vmap(one)(*(args if aligned else (*args, pos)))
    return raw if apart else finished(model, layout, opts, raw)


def finished(model, layout, opts, raw):
    """A group's results from its sums, packed (:func:`pack`)."""
    return pack(jax.vmap(lambda r: finish(model, layout, opts, r))(raw), raw.y0.dtype)


group_fused = filter_jit(compiler_options=REASSOCIATE)(group_program)
group_compact = filter_jit(compiler_options={**REASSOCIATE, **FAST_COMPILE})(group_program)
#: The finish of every model but a fused linear one: a few dozen tiny kernels, compiled
#: without optimisation (:data:`ONCE`) on a thread of its own while the group program
#: compiles: a first fit starts sooner, at the cost of a second call per group (which,
#: not the unoptimised code, makes long fits about 10 % slower).
group_finish = filter_jit(compiler_options=ONCE)(finished)


#: A small batch's group program, its finish inline: compiled without optimisation, as one
#: part (:data:`ONE_PART`: a first fit compiles it beside its other programs).
group_small = filter_jit(compiler_options={**REASSOCIATE, **ONCE, **ONE_PART})(group_program)


def group_for(model: ErrorModel, fused: bool, samples: int):
    """The compiled group program for a batch of ``samples`` (devices × samples): a small
    batch's compiled without optimisation (:data:`~diffgyro._xla_options.SMALL_WORK`), a fused linear
    model's with XLA's fusion emitters (its sums at memory speed), any other compiled for
    compile time (:data:`FAST_COMPILE`)."""
    if samples <= SMALL_WORK:
        return group_small
    return group_fused if fused and not model.n_nonlinear else group_compact


def pack(out, dtype):
    """Every result of a group as the columns of one (devices, k) array, and the results'
    shapes and dtypes as empty arrays: the host then fetches one array per group, not
    one per result (each fetch costs tens of µs). Integers and flags are exact in the
    float dtype (counts stay far below 2^24)."""
    leaves, tree = jax.tree.flatten(out)
    packed = jnp.concatenate([x.reshape(x.shape[0], -1).astype(dtype) for x in leaves], axis=1)
    return packed, jax.tree.unflatten(tree, [jnp.zeros((0, *x.shape[1:]), x.dtype)
                                             for x in leaves])


def unpack_results(packed: np.ndarray, spec) -> dict:
    """The results :func:`pack` packed, as numpy arrays of their own shapes and dtypes."""
    leaves, tree = jax.tree.flatten(spec)
    sizes = [int(np.prod(x.shape[1:], dtype=np.int64)) for x in leaves]
    cols = np.split(packed, np.cumsum(sizes)[:-1], axis=1)
    return jax.tree.unflatten(tree, [c.reshape(packed.shape[0], *x.shape[1:]).astype(x.dtype)
                                     for c, x in zip(cols, leaves)])
