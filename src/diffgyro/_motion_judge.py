"""The motion judgement of a fit: whether each device's recording was at rest, and the
status of a device that moved or whose rest cannot be shown.

Every path that fits a batch ends in :func:`judge_motion` (the front door
:func:`diffgyro.fit.fit`, the streamed chunks); the check itself is
:func:`diffgyro.motion.motion_check`. A model without a rate reference explains a rest
recording only: a device that moved gets ``in_motion``, one whose recording cannot show
its rest ``rest_unverified``. A deterministic model's residual tells a fast thermal
transient it follows from a turn it cannot (:func:`_unexplained`); a result whose
smoothed bias follows turns (a random walk's) says so by
:attr:`~diffgyro._fit_result.AbstractFitResult.residual_tells_motion`.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float

from ._fit_result import AbstractFitResult
from .data import Batch
from .motion import MAX_BIAS, PAD_SAMPLES, Motion, motion_check, rest_kept
from .status import IN_MOTION, OK, REST_UNVERIFIED

__all__ = ["judge_motion"]


def judge_motion(result: AbstractFitResult, batch: Batch, motion: Motion | None = None,
                 recorded: Float[Array, " d"] | None = None,
                 static_only: bool = False) -> AbstractFitResult:
    """``result`` (any fit: :class:`~diffgyro._fit_result.AbstractFitResult`) with the motion check
    of ``batch`` (computed here unless given) and, where the model has no rate reference,
    status ``in_motion`` for a device that moved and ``rest_unverified`` for one whose
    recording cannot show that it was at rest (:class:`diffgyro.motion.Motion`);
    ``recorded``: samples per device before ``static_only`` masked the moving ones (whose
    fit is ``rest_unverified`` where too little rest is left). Every path that fits a batch
    ends here."""
    if motion is None:
        motion = motion_check(batch)
    if recorded is None:
        recorded = jax.device_put(np.asarray(batch.mask).sum(axis=1).astype(float))
    status = result.status
    if batch.rate is None:  # a fit with a rate reference subtracts it
        if static_only:
            motion = rest_kept(motion)
            moved = np.zeros(len(motion.verdict), bool)
        else:
            moved = motion.moved_all()
        # (a random walk's smoothed bias follows a turn: only a deterministic model's
        # residual tells a thermal transient from motion)
        # (the accelerometer channel keeps the IMU's verdict: its residual is in m/s²)
        if (not static_only and result.residual_tells_motion
                and getattr(result, "channel", "gyro") == "gyro"
                and np.any(moved & (np.asarray(status) == OK))):
            motion = _unexplained(result, batch, motion, moved)
            moved = motion.moved_all()
        status = np.asarray(status)  # on the host: no program per batch size
        unverified = motion.unverified_all()
        status = np.where(moved & (status == OK), IN_MOTION, status)
        status = np.where(unverified & (status == OK), REST_UNVERIFIED, status)
        status = jax.device_put(status.astype(np.asarray(result.status).dtype))
    return _replace(result, status=status, motion=motion, n_recorded=recorded,
                    static_only=static_only)


def _unexplained(result: AbstractFitResult, batch: Batch, motion: Motion, moved) -> Motion:
    """The motion check of what the fitted model leaves unexplained (its residual), for the
    devices whose recording moved; the others keep ``motion``. A fast thermal transient the
    model follows is not motion; a turn no model without a rate reference can follow
    stays in the residual; a spin (a rate held beyond :data:`~diffgyro.motion.MAX_BIAS`),
    which a bias absorbs, keeps the recording's verdict."""
    d, n = np.shape(batch.mask)
    # a large batch: only the devices that moved (a residual and a check of the whole batch
    # cost more than the fit itself); a small one whole (its check program is compiled
    # already, where a sub-batch's would compile anew)
    idx = np.flatnonzero(moved) if d * n > PAD_SAMPLES else np.arange(d)

    def take(x):
        return x[idx] if isinstance(x, (np.ndarray, jax.Array)) and x.ndim and x.shape[0] == d else x

    sub, part = (result, batch) if len(idx) == d else (jax.tree.map(take, result), batch.select(idx))
    resid = np.asarray(sub.residuals(part))  # (only called where batch.rate is None)
    again = motion_check(eqx.tree_at(lambda b: b.gyro, part, resid))
    if len(idx) == d:
        idx = np.flatnonzero(moved)
        again = again.select(idx)
    # a rate held beyond any bias is a spin, which a bias term absorbs: the residual of
    # such a fit shows nothing, and the recording's verdict stands
    with np.errstate(invalid="ignore"):
        keep = ~(np.asarray(motion.rest_rate, float)[idx] > MAX_BIAS)
    return motion.put(idx[keep], again.select(np.flatnonzero(keep)))


def _replace(result, **changes):
    """``result`` with some fields changed (static ones included)."""
    return dataclasses.replace(result, **changes)
