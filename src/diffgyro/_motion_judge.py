"""The motion judgement of a fit: whether each device's recording was at rest, and the
status of a device that moved or whose rest cannot be shown.

Every path that fits a batch ends in :func:`judge_motion` (the front door
:func:`diffgyro.fit.fit`, the streamed chunks); the check itself is
:func:`diffgyro.motion.motion_check`. A model without a rate reference explains a rest
recording only: a device that moved gets ``in_motion``, one whose recording cannot show
its rest ``rest_unverified``. A deterministic model's residual tells a fast thermal
transient it follows from a turn it cannot (:func:`_explanation`); a result whose
smoothed bias follows turns (a random walk's) says so by
:attr:`~diffgyro._fit_result.AbstractFitResult.residual_tells_motion`.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np
from jaxtyping import Array, Float

from ._fit_result import AbstractFitResult
from ._window_explain import Explanation
from .data import Batch, valid_samples
from .motion import Motion, motion_check, rest_kept
from .status import IN_MOTION, OK, REST_UNVERIFIED

__all__ = ["judge_motion"]


def judge_motion(result: AbstractFitResult, batch: Batch, motion: Motion | None = None,
                 recorded: Float[Array, " d"] | None = None,
                 static_only: bool = False, ahead=None) -> AbstractFitResult:
    """``result`` (any fit: :class:`~diffgyro._fit_result.AbstractFitResult`) with the motion check
    of ``batch`` and, where the model has no rate reference, status ``in_motion`` for a
    device that moved and ``rest_unverified`` for one whose recording cannot show that it
    was at rest (:class:`diffgyro.motion.Motion`). ``motion``: the check, where already
    made; else it is made here, judging what the fitted model leaves where its residual
    tells motion (:func:`_explanation`). ``recorded``: samples per device before
    ``static_only`` masked the moving ones (whose fit is ``rest_unverified`` where too
    little rest is left). ``ahead``: the check's first look read beside the fit
    (:func:`diffgyro.motion.check_ahead`). Every path that fits a batch ends here."""
    if motion is None:
        motion = motion_check(batch, explain=None if static_only else _explanation(result, batch),
                              ahead=ahead)
    if recorded is None:
        recorded = jax.device_put(valid_samples(batch.mask).astype(float))
    status = result.status
    if batch.rate is None:  # a fit with a rate reference subtracts it
        if static_only:
            motion = rest_kept(motion)
            moved = np.zeros(len(motion.verdict), bool)
        else:
            moved = motion.moved_all()
        status = np.asarray(status)  # on the host: no program per batch size
        unverified = motion.unverified_all()
        status = np.where(moved & (status == OK), IN_MOTION, status)
        status = np.where(unverified & (status == OK), REST_UNVERIFIED, status)
        status = jax.device_put(status.astype(np.asarray(result.status).dtype))
    return _replace(result, status=status, motion=motion, n_recorded=recorded,
                    static_only=static_only)


def _explanation(result: AbstractFitResult, batch: Batch) -> Explanation | None:
    """The fitted model as the motion check reads it (its residual at given samples), where
    its residual tells motion: a deterministic model of the gyro without a rate reference
    follows a thermal transient but no turn. A random walk's smoothed bias follows a turn,
    and the accelerometer's residual is in m/s²: those keep the recording's verdict."""
    if (batch.rate is not None or not result.residual_tells_motion
            or getattr(result, "channel", "gyro") != "gyro"):
        return None
    d = len(result.devices)

    def residual(rows, half: Batch):
        sub = result
        if not np.array_equal(rows, np.arange(d)):  # (on the host: no program per subset)
            sub = jax.tree.map(lambda x: np.asarray(x)[rows] if _per_device(x, d) else x, result)
        return np.asarray(sub.residuals(half))

    return Explanation(residual=residual, reads=frozenset(result.model.requires()),
                       trusted=np.asarray(result.status) == OK)


def _per_device(x, d: int) -> bool:
    return isinstance(x, (np.ndarray, jax.Array)) and x.ndim > 0 and x.shape[0] == d


def _replace(result, **changes):
    """``result`` with some fields changed (static ones included)."""
    return dataclasses.replace(result, **changes)
