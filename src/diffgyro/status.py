"""A device's fit status in plain words: why a device is not ``ok``.

Every fitting path (closed form, the sums path, the state-space path) sets a
device's status with :func:`fit_status`, most basic problem first,
and every record says why a device is not ``ok`` with :func:`explain` (its
``status_detail``): which term the data cannot support and what it needs, which
terms the data do not tell apart (the rank check: never a silent truncation),
or what went wrong in the solve. A number a record cannot give (``null`` in
JSON) is missing for the reason its ``status_detail`` states.
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from ._motion_result import describe, reason
from ._vocabulary import (
    RESIDUAL_REFUSE,
    RESIDUAL_WARN,
    STATUS_NAMES,
    min_samples,
    residual_note,
    residual_verdict,
)

__all__ = ["explain", "fit_status", "STATUS_NAMES", "OK", "NOT_CONVERGED", "RANK_DEFICIENT",
           "INSUFFICIENT_RANGE", "INSUFFICIENT_DATA", "FAILED", "IN_MOTION", "REST_UNVERIFIED", "min_samples",
           "RESIDUAL_WARN", "RESIDUAL_REFUSE", "residual_verdict", "residual_note",
           "collinear_terms"]

(OK, NOT_CONVERGED, RANK_DEFICIENT, INSUFFICIENT_RANGE, INSUFFICIENT_DATA, FAILED, IN_MOTION,
 REST_UNVERIFIED) = range(8)


def fit_status(n_valid, min_samples: int, converged, finite, range_flags=None, rank_ok=None):
    """Status code of a fit, the most basic problem first: too few samples, a term
    whose signal does not vary (``range_flags``), collinear columns (``rank_ok``
    false on an axis), no convergence, non-finite results.

    **Arguments:**

    - ``n_valid``: the device's valid samples.
    - ``min_samples``: the fewest the fit needs (:func:`min_samples`).
    - ``converged``: whether the solver converged.
    - ``finite``: whether the results are finite.
    - ``range_flags``: per term, positive where the data cannot support it.
    - ``rank_ok``: per axis, whether the design has full rank.
    """
    status = jnp.where(finite, OK, FAILED)
    status = jnp.where(~converged, NOT_CONVERGED, status)
    if rank_ok is not None:
        status = jnp.where(~jnp.all(rank_ok), RANK_DEFICIENT, status)
    if range_flags is not None:
        status = jnp.where(jnp.any(range_flags), INSUFFICIENT_RANGE, status)
    return jnp.where(n_valid < min_samples, INSUFFICIENT_DATA, status)


def collinear_terms(model, direction, rank_ok):
    """Per term: does it weigh in a direction the data do not excite?
    ``direction`` (3, p) is the smallest eigenvector of each axis' scaled Gram matrix.

    **Arguments:**

    - ``model``: the fitted :class:`~diffgyro.model.ErrorModel`.
    - ``direction``: the smallest eigenvector of each axis' scaled Gram matrix (3, p).
    - ``rank_ok``: per axis, whether the design has full rank.
    """
    terms = model.terms
    if not model.n_params:
        return jnp.zeros((len(terms),), bool)
    owner = jnp.asarray([terms.index(t) for t in model.column_terms()], jnp.int32)
    weak = (jnp.abs(direction) > 0.3) & (~rank_ok[:, None])  # (3, p)
    return jnp.zeros((len(terms),), bool).at[owner].max(jnp.any(weak, axis=0))


def _temperature_fact(temp_range) -> tuple[str, float] | None:
    if temp_range is None:
        return None
    lo, hi = (float(v) for v in np.asarray(temp_range, float))
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return None
    if hi - lo == 0.0:
        return f"temperature constant at {lo:.1f} °C", 0.0
    return f"temperature spans only {hi - lo:.3g} °C ({lo:.1f} to {hi:.1f} °C)", hi - lo


def _range_reason(term, temp_range, channel: str = "gyro") -> str:
    need = term.range_need()
    if channel != "gyro" and "rate" in term.requires():  # its input is gravity on a face
        need = "gravity along every axis: the faces held with each axis up, and down"
    fact = _temperature_fact(temp_range)
    if fact is not None and fact[1] < term.min_temp_span:
        return f"{fact[0]}: {term.spec} needs {need}"
    return f"{term.spec} needs {need}"


def explain(name: str, model, *, range_flags=None, collinear=None, temp_range=None,
            n_samples=None, steps=None, motion=None, channel: str = "gyro") -> str:
    """``status_detail``: the status name, and for a device not ``ok`` why, in plain words
    (``channel``: the sensor fitted, whose remedies differ).

    **Arguments:**

    - ``name``: the status name (``ok``, ``rank_deficient``, …).
    - ``model``: the fitted :class:`~diffgyro.model.ErrorModel`.
    - ``range_flags``: per term, whether the data could not support it.
    - ``collinear``: per term, whether it weighs in a direction the data do not excite.
    - ``temp_range``: the device's temperature span, °C.
    - ``n_samples``: its valid samples.
    - ``steps``: the solver's steps.
    - ``motion``: the device's motion record (a dict, as the result keeps it), for
      ``in_motion`` and ``rest_unverified``.
    - ``channel``: the sensor fitted, ``"gyro"`` or ``"accel"``, whose remedies differ.
    """
    terms = model.terms
    if name == "ok":
        return name
    if name == "insufficient_data":
        need = min_samples(model.n_params + model.n_nonlinear)
        have = "" if n_samples is None else f"{int(n_samples)} valid samples; "
        return f"{name}: {have}model {model.spec} needs at least {need}"
    if name == "insufficient_range":
        flags = np.asarray(range_flags if range_flags is not None else [], bool)
        bad = [t for t, f in zip(terms, flags) if f]
        reasons = "; ".join(_range_reason(t, temp_range, channel) for t in bad)
        return f"{name}: {reasons or 'the data do not vary what the model needs'}"
    if name == "rank_deficient":
        flags = np.asarray(collinear if collinear is not None else [], bool)
        bad = [t.spec for t, f in zip(terms, flags) if f]
        which = ", ".join(bad) if bad else "the model's terms"
        return (f"{name}: collinear {which}: the data do not excite "
                f"{'these terms' if len(bad) > 1 else 'the design'} independently "
                f"(near-singular design, not truncated); record data that vary them apart, "
                f"or fit a model without one of them")
    if name == "not_converged":
        after = "" if steps is None else f" after {int(steps)} steps"
        return (f"{name}: the time-constant solve stopped{after} without converging "
                f"(or short of the best start point); the coefficients are not trusted")
    if name == "in_motion":
        if channel != "gyro":  # gravity is the reference: one orientation, at rest
            return (f"{name}: {describe(motion or {})}; record the soak at rest in one "
                    f"orientation (the accelerometer's gravity reference holds only there), "
                    f"or hold it on several faces and fit scale_poly(0) with the bias "
                    f"(gravity on each face the input)")
        return (f"{name}: {describe(motion or {})}; record at rest, give a rate reference "
                f"(rx, ry, rz), or fit the static intervals only with --static-only")
    if name == "rest_unverified":
        rec = motion or {}
        why = rec.get("reason") or reason(rec)
        return (f"{name}: {why}; a fit without a rate reference needs the device at rest, and "
                f"nothing shows that it was")
    if name == "failed":
        return (f"{name}: the solve gave non-finite numbers (coefficients or residual); "
                f"no calibration for this device: check its data for extreme values")
    return name
