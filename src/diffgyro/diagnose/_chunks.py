"""Every device through the compiled programs, a chunk of devices at a time.

The candidates' ranges and the scoring run on about :data:`CHUNK_SAMPLES` samples per
compiled call, a power-of-two number of devices per chunk so that few shapes compile, and
one device at a time inside (``lax.map``): memory is that of one device's per-sample
arrays, whatever the batch.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._jit import by_work, signature
from .._signal_builder import batch_inputs, input_signals
from .._xla_options import ONE_PART
from ..data import Batch, as_slice, device_bucket
from ..model import ErrorModel
from ._ahead import AHEAD, Setting
from ._candidates import CandidateSpec
from ._floor import white_noise_rms
from ._random_walk import random_walk_scores, segment_length
from ._scoring import (
    CandidateScores,
    base_scores,
    block_windows,
    candidate_scores,
    design_and_residual,
    segments,
    window,
)
from ._scoring import segment_length as search_length

#: About this many samples (devices × padded length) go through one compiled call.
CHUNK_SAMPLES = 1 << 18


def chunk_size(n_devices: int, length: int) -> int:
    """Devices per compiled call: a power of two, about :data:`CHUNK_SAMPLES` samples."""
    g = 1 << max((CHUNK_SAMPLES // max(length, 1)).bit_length() - 1, 0)
    return max(1, min(device_bucket(n_devices, minimum=1), g))


def chunks(n_devices: int, size: int):
    """Device indices of each chunk, the last device repeated to fill the last chunk."""
    for start in range(0, n_devices, size):
        yield start, np.minimum(np.arange(start, start + size), n_devices - 1)


def put(x: np.ndarray) -> jax.Array:
    """A host array on the device as it is: ``jnp.asarray`` of a numpy array compiles a
    staging program for every new shape, ``device_put`` does not."""
    return jax.device_put(np.asarray(x))


def spec(x: np.ndarray) -> jax.ShapeDtypeStruct:
    """The shape and dtype :func:`put` gives ``x`` on the device, without moving it."""
    x = np.asarray(x)
    return jax.ShapeDtypeStruct(x.shape, jax.dtypes.canonicalize_dtype(x.dtype))


def _inputs(batch: Batch, st: Setting, idx: np.ndarray, aux: dict, put=put) -> dict:
    """One chunk's samples, the fit's temperature normalisation (``st``) and sampling
    intervals and the extra columns ``aux`` (centred and scaled, :func:`._plan._extra_columns`)."""
    take = as_slice(idx)  # devices in order: views of the batch, not copies
    return batch_inputs(batch, take, st.norm, aux, put=put)


def _ranges_of(cands, inputs, dtemp_window):
    """Per device of a chunk: > 0 where its data cannot support a candidate (``dtemp_window``
    an array: traced, one program for every window)."""
    def one(inp):
        s = input_signals(inp, dtemp_window)
        return jnp.stack([c.term.range_problem(s) for c in cands]) if cands else jnp.zeros((0,))

    return jax.lax.map(one, inputs)


#: :func:`_ranges_of` compiled for a batch's size (:func:`~diffgyro._jit.by_work`); a
#: small batch's as one part (:data:`~diffgyro._xla_options.ONE_PART`): the plan waits for
#: its compilation.
_ranges = by_work(_ranges_of, persistent=True, small_options=ONE_PART)


def _white_noise(batch: Batch) -> np.ndarray:
    """The decision's white-noise level (devices, 3), on the host."""
    out = []
    for i in range(batch.n_devices):
        rate = None if batch.rate is None else np.asarray(batch.rate[i], np.float64)
        gyro = np.asarray(batch.gyro[i], np.float64)
        out.append(white_noise_rms(gyro if rate is None else gyro - rate, np.asarray(batch.mask[i]), rate))
    return np.stack(out)


def _device_scores(base: ErrorModel, cands: tuple[CandidateSpec, ...], n_blocks: int,
                   n_folds: int, log_min_lag, rw_m: int, search_m: int, dtemp_window, inp: dict,
                   beta_b, theta_b, floor_axes, idx, inside, dt0) -> dict:
    """Held-out scores of the base model, every deterministic candidate and the random walk
    (``log_min_lag``, ``dtemp_window``: traced scalars, :func:`_windows`; ``rw_m``,
    ``search_m``: samples per segment of the random-walk check and the time-constant
    search; ``dt0``: the median sample interval, :func:`_median_steps`)."""
    sig = input_signals(inp, dtemp_window)
    dtype = sig.gyro.dtype
    y = sig.gyro - sig.rate
    w = sig.mask.astype(dtype)
    xb = base.design(sig, theta_b) if base.n_params else jnp.zeros((y.shape[0], 3, 0), dtype)
    e = (y - jnp.einsum("nip,ip->ni", xb, beta_b)) * w[:, None]  # base residual (full fit)
    e = jnp.where(jnp.isfinite(e), e, 0.0)
    xe_w = design_and_residual(xb, e, idx, inside)
    b = base_scores(xe_w, inside, n_folds)
    searched = any(c.old is None and c.term.n_nonlinear for c in cands)  # a time-constant grid
    seg = segments(sig, xe_w, idx, inside, search_m, n_folds) if searched else None
    scores = [candidate_scores(c, base, sig, theta_b, log_min_lag, b, xe_w, idx, inside, seg, n_folds)
              for c in cands]
    base_full = jnp.sum(e * e, 0)
    rw = random_walk_scores(xe_w, window(sig.t, idx, inside), inside, b.b_base,
                            b.base_sse, b.base_blk, base_full, floor_axes, dt0, rw_m)
    out = dict(cnt=b.cnt, base_sse=b.base_sse, base_full=base_full, blk_cnt=b.blk_cnt,
               base_blk=b.base_blk, residual=e, **_fields(rw),
               **_stacked(scores, n_folds, n_blocks, dtype))
    if sig.dtemp is not None:
        out["dtemp"] = sig.dtemp
    if sig.heating is not None:
        out["heating"] = sig.heating
    return out


def _stacked(scores: list[CandidateScores], n_folds: int, n_blocks: int, dtype) -> dict:
    """The candidates' scores stacked on a leading axis (one NaN placeholder when there are
    none: lax.map dislikes empty outputs)."""
    if not scores:
        return dict(cand_sse=jnp.full((1, n_folds, 3), jnp.nan, dtype),
                    cand_full=jnp.full((1, 3), jnp.nan, dtype), cand_theta=jnp.full((1, 1), jnp.nan, dtype),
                    cand_blk=jnp.full((1, n_blocks), jnp.nan, dtype), cand_edge=jnp.zeros((1,), bool))
    q = max(int(s.theta.shape[0]) for s in scores)
    theta = [jnp.pad(s.theta, (0, q - s.theta.shape[0]), constant_values=jnp.nan) for s in scores]
    return dict(cand_sse=jnp.stack([s.held for s in scores]),
                cand_full=jnp.stack([s.full for s in scores]), cand_theta=jnp.stack(theta),
                cand_blk=jnp.stack([s.blk for s in scores]),
                cand_edge=jnp.stack([s.edge for s in scores]))


def _fields(module: eqx.Module) -> dict:
    """A module's fields by name: the engine's output is keyed like :attr:`Diagnosis.raw`."""
    return {f.name: getattr(module, f.name) for f in dataclasses.fields(module)}


def _scores(base, cands, n_blocks, n_folds, log_min_lag, rw_m, search_m, dtemp_window, inputs,
            beta, theta, floors, idx, inside, dt0):
    def one(args):
        inp, b, th, fl, ix, ins, dt = args
        return _device_scores(base, cands, n_blocks, n_folds, log_min_lag, rw_m, search_m,
                              dtemp_window, inp, b, th, fl, ix, ins, dt)

    return jax.lax.map(one, (inputs, beta, theta, floors, idx, inside, dt0))


#: :func:`_scores` compiled for a batch's size (the diagnosis engine,
#: :func:`~diffgyro._jit.by_work`); a small batch's as one part
#: (:data:`~diffgyro._xla_options.ONE_PART`): it compiles beside the base fit.
engine = by_work(_scores, persistent=True, small_options=ONE_PART)


def _median_steps(t: np.ndarray) -> np.ndarray:
    """Every device's median step of ``t`` (devices, length), padding included, at least
    1e-12 s: on the host, whose median selects in linear time where the compiled
    program sorted the whole record."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a device of one sample
        return np.maximum(np.nanmedian(np.diff(t, axis=1), axis=1), 1e-12)


def _windows(dtemp_window: float, put=put):
    """The dT/dt window (s) as the compiled programs take it: arrays, traced, so that every
    window shares one program; and the log of the shortest time constant a lag term's grid
    starts at (the window, −inf for none), taken on the host."""
    w = float(dtemp_window)
    log_min_lag = math.log(w) if w > 0 else -math.inf
    return put(np.float64(log_min_lag)), put(np.float64(w))


def _gather(chunks: list[dict], n_dev: int) -> dict:
    """Chunk outputs joined on the device axis, the repeated devices dropped."""
    return {k: np.concatenate([np.asarray(c[k]) for c in chunks])[:n_dev] for k in chunks[0]}


def prepare(batch: Batch, st: Setting, every: list[CandidateSpec], aux: dict,
             meanwhile=None):
    """Ranges of every candidate and floors, streamed per chunk of devices (``meanwhile``:
    called while the ranges' program compiles, or is read from the caches, on a thread)."""
    n_dev, length = batch.n_devices, batch.t.shape[1]
    size = chunk_size(n_dev, length)
    window_s = _windows(st.dtemp_window)[1]
    program = _ranges(n_dev * length)
    if meanwhile is not None:
        _, idx = next(chunks(n_dev, size))
        compiling = program.compile_ahead(tuple(every), _inputs(batch, st, idx, aux, spec),
                                          _windows(st.dtemp_window, spec)[1])
        meanwhile()
        compiling.join()
    ranges = [np.asarray(program(tuple(every), _inputs(batch, st, idx, aux), window_s))
              for _, idx in chunks(n_dev, size)]
    return np.concatenate(ranges)[:n_dev], _white_noise(batch)


def chunk_args(model, cands, batch: Batch, st: Setting, floors, aux: dict, beta, theta, idx,
                windows, dt0, put=put) -> tuple:
    """The scoring program's arguments for the devices ``idx`` (``windows``: their fold
    blocks, :func:`block_windows`; ``put``: :func:`put`, or :func:`spec` for shapes)."""
    length = batch.t.shape[1]
    ix = np.stack([windows[i][0] for i in idx])
    ins = np.stack([windows[i][1] for i in idx])
    log_min_lag, window_s = _windows(st.dtemp_window, put)
    return (model, tuple(cands), st.n_blocks, st.n_folds, log_min_lag,
            segment_length(length, st.n_blocks), search_length(length, st.n_blocks), window_s,
            _inputs(batch, st, idx, aux, put), put(beta[idx]), put(theta[idx]), put(floors[idx]),
            put(ix), put(ins), put(dt0[idx]))


def score(model, cands, batch, st: Setting, params, floors, aux: dict, say=lambda _text: None,
           ahead=None) -> dict:
    """Every device's scores (:func:`_device_scores`), one chunk of devices at a time
    (``params``: the base fit's; ``say``: told before each chunk; ``ahead``: the signature
    the program was compiled ahead for and the thread compiling it, :func:`._plan._ahead_programs`)."""
    n_dev, length = batch.n_devices, batch.t.shape[1]
    size = chunk_size(n_dev, length)
    beta, theta = np.asarray(params.beta), np.asarray(params.theta)
    windows = [block_windows(np.asarray(batch.mask[i]), st.n_blocks) for i in range(n_dev)]
    dt0 = _median_steps(np.asarray(batch.t))
    program = engine(n_dev * length)
    out = []
    for start, idx in chunks(n_dev, size):
        say(f"scoring {len(cands)} candidate(s) on devices {start + 1}-{min(start + size, n_dev)} "
            f"of {n_dev}")
        args = chunk_args(model, cands, batch, st, floors, aux, beta, theta, idx, windows, dt0)
        if ahead is not None:
            foreseen, thread = ahead
            hit = foreseen == signature(*args)
            if hit:
                thread.join()
            AHEAD["hit" if hit else "miss"] += 1
            ahead = None
        out.append(jax.device_get(program(*args)))
    out = _gather(out, n_dev)
    if not cands:
        for k in ("cand_sse", "cand_full", "cand_theta", "cand_blk", "cand_edge"):
            out[k] = out[k][:, :0]
    return out
