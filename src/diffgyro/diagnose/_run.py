"""diagnose(model, batch): the base fit, then every device through the scoring, in chunks.

Devices go through the compiled programs a chunk at a time (about
:data:`CHUNK_SAMPLES` samples per chunk, a power-of-two number of devices so
that few shapes compile), one device at a time inside (``lax.map``): memory
is that of one device's per-sample arrays, whatever the batch.

What the scoring reads of the base fit besides its coefficients is known before the fit
(:mod:`._ahead`), so the candidates' ranges run first and the scoring program and the
residuals' Allan deviation are compiled, or read from the caches, on threads while the
fit runs (:func:`_ahead_programs`); after the fit the prediction is checked bit for bit.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import math
import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _aux as aux_cols
from .. import _noise as noise
from .. import allan as allan_mod
from .. import motion as motion_mod
from .._jit import by_work, filter_jit, release_compiled_if_crowded, signature
from .._signal_builder import batch_inputs, input_signals
from .._temperature import suggest_dtemp_window
from .._xla_options import ONE_PART
from ..channel import GRAVITY, UNITS, as_channel, check_channel, reads_gravity
from ..data import Batch, Recording, as_batch, as_slice, aux_key, device_bucket
from ..effects import AbstractNoise, RandomWalk, is_column_name
from ..errors import SpecError
from ..fit import fit as fit_fn
from ..model import ErrorModel
from ..signals import TempNorm
from ._ahead import Setting, of_fit, predicted, same
from ._candidates import CandidateSpec, candidate_specs, term_column, unnamed_columns
from ._decision import allan_slope, decide, not_judged
from ._evidence import evidence
from ._floor import white_noise_rms
from ._greedy import pairs as greedy_pairs
from ._noise_model import attach_noise, residual_floor
from ._random_walk import random_walk_scores, segment_length
from ._results import AllanCurves, Diagnosis
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
from ._synthesis import apply as synthesise
from ._synthesis import apply_one as synthesise_one
from ._thresholds import Thresholds
from ._unsupported import reason as unsupported_reason

#: About this many samples (devices × padded length) go through one compiled call.
CHUNK_SAMPLES = 1 << 18

NOISE_UNSCORED = "diagnose scores one noise process, the random walk; fit this one directly"

#: How the programs prepared before the fit served (``"hit"``: the scoring's call ran the
#: program compiled ahead; ``"miss"``: its arguments' shapes differed from those foreseen;
#: ``"refit"``: the fit's setting differed from the prediction, so the ranges and the
#: candidates were formed again from the fit). Tests read it; nothing else does.
AHEAD: collections.Counter = collections.Counter()


def chunk_size(n_devices: int, length: int) -> int:
    """Devices per compiled call: a power of two, about :data:`CHUNK_SAMPLES` samples."""
    g = 1 << max((CHUNK_SAMPLES // max(length, 1)).bit_length() - 1, 0)
    return max(1, min(device_bucket(n_devices, minimum=1), g))


def _chunks(n_devices: int, size: int):
    """Device indices of each chunk, the last device repeated to fill the last chunk."""
    for start in range(0, n_devices, size):
        yield start, np.minimum(np.arange(start, start + size), n_devices - 1)


def _put(x: np.ndarray) -> jax.Array:
    """A host array on the device as it is: ``jnp.asarray`` of a numpy array compiles a
    staging program for every new shape, ``device_put`` does not."""
    return jax.device_put(np.asarray(x))


def _spec(x: np.ndarray) -> jax.ShapeDtypeStruct:
    """The shape and dtype :func:`_put` gives ``x`` on the device, without moving it."""
    x = np.asarray(x)
    return jax.ShapeDtypeStruct(x.shape, jax.dtypes.canonicalize_dtype(x.dtype))


def _inputs(batch: Batch, st: Setting, idx: np.ndarray, aux: dict, put=_put) -> dict:
    """One chunk's samples, the fit's temperature normalisation (``st``) and sampling
    intervals and the extra columns ``aux`` (centred and scaled, :func:`_extra_columns`)."""
    take = as_slice(idx)  # devices in order: views of the batch, not copies
    return batch_inputs(batch, take, st.norm, aux, put=put)


def _extra_columns(batch: Batch, model: ErrorModel, st: Setting) -> tuple[dict, dict]:
    """The extra columns diagnose reads, centred and scaled ((devices, n) each, zero where
    not finite): those the model reads with the base fit's centring, the others (candidate
    ``aux`` terms) with each device's own range; and, per column the model does not read,
    every device's problem with it (None: usable, see ``_aux.column_problem``)."""
    used = aux_cols.aux_names(model.requires())
    problems = {k: aux_cols.device_problems(batch, k) for k in batch.aux if k not in used}
    fresh = [k for k, p in problems.items() if any(q is None for q in p)]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN devices: skipped below
        norms = {**{k: TempNorm(centre=np.asarray(v.centre), scale=np.asarray(v.scale))
                    for k, v in st.aux_norm.items()}, **aux_cols.norms(batch, fresh)}
        scaled = aux_cols.scaled(batch, norms)
    return {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in scaled.items()}, problems


def _column_skips(every: list[CandidateSpec], ranges: np.ndarray, problems: dict,
                  batch: Batch) -> list[dict]:
    """Per device, the column candidates (``aux(vdd)``) it skips and why: its column is
    unusable (``_aux.column_problem``; the candidate's range marked so) or its
    data cannot support the term (:func:`._unsupported.reason`)."""
    n_dev = batch.n_devices
    skips: list[dict] = [{} for _ in range(n_dev)]
    for j, c in enumerate(every):
        col = term_column(c.term)
        if col is None:
            continue
        for i in range(n_dev):
            why = problems.get(col, [None] * n_dev)[i]
            if why is not None:
                ranges[i, j] = 1.0
                skips[i][c.term.spec] = why
            elif ranges[i, j] > 0:
                skips[i][c.term.spec] = unsupported_reason(c.term, batch.recording(i))
    return skips


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
_engine = by_work(_scores, persistent=True, small_options=ONE_PART)


#: The residuals' Allan deviation (:func:`diffgyro.allan.oadev`, with its options)
#: compiled for a batch's size (:func:`~diffgyro._jit.by_work`): a small batch's without
#: optimisation, as one part, compiles in about a fifth of the time, with the same bits
#: (its differences and sums run in the program's order either way).
_oadev = by_work(allan_mod.oadev.__wrapped__, compiler_options=allan_mod.OADEV_OPTIONS,
                 small_options=ONE_PART)


def _median_steps(t: np.ndarray) -> np.ndarray:
    """Every device's median step of ``t`` (devices, length), padding included, at least
    1e-12 s: on the host, whose median selects in linear time where the compiled
    program sorted the whole record."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a device of one sample
        return np.maximum(np.nanmedian(np.diff(t, axis=1), axis=1), 1e-12)


def _windows(dtemp_window: float, put=_put):
    """The dT/dt window (s) as the compiled programs take it: arrays, traced, so that every
    window shares one program; and the log of the shortest time constant a lag term's grid
    starts at (the window, −inf for none), taken on the host."""
    w = float(dtemp_window)
    log_min_lag = math.log(w) if w > 0 else -math.inf
    return put(np.float64(log_min_lag)), put(np.float64(w))


def _gather(chunks: list[dict], n_dev: int) -> dict:
    """Chunk outputs joined on the device axis, the repeated devices dropped."""
    return {k: np.concatenate([np.asarray(c[k]) for c in chunks])[:n_dev] for k in chunks[0]}


def _prepare(batch: Batch, st: Setting, every: list[CandidateSpec], aux: dict,
             meanwhile=None):
    """Ranges of every candidate and floors, streamed per chunk of devices (``meanwhile``:
    called while the ranges' program compiles, or is read from the caches, on a thread)."""
    n_dev, length = batch.n_devices, batch.t.shape[1]
    size = chunk_size(n_dev, length)
    window_s = _windows(st.dtemp_window)[1]
    program = _ranges(n_dev * length)
    if meanwhile is not None:
        _, idx = next(_chunks(n_dev, size))
        compiling = program.compile_ahead(tuple(every), _inputs(batch, st, idx, aux, _spec),
                                          _windows(st.dtemp_window, _spec)[1])
        meanwhile()
        compiling.join()
    ranges = [np.asarray(program(tuple(every), _inputs(batch, st, idx, aux), window_s))
              for _, idx in _chunks(n_dev, size)]
    return np.concatenate(ranges)[:n_dev], _white_noise(batch)


def _chunk_args(model, cands, batch: Batch, st: Setting, floors, aux: dict, beta, theta, idx,
                windows, dt0, put=_put) -> tuple:
    """The scoring program's arguments for the devices ``idx`` (``windows``: their fold
    blocks, :func:`block_windows`; ``put``: :func:`_put`, or :func:`_spec` for shapes)."""
    length = batch.t.shape[1]
    ix = np.stack([windows[i][0] for i in idx])
    ins = np.stack([windows[i][1] for i in idx])
    log_min_lag, window_s = _windows(st.dtemp_window, put)
    return (model, tuple(cands), st.n_blocks, st.n_folds, log_min_lag,
            segment_length(length, st.n_blocks), search_length(length, st.n_blocks), window_s,
            _inputs(batch, st, idx, aux, put), put(beta[idx]), put(theta[idx]), put(floors[idx]),
            put(ix), put(ins), put(dt0[idx]))


def _score(model, cands, batch, st: Setting, params, floors, aux: dict, say=lambda _text: None,
           ahead=None) -> dict:
    """Every device's scores (:func:`_device_scores`), one chunk of devices at a time
    (``params``: the base fit's; ``say``: told before each chunk; ``ahead``: the signature
    the program was compiled ahead for and the thread compiling it, :func:`_ahead_programs`)."""
    n_dev, length = batch.n_devices, batch.t.shape[1]
    size = chunk_size(n_dev, length)
    beta, theta = np.asarray(params.beta), np.asarray(params.theta)
    windows = [block_windows(np.asarray(batch.mask[i]), st.n_blocks) for i in range(n_dev)]
    dt0 = _median_steps(np.asarray(batch.t))
    engine = _engine(n_dev * length)
    out = []
    for start, idx in _chunks(n_dev, size):
        say(f"scoring {len(cands)} candidate(s) on devices {start + 1}-{min(start + size, n_dev)} "
            f"of {n_dev}")
        args = _chunk_args(model, cands, batch, st, floors, aux, beta, theta, idx, windows, dt0)
        if ahead is not None:
            foreseen, thread = ahead
            hit = foreseen == signature(*args)
            if hit:
                thread.join()
            AHEAD["hit" if hit else "miss"] += 1
            ahead = None
        out.append(jax.device_get(engine(*args)))
    out = _gather(out, n_dev)
    if not cands:
        for k in ("cand_sse", "cand_full", "cand_theta", "cand_blk", "cand_edge"):
            out[k] = out[k][:, :0]
    return out


def _allan_args(resid: np.ndarray | None, batch: Batch, put=_put):
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


def _allan_program(batch: Batch):
    """The Allan deviation's program for ``batch``'s residuals (:data:`_oadev`)."""
    return _oadev(device_bucket(batch.n_devices, minimum=1) * 3 * batch.t.shape[1])


def _allan(resid: np.ndarray, batch: Batch, ahead=None) -> AllanCurves:
    """Overlapping Allan deviation of every device's residual (devices, 3, k) (``ahead``:
    the thread compiling its program, joined first)."""
    n_dev = batch.n_devices
    args, dts, m = _allan_args(resid, batch)
    if ahead is not None:
        ahead.join()
    adev, _ = _allan_program(batch)(*args)
    adev = np.asarray(adev)[:n_dev]
    tau = dts[:, None, None] * np.asarray(m)[None, None, :] * np.ones((1, 3, 1))
    return AllanCurves(tau=tau, adev=adev)


@filter_jit
def _nonlinear_values(term, theta):
    """``term.nonlinear_values(theta)`` as one program (run eagerly, its clip and exp were
    two, each compiled, or read from the cache, in every process; the same bits)."""
    return term.nonlinear_values(theta)


def _taus(cands, theta_row) -> list:
    """The chosen time constant (s) of every candidate with one, else None."""
    taus = []
    for c, th in zip(cands, theta_row):
        if c.old is None and c.term.n_nonlinear == 1 and np.isfinite(th).all():
            taus.append(float(np.asarray(_nonlinear_values(c.term, _put(th)))[0]))
        else:
            taus.append(None)
    return taus


def _reported_floor(batch: Batch, res) -> list[tuple[float, list[float]]]:
    """(noise floor, per axis) of every device: the base fit's (``_noise``),
    computed here when that fit was run without it, so ``diagnose`` and ``fit`` report
    the same floor for the same device."""

    if res.options.noise_floor:
        axes = np.asarray(res.noise_axes, float)
    else:
        axes = noise.noise_axes(np.asarray(batch.gyro), None if batch.rate is None
                                else np.asarray(batch.rate), np.asarray(batch.mask, bool))
    return [(float(f), [float(v) for v in a]) for f, a in zip(noise.noise_floor(axes), axes)]


def _device(i, batch, res, out, cands, ranges, floors, al, rw_spec, th, model, unsupported,
            skips: dict, pair=None):
    """One device's :class:`DeviceDiagnosis` from its scores (floors: the white-noise level
    the decision uses); slope and floor_allan too. ``skips``: the column candidates it skips
    and why (:func:`_column_skips`), listed by term; ``pair``: :class:`.greedy.Pair`."""
    nv = int(batch.n_valid[i])
    total = float(batch.t[i, nv - 1] - batch.t[i, 0])
    adev, tau = al.adev[i], al.tau[i]
    slope = allan_slope(adev, tau, total)
    first = np.isfinite(adev[:, 0])
    floor_allan = float(np.sqrt(np.mean(adev[first, 0] ** 2))) if first.any() else float("nan")
    status = res.status_name(i)
    if status != "ok" or not (np.all(np.isfinite(np.asarray(res.params.beta[i])))
                              and np.all(np.isfinite(np.asarray(res.params.theta[i])))):
        d = not_judged(batch.devices[i], status, res.status_detail(i), floors[i],
                       float(res.rms[i]), float(res.heldout_rms[i]))
        d.skipped.update(skips)
        return d, slope, floor_allan
    sd = {k: (out[k][i, :nv] if k in out else None) for k in ("dtemp", "heating")}
    rec = batch.recording(i)
    ev = evidence(out["residual"][i, :nv], rec, sd, floors[i])
    ok = ranges[i] <= 0 if ranges.size else np.zeros(0, bool)
    why = {j: unsupported_reason(c.term, rec, sd["dtemp"], sd["heating"])
           for j, c in enumerate(cands) if not ok[j] and term_column(c.term) is None}
    d = decide(
        batch.devices[i], res.status_name(i), out["base_sse"][i], out["cnt"][i],
        out["base_full"][i], [c.effect for c in cands], [c.spec for c in cands],
        out["cand_sse"][i], out["cand_full"][i], ok, _taus(cands, out["cand_theta"][i]), rw_spec,
        out["rw_interp"][i], out["rw_full"][i], floors[i], floor_allan, slope, nv, th, ev,
        blocks={"cnt": out["blk_cnt"][i], "base": out["base_blk"][i], "cand": out["cand_blk"][i]},
        edge=out["cand_edge"][i], base_spec=model.spec, pair=pair, why=why)
    d.status_detail = res.status_detail(i)
    for c in unsupported:  # column candidates are listed by term (aux(vdd)), in skips
        d.skipped[c.effect] = unsupported_reason(c.term, rec, sd["dtemp"], sd["heating"])
    d.skipped.update(skips)
    return d, slope, floor_allan


def _candidates(model: ErrorModel, batch: Batch, st: Setting, names):
    """The deterministic candidates, the random walk's spec (or None), the extra columns
    their terms read (:func:`_extra_columns`), every column's problems per device, the
    column candidates no device can use (listed under skipped, never compiled) and the
    other noise processes offered (listed under skipped: the smoother scored here is the
    random walk's); the column terms that cannot be written (:func:`.unnamed_columns`)."""
    aux, problems = _extra_columns(batch, model, st)
    unnamed = unnamed_columns(problems, names)
    specs = candidate_specs(model, frozenset(batch.signals) | {aux_key(k) for k in batch.aux},
                            names, columns=tuple(k for k in problems if is_column_name(k)))
    dead = [c for c in specs if term_column(c.term) is not None and term_column(c.term) not in aux]
    every = [c for c in specs if not isinstance(c.term, AbstractNoise) and c not in dead]
    noise = [c for c in specs if isinstance(c.term, AbstractNoise)]
    walk = next((c for c in noise if isinstance(c.term, RandomWalk)), None)
    unscored = [c.effect for c in noise if c is not walk]
    read = set(st.aux_norm) | {term_column(c.term) for c in every}
    return (every, walk.spec if walk else None, {k: v for k, v in aux.items() if k in read},
            problems, dead, unscored, unnamed)


class _Plan(NamedTuple):
    """What is scored, decided before the scoring: the setting it was formed for, the
    candidates (``every`` tried, ``cands`` those some device supports, ``unsupported``
    those none does), the random walk's spec, the extra columns, every candidate's range
    problem and the white-noise floors per device, what each device skips and why, and the
    programs prepared ahead (:func:`_ahead_programs`: None, or the scoring's signature and
    thread and the Allan deviation's thread)."""

    setting: Setting
    every: list
    cands: list
    unsupported: list
    rw_spec: str | None
    aux: dict
    all_ranges: np.ndarray
    usable: list
    floors: np.ndarray
    skips: list
    ahead: tuple | None = None


def _plan(model: ErrorModel, batch: Batch, st: Setting, names, say, meanwhile=None) -> _Plan:
    """The :class:`_Plan` of ``model`` on ``batch`` with the base fit's setting ``st``: the
    candidates, their ranges (a compiled program per chunk of devices) and the floors
    (``meanwhile``: :func:`_prepare`'s)."""
    every, rw_spec, aux, problems, dead, unscored, unnamed = _candidates(model, batch, st, names)
    say(f"checking which of {len(every)} candidate(s) the data support")
    all_ranges, floors = _prepare(batch, st, every, aux, meanwhile)
    skips = _skips(every, all_ranges, problems, batch, dead, unscored, unnamed)
    # drop candidates no device can support (e.g. scale terms on a static run) before compiling
    usable = [j for j in range(len(every)) if np.any(all_ranges[:, j] <= 0)]
    cands = [every[j] for j in usable]
    unsupported = [c for j, c in enumerate(every)
                   if j not in usable and term_column(c.term) is None]
    return _Plan(st, every, cands, unsupported, rw_spec, aux, all_ranges, usable, floors, skips)


def _ahead_programs(model: ErrorModel, batch: Batch, plan: _Plan) -> tuple:
    """Start compiling (or reading from the caches) the scoring program for the first chunk
    of devices and the residuals' Allan deviation, each on a thread of its own, from their
    arguments' shapes: the base fit's coefficients are the only inputs not known yet.
    Returns (the scoring's signature, its thread, the Allan deviation's thread)."""
    st = plan.setting
    n_dev, length = batch.n_devices, batch.t.shape[1]
    size = chunk_size(n_dev, length)
    _, idx = next(_chunks(n_dev, size))
    dtype = jax.dtypes.canonicalize_dtype(np.float64)
    beta = np.zeros((n_dev, 3, model.n_params), dtype)
    theta = np.zeros((n_dev, model.n_nonlinear), dtype)
    windows = {i: block_windows(np.asarray(batch.mask[i]), st.n_blocks) for i in idx}
    dt0 = np.zeros(n_dev, dtype)
    args = _chunk_args(model, plan.cands, batch, st, plan.floors, plan.aux, beta, theta, idx,
                       windows, dt0, put=_spec)
    allan = _allan_program(batch).compile_ahead(*_allan_args(None, batch, put=_spec)[0])
    return signature(*args), _engine(n_dev * length).compile_ahead(*args), allan


def _first_programs(batch: Batch, fit_options: dict):
    """A function that starts compiling (or reading from the caches), once, the programs
    whose shapes follow from the batch alone: the base fit's motion check
    (:func:`diffgyro.motion.program_ahead`; the fit's own ``check_ahead`` then waits for
    this compilation) and the residuals' Allan deviation (:func:`_ahead_programs` asks
    for it again and gets this thread). The plan calls it while the ranges' program
    compiles (:func:`_prepare`): their traces fill that wait, and XLA compiles them
    while the plan traces the scoring program, whose compilation, the longest, still
    starts as early."""
    done = []

    def start() -> None:
        if done:
            return
        done.append(True)
        try:
            if fit_options.get("check_motion", True) and not fit_options.get("static_only"):
                motion_mod.program_ahead(batch)
            _allan_program(batch).compile_ahead(*_allan_args(None, batch, put=_spec)[0])
        except Exception:  # noqa: BLE001 - the fit and the scoring compile what they need
            logging.getLogger("diffgyro").debug("diagnose: no programs before the plan",
                                                exc_info=True)

    return start


def _planned_ahead(model, batch: Batch, names, fit_options: dict, say,
                   meanwhile=None) -> _Plan | None:
    """The plan formed before the base fit from the setting it will hold (:mod:`._ahead`),
    its programs started (:func:`_ahead_programs`); None where the setting is not foreseen
    or forming the plan fails (the fit then raises its own error, or the plan is formed
    after it). ``meanwhile``: called while the ranges' program compiles
    (:func:`_first_programs`)."""
    try:
        st = predicted(model, batch, fit_options)
        if st is None:
            return None
        plan = _plan(model, batch, st, names, say, meanwhile)
        return plan._replace(ahead=_ahead_programs(model, batch, plan))
    except Exception:  # noqa: BLE001 - formed again after the fit, which raises what is wrong
        logging.getLogger("diffgyro").debug("diagnose: no plan before the fit", exc_info=True)
        return None


def _plan_of_fit(plan: _Plan | None, model, batch: Batch, res, names, say) -> _Plan:
    """The plan formed before the fit where the fit's setting is the one foreseen, else the
    plan formed from the fit (the programs started before it kept: they serve where their
    arguments' shapes still hold, which :func:`_score` checks)."""
    if plan is not None and same(plan.setting, of_fit(res)):
        return plan
    AHEAD["refit"] += plan is not None
    return _plan(model, batch, of_fit(res), names, say)._replace(
        ahead=None if plan is None else plan.ahead)


def _skips(every, all_ranges, problems, batch, dead, unscored, unnamed) -> list[dict]:
    """Per device, every candidate not tried and why (:func:`_column_skips`, the column
    candidates no device can use, the noise processes not scored, the unnamed columns)."""
    skips = _column_skips(every, all_ranges, problems, batch)
    for c in dead:
        for i, why in enumerate(problems[term_column(c.term)]):
            skips[i][c.term.spec] = why
    for name, skip in ((n, s) for n in unscored for s in skips):
        skip[name] = NOISE_UNSCORED
    for skip in skips:
        skip.update(unnamed)
    return skips


def _rescorer(devices, batch, res, out, cands, ranges, floors, al, rw_spec, th, model,
              unsupported, skips, reported, synthesis: bool):
    """``rescore(i, floor_axes, builtin)``: device i's decision against another per-axis
    floor (the white level + the identified Gauss–Markov power, :mod:`.noise_model`), then,
    where no built-in term closes the gap, the synthesis judged against the noise its terms
    leave. Without ``builtin`` the white-floor decision is kept and only the synthesis runs
    (None unless it proposes a term)."""
    def rescore(i, floor_axes, builtin=True):
        if builtin:
            fl = np.array(floors, copy=True)
            fl[i] = floor_axes
            alt = _device(i, batch, res, out, cands, ranges, fl, al, rw_spec, th, model,
                          unsupported, skips[i])[0]
            alt.noise_floor, alt.noise_axes = reported[i]
        else:
            alt = devices[i]
        prop = synthesise_one(i, alt, batch, res, model, cands, ranges <= 0, th,
                              devices[i].white_noise_rms,
                              lambda k, e: residual_floor(e, batch.t[k], floors[k])) \
            if synthesis else None
        return alt if builtin or prop is not None else None

    return rescore


def _nested_options(opts, fit_options: dict) -> dict:
    """The nested diagnosis's options: the base fit's folds and dT/dt window (``opts``), the
    caller's fit options, no synthesis, and no second motion check (:func:`_nested`)."""
    nested = {"n_blocks": opts.n_blocks, "n_folds": opts.n_folds,
              "dtemp_window": opts.dtemp_window, "synthesis": False, **fit_options}
    if not fit_options.get("static_only"):  # (static_only fits the check's rests)
        nested["check_motion"] = False
    return nested


def _nested(*args, **kwargs) -> Diagnosis:
    """The greedy pair's nested diagnosis: its residual's noise is not reported, and its
    fit does not check the recordings for motion again: a pair is formed only for a device
    the base fit's check found fit to judge, and the check's programs (compiled for the
    sub-batch's size) were most of a nested diagnosis's compile time after the scoring's."""
    return diagnose(*args, noise=False, **kwargs)


def _in_units(devices, channel: str) -> None:
    """The explanations in the channel's unit (the accelerometer's measurement is in m/s²,
    where the wording is the gyro's rad/s)."""
    if channel != "gyro":
        for d in devices:
            d.explanation = d.explanation.replace("rad/s", UNITS[channel])


def _base_fit(model, batch: Batch, base_fit, channel: str, fit_options: dict):
    """The fit the diagnosis starts from and the batch its candidates are scored on (the
    accelerometer less its gravity reference, on that channel)."""
    extra = {} if channel == "gyro" else {"channel": channel}
    res = base_fit if base_fit is not None else fit_fn(model, batch, **fit_options, **extra)
    if channel != "gyro":  # several orientations: the rests the fit read, gravity their input
        static = res.motion.static if reads_gravity(model) else None
        batch, _ = as_channel(batch, channel, getattr(res, "reference", None), static=static,
                              gravity=fit_options.get("gravity", GRAVITY))
    return res, batch


def diagnose(
    model: ErrorModel | str,
    batch: Batch | Recording | list[Recording],
    candidates: list[str] | None = None,
    *,
    thresholds: Thresholds | None = None,
    base_fit=None,
    greedy: bool = True,
    synthesis: bool = True,
    noise="auto",
    progress=None,
    channel: str = "gyro",
    **fit_options,
) -> Diagnosis:
    """Diagnose every device of ``batch`` against ``model``.

    ``candidates`` limits the effects tried (names or terms, default: every
    registered effect the data supports). ``base_fit`` reuses a
    :class:`~diffgyro.fit.FitResult` of ``model`` on this batch. Other
    keywords are fit options (``n_folds``, ``n_blocks``, ``dtemp_window``...).
    ``greedy``: before a random walk is named, try the best term followed by the
    best second term (:mod:`.greedy`). ``synthesis``: where no built-in term closes the
    gap, propose a term built from the recording's signals (:mod:`.synthesis`).
    ``noise``: identify the residual's stochastic model ("auto": where the residual is not
    white and no term explains it, ``adequate`` included; True: every judged device; False:
    none; :mod:`.noise_model`).
    ``progress`` is called with a line of text before each stage (the base fit, the
    candidates' ranges, each chunk of devices scored, the pairs, synthesis, noise).
    ``channel="accel"`` diagnoses the accelerometer's thermal offset (relative to its
    gravity reference, :mod:`diffgyro.channel`): the base fit judges rest on the IMU as
    loaded, and the candidates are scored on the accelerometer less its reference.
    Returns a :class:`Diagnosis`; ``.to_json()`` is the ``diagnose --json``
    object.

    **Arguments:**

    - ``model``: the base model: a spec string or an :class:`~diffgyro.model.ErrorModel`.
    - ``batch``: a Batch, one Recording or a list of them.
    - ``candidates``: the effects tried, names or terms (default: every registered effect
      the data supports).
    - ``thresholds``: the decision's :class:`Thresholds` (default: the calibrated ones).
    - ``base_fit``: a :class:`~diffgyro.fit.FitResult` of ``model`` on this batch, reused
      instead of fitting again.
    - ``greedy``: try the best term followed by the best second term before a random walk is
      named.
    - ``synthesis``: propose a term built from the recording's signals where no built-in
      term closes the gap.
    - ``noise``: identify the residual's stochastic model: ``"auto"``, True (every judged
      device) or False.
    - ``progress``: called with a line of text before each stage.
    - ``channel``: ``"gyro"`` or ``"accel"`` (the accelerometer's thermal offset).
    - ``**fit_options``: fit options (``n_folds``, ``n_blocks``, ``dtemp_window``, …).
    """
    release_compiled_if_crowded(interval=1.0)  # before this call compiles its programs

    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    if model.noise is not None:
        raise SpecError(f"diagnose takes a deterministic model, not {model.spec!r}",
                        hint=f"drop {model.noise.spec} from --model: it is tried as a candidate")
    batch = as_batch(batch)
    say = progress or (lambda _text: None)
    th = thresholds or Thresholds()
    if "dtemp_window" not in fit_options and base_fit is None:
        fit_options["dtemp_window"] = suggest_dtemp_window(batch)
    channel = check_channel(channel)
    # on the gyro the batch scored is the one fitted: the plan can be formed before the fit
    plan = None
    if base_fit is None and channel == "gyro":
        first = _first_programs(batch, fit_options)
        plan = _planned_ahead(model, batch, candidates, fit_options, say, first)
        first()  # (where no plan was formed ahead)
    if base_fit is None:
        say(f"fitting {model.spec} on {batch.n_devices} device(s)")
    res, batch = _base_fit(model, batch, base_fit, channel, fit_options)
    plan = _plan_of_fit(plan, model, batch, res, candidates, say)
    cands, unsupported, rw_spec, floors, skips = (plan.cands, plan.unsupported, plan.rw_spec,
                                                  plan.floors, plan.skips)
    ahead = plan.ahead or (None, None, None)
    out = _score(model, cands, batch, plan.setting, res.params, floors, plan.aux, say,
                 None if ahead[1] is None else ahead[:2])
    ranges = plan.all_ranges[:, plan.usable]
    say("Allan deviation of the residuals")
    al = _allan(out["residual"], batch, ahead[2])
    reported = _reported_floor(batch, res)
    devices, slopes, floor_allans = [], [], []
    host = res.on_host()  # read device by device: indexing JAX arrays compiles programs
    for i in range(batch.n_devices):
        d, slope, fa = _device(i, batch, host, out, cands, ranges, floors, al, rw_spec, th, model,
                               unsupported, skips[i])
        d.noise_floor, d.noise_axes = reported[i]
        devices.append(d)
        slopes.append(slope)
        floor_allans.append(fa)
    opts = res.options
    if greedy:
        say("trying the best term followed by a second")
        pairs = greedy_pairs(devices, batch, candidates, th, _nested_options(opts, fit_options),
                             _nested)
        for i, pair in pairs.items():
            devices[i] = _device(i, batch, host, out, cands, ranges, floors, al, rw_spec, th,
                                 model, unsupported, skips[i], pair)[0]
            devices[i].noise_floor, devices[i].noise_axes = reported[i]
    if synthesis:
        say("proposing terms built from the recording's signals")
        synthesise(devices, batch, res, model, cands, ranges <= 0, th)
    rescore = _rescorer(devices, batch, res, out, cands, ranges, floors, al, rw_spec, th, model,
                        unsupported, skips, reported, synthesis)
    say("identifying the residual's noise")
    attach_noise(devices, out["residual"], batch.n_valid, batch.t, noise, rescore, th.excess_min)
    _in_units(devices, getattr(res, "channel", "gyro"))
    raw = {k: v for k, v in out.items() if k not in ("residual", "dtemp", "heating")}
    return Diagnosis(model=model, devices=devices, fit=res, residuals=out["residual"], allan=al,
                     thresholds=th, options={"n_blocks": opts.n_blocks, "n_folds": opts.n_folds,
                                             "dtemp_window": opts.dtemp_window},
                     raw={**raw, "floors": floors, "ok": ranges <= 0, "slope": np.asarray(slopes),
                          "floor_allan": np.asarray(floor_allans), "candidates": cands,
                          "n_valid": np.asarray(batch.n_valid)})
