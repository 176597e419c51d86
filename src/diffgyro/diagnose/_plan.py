"""What is scored, decided before the scoring, and its programs prepared ahead of the fit.

The plan is the candidates, their ranges, the white-noise floors and what each device
skips and why. What the scoring reads of the base fit besides its coefficients is known
before the fit (:mod:`._ahead`), so the plan is formed first and the scoring program and
the residuals' Allan deviation are compiled, or read from the caches, on threads while
the fit runs (:func:`_ahead_programs`); after the fit the prediction is checked bit for
bit and the plan formed again from the fit where it differs (:func:`plan_of_fit`).
"""

from __future__ import annotations

import logging
import warnings
from typing import NamedTuple

import jax
import numpy as np

from .. import _aux as aux_cols
from .._jit import signature
from ..data import Batch, inputs_of
from ..effects import AbstractNoise, RandomWalk, is_column_name
from ..model import ErrorModel
from ..signals import TempNorm
from ._ahead import AHEAD, Setting, of_fit, predicted, same
from ._candidates import CandidateSpec, candidate_specs, term_column, unnamed_columns
from ._chunks import chunk_args, chunk_size, chunks, engine, prepare, spec
from ._residual_allan import allan_args, allan_program
from ._scoring import block_windows
from ._unsupported import reason as unsupported_reason

NOISE_UNSCORED = "diagnose scores one noise process, the random walk; fit this one directly"


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


def _candidates(model: ErrorModel, batch: Batch, st: Setting, names):
    """The deterministic candidates, the random walk's spec (or None), the extra columns
    their terms read (:func:`_extra_columns`), every column's problems per device, the
    column candidates no device can use (listed under skipped, never compiled) and the
    other noise processes offered (listed under skipped: the smoother scored here is the
    random walk's); the column terms that cannot be written (:func:`.unnamed_columns`)."""
    aux, problems = _extra_columns(batch, model, st)
    unnamed = unnamed_columns(problems, names)
    specs = candidate_specs(model, inputs_of(batch), names,
                            columns=tuple(k for k in problems if is_column_name(k)))
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
    (``meanwhile``: :func:`._chunks.prepare`'s)."""
    every, rw_spec, aux, problems, dead, unscored, unnamed = _candidates(model, batch, st, names)
    say(f"checking which of {len(every)} candidate(s) the data support")
    all_ranges, floors = prepare(batch, st, every, aux, meanwhile)
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
    _, idx = next(chunks(n_dev, size))
    dtype = jax.dtypes.canonicalize_dtype(np.float64)
    beta = np.zeros((n_dev, 3, model.n_params), dtype)
    theta = np.zeros((n_dev, model.n_nonlinear), dtype)
    windows = {i: block_windows(np.asarray(batch.mask[i]), st.n_blocks) for i in idx}
    dt0 = np.zeros(n_dev, dtype)
    args = chunk_args(model, plan.cands, batch, st, plan.floors, plan.aux, beta, theta, idx,
                       windows, dt0, put=spec)
    allan = allan_program(batch).compile_ahead(*allan_args(None, batch, put=spec)[0])
    return signature(*args), engine(n_dev * length).compile_ahead(*args), allan


def first_programs(batch: Batch):
    """A function that starts compiling (or reading from the caches), once, the program
    whose shape follows from the batch alone: the residuals' Allan deviation
    (:func:`_ahead_programs` asks for it again and gets this thread). The plan calls it
    while the ranges' program compiles (:func:`._chunks.prepare`): its trace fills that
    wait, and XLA compiles it while the plan traces the scoring program, whose
    compilation, the longest, still starts as early."""
    done = []

    def start() -> None:
        if done:
            return
        done.append(True)
        try:
            allan_program(batch).compile_ahead(*allan_args(None, batch, put=spec)[0])
        except Exception:  # noqa: BLE001 - the fit and the scoring compile what they need
            logging.getLogger("diffgyro").debug("diagnose: no programs before the plan",
                                                exc_info=True)

    return start


def planned_ahead(model, batch: Batch, names, fit_options: dict, say,
                   meanwhile=None) -> _Plan | None:
    """The plan formed before the base fit from the setting it will hold (:mod:`._ahead`),
    its programs started (:func:`_ahead_programs`); None where the setting is not foreseen
    or forming the plan fails (the fit then raises its own error, or the plan is formed
    after it). ``meanwhile``: called while the ranges' program compiles
    (:func:`first_programs`)."""
    try:
        st = predicted(model, batch, fit_options)
        if st is None:
            return None
        plan = _plan(model, batch, st, names, say, meanwhile)
        return plan._replace(ahead=_ahead_programs(model, batch, plan))
    except Exception:  # noqa: BLE001 - formed again after the fit, which raises what is wrong
        logging.getLogger("diffgyro").debug("diagnose: no plan before the fit", exc_info=True)
        return None


def plan_of_fit(plan: _Plan | None, model, batch: Batch, res, names, say) -> _Plan:
    """The plan formed before the fit where the fit's setting is the one foreseen, else the
    plan formed from the fit (the programs started before it kept: they serve where their
    arguments' shapes still hold, which :func:`._chunks.score` checks)."""
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
