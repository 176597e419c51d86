"""Which sensor a calibration serves: the gyro (default) or the accelerometer.

The engine explains one measured triad per device, ``Batch.gyro``. The accelerometer
channel puts the specific force there, less its **gravity reference**: at rest, in one
orientation, the accelerometer reads ``g_s + b(T)`` (gravity in the sensor frame plus
its offset), and only the change of that reading with temperature,
``b(T) − b(T_ref)``, is determined by the soak. The absolute offset ``b(T_ref)`` and
``g_s`` cannot be told apart there: that takes several orientations (the six-position
recipe, ``diffgyro recipe six-position``). So the channel subtracts each device's
median reading (the reference, kept in the calibration file) and the model fits what is
left: a bias polynomial's constant is the offset at the centre of the range relative to
the reference, and every other coefficient is the thermal change itself, as PX4's
``TC_A*`` and ArduPilot's ``INS_TCALn_ACC*`` parameters hold it.

**Several orientations.** A model with terms that read a reference input (``scale_poly``,
``misalignment``, ``scale_asym``, a ``term(...)`` of ``rx``, ``ry``, ``rz``) reads gravity
there: the recording holds the sensor still in several orientations (the faces of the
six-position method, ``diffgyro recipe six-position``), each stretch of rest is given the
face its gravity lies along, and the input of every sample at rest is gravity along that
face, ``±g·e_k`` (:func:`faces`). Nothing is subtracted then: the model
``bias_poly(k) + scale_poly(0) + misalignment`` fits ``a = (I + S + M)·g_face + b(T)``, so
its ``bias_poly`` holds the **absolute** offset and its thermal change, and
``scale_poly``/``misalignment`` the accelerometer's matrix (the six-position recipe's
``accel_matrix`` is ``(I + S + M)⁻¹``, its ``accel_bias`` the offset ``b``). Samples in
motion are left out, as the IMU's motion check finds them.

A term reading the accelerometer itself (``g_sens``) has no meaning on this channel and is
refused. The motion check stays the IMU's (:func:`diffgyro.fit.fit` judges rest on the
gyro and accelerometer as loaded).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float

from ._vocabulary import CHANNELS, UNITS
from .data import Batch, Recording, as_batch
from .errors import DataError, SpecError

__all__ = ["CHANNELS", "UNITS", "GRAVITY", "FACE_TOLERANCE", "check_channel", "split_spec",
           "resolve", "check_model", "reads_gravity", "gravity_reference", "faces",
           "as_channel", "fitted_batch"]

#: Standard gravity (m/s²): the magnitude of the reference in several orientations
#: unless the local value is given (it differs by up to 0.3 %, a scale error that size).
GRAVITY = 9.80665
#: A stretch of rest is a face when its gravity lies within this many degrees of an axis.
FACE_TOLERANCE = 15.0
#: Signals a model may not read on the accelerometer channel, and why.
_NOT_ON_ACCEL = {
    "accel": "the accelerometer is the measurement on this channel, not an input",
}
_AXES = "xyz"


def check_channel(channel: str | None) -> str:
    """``channel`` checked (None: the gyro).

    **Arguments:**

    - ``channel``: a channel's name, any case (None: the gyro).
    """
    channel = "gyro" if channel is None else str(channel).strip().lower()
    if channel not in CHANNELS:
        raise SpecError(f"unknown channel {channel!r}", hint=f"one of {', '.join(CHANNELS)}")
    return channel


def split_spec(spec: str) -> tuple[str | None, str]:
    """A spec's channel prefix (``"accel: bias_poly(3)"``) and the spec without it.

    **Arguments:**

    - ``spec``: a model spec, perhaps prefixed by its channel (``"accel: bias_poly(3)"``).
    """
    head, sep, rest = str(spec).partition(":")
    if sep and head.strip().lower() in CHANNELS:
        return head.strip().lower(), rest.strip()
    return None, str(spec)


def resolve(spec: str, channel: str | None = None) -> tuple[str, str]:
    """The channel (named by the spec, by ``channel``, or the gyro) and the bare spec; a
    SpecError where the two name different channels.

    **Arguments:**

    - ``spec``: a model spec, perhaps prefixed by its channel.
    - ``channel``: the channel asked for apart from the spec (None: the spec's, or the
      gyro).
    """
    named, bare = split_spec(spec)
    if named is not None and channel is not None and check_channel(channel) != named:
        raise SpecError(f"model {spec!r} names channel {named}, but channel {channel} was asked "
                        "for", hint="drop the prefix or the --channel option")
    return check_channel(named if named is not None else channel), bare


def check_model(model, channel: str) -> None:
    """A SpecError naming the first term the channel cannot hold (``model``: an ErrorModel).

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel` to be fitted.
    - ``channel``: the channel it is fitted on.
    """
    if check_channel(channel) == "gyro":
        return
    if getattr(model, "noise", None) is not None:
        raise SpecError(f"{model.noise.spec} cannot be fitted on the accelerometer channel yet",
                        hint="diagnose --channel accel names it where the residual wanders")
    for term in model.parts:
        for sig, why in _NOT_ON_ACCEL.items():
            if sig in term.requires():
                raise SpecError(f"term {term.spec} cannot be fitted on the accelerometer "
                                f"channel: {why}")


def reads_gravity(model) -> bool:
    """Whether ``model`` (an ErrorModel) reads a reference input: on the accelerometer
    channel, gravity in several orientations (absolute offset and scale).

    **Arguments:**

    - ``model``: an :class:`~diffgyro.model.ErrorModel`.
    """
    return any("rate" in term.requires() for term in model.parts)


def faces(accel: Float[np.ndarray, "n 3"], static: np.ndarray, gravity: float = GRAVITY,
          device: str | None = None, file: str | None = None,
          ) -> tuple[Float[np.ndarray, "n 3"], list[str]]:
    """Gravity along the face each stretch of rest lies on (``±gravity`` on one axis; 0
    where not at rest) and the faces seen (``"+z"``, ``"-x"``, ... in order of first hold).

    A stretch is the run of ``static`` samples between two moves; its face is the axis
    nearest its median reading. A DataError names the device and rows of a stretch whose
    gravity lies more than :data:`FACE_TOLERANCE` degrees from every axis (the method
    needs the axes up and down), or of a sample that leaves its stretch's face (a move
    the motion check did not see).

    **Arguments:**

    - ``accel``: one device's specific force (n, 3), m/s².
    - ``static``: its samples at rest (n,), booleans.
    - ``gravity``: the magnitude of gravity, m/s².
    - ``device``: the device's name, for the error.
    - ``file``: the file it came from, for the error.
    """
    acc = np.asarray(accel, float)
    still = np.asarray(static, bool)
    out = np.zeros_like(acc)
    seen: list[str] = []
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(np.int8), [0]])))
    cos_tol = np.cos(np.radians(FACE_TOLERANCE))
    for start, stop in zip(edges[::2], edges[1::2]):
        med = np.median(acc[start:stop], axis=0)
        norm = float(np.linalg.norm(med))
        k = int(np.argmax(np.abs(med)))
        if not norm or abs(med[k]) / norm < cos_tol:
            angle = 90.0 if not norm else float(np.degrees(np.arccos(abs(med[k]) / norm)))
            raise DataError(f"the rest at rows {start}–{stop - 1} holds gravity {angle:.0f}° "
                            f"from every axis: scale and absolute offset need the faces of "
                            f"the six-position method (each axis up, and down)",
                            device=device, file=file, row=int(start),
                            hint=f"hold each face within {FACE_TOLERANCE:.0f}° of level, "
                                 "or fit bias_poly alone (one orientation)")
        sign = 1.0 if med[k] > 0 else -1.0
        along = sign * acc[start:stop, k] / np.maximum(np.linalg.norm(acc[start:stop], axis=1),
                                                        1e-12)
        off = np.flatnonzero(along < cos_tol)
        if off.size:
            raise DataError(f"row {start + int(off[0])} leaves face {'+-'[sign < 0]}"
                            f"{_AXES[k]} within a stretch of rest (a move the motion check "
                            f"did not see)", device=device, file=file,
                            row=int(start + off[0]), hint="hold each face still; leave "
                            "the moves between faces a few seconds")
        out[start:stop, k] = sign * gravity
        face = f"{'+-'[sign < 0]}{_AXES[k]}"
        if face not in seen:
            seen.append(face)
    return out, seen


def gravity_reference(batch: Batch) -> Float[np.ndarray, "d 3"]:
    """Each device's median specific force over its valid samples (m/s²): the reading at
    rest that the accelerometer channel's offsets are relative to.

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch`, with accelerometer readings.
    """
    if batch.accel is None:
        raise DataError("the accelerometer channel needs ax, ay, az, which the data lack",
                        device=batch.devices[0] if batch.devices else None,
                        file=batch.sources[0] if batch.sources else None,
                        hint="load a file or log with accelerometer readings")
    acc = np.asarray(batch.accel, float)
    mask = np.asarray(batch.mask, bool)
    out = np.empty((batch.n_devices, 3))
    for i in range(batch.n_devices):
        out[i] = np.median(acc[i][mask[i]], axis=0)
    return out


def as_channel(data: Batch | Recording | list[Recording], channel: str = "gyro",
               reference: Float[np.ndarray, "d 3"] | None = None,
               static: np.ndarray | None = None,
               gravity: float = GRAVITY) -> tuple[Batch, np.ndarray | None]:
    """The batch the engine fits for ``channel`` and the gravity reference it subtracted
    (None for the gyro, whose batch is returned as it is).

    Accelerometer: the measured triad is ``accel − reference`` (``reference`` default:
    :func:`gravity_reference`); the batch keeps time, temperatures, extra columns and
    mask, and drops the accelerometer and reference-rate inputs.

    With ``static`` (devices × samples, the IMU's samples at rest), several orientations:
    the measured triad is the accelerometer as read, its input (the batch's reference
    slot) gravity along each stretch's face (:func:`faces`, ``gravity`` in m/s²), the
    samples in motion are masked out, and the reference subtracted is zero. A DataError
    names a device that holds fewer than two faces.

    **Arguments:**

    - ``data``: a :class:`~diffgyro.data.Batch`, a recording, or a list of recordings.
    - ``channel``: ``"gyro"`` or ``"accel"``.
    - ``reference``: each device's gravity reference (devices, 3), m/s² (default:
      :func:`gravity_reference`).
    - ``static``: the samples at rest (devices, samples), for several orientations (default:
      one orientation).
    - ``gravity``: the magnitude of gravity in several orientations, m/s².
    """
    batch = as_batch(data)
    if check_channel(channel) == "gyro":
        return batch, None
    if static is not None:
        return _oriented(batch, np.asarray(static, bool), float(gravity))
    ref = gravity_reference(batch) if reference is None else np.asarray(reference, float)
    if ref.shape != (batch.n_devices, 3):
        raise DataError(f"gravity reference has shape {ref.shape}, expected "
                        f"({batch.n_devices}, 3)")
    meas = np.asarray(batch.accel, float) - ref[:, None, :]
    meas = np.where(np.asarray(batch.mask, bool)[..., None], meas, 0.0)
    out = dataclasses.replace(batch, gyro=meas, accel=None, rate=None, quat=None, mag=None)
    return out, ref


def fitted_batch(result, batch: Batch) -> Batch:
    """The batch a fit ``result`` was fitted on: ``batch`` as loaded for the gyro; for the
    accelerometer its channel batch (:func:`as_channel`: less the result's gravity
    reference, or the rests its motion check kept with the result's gravity their input);
    a batch already of the channel (no accelerometer left in it) as it is.

    **Arguments:**

    - ``result``: the fit's result (its channel, reference, gravity and motion check).
    - ``batch``: the :class:`~diffgyro.data.Batch` as loaded, or already of the channel.
    """
    channel = getattr(result, "channel", "gyro")
    if channel == "gyro" or batch.accel is None:
        return batch
    static = result.motion.static if reads_gravity(result.model) else None
    gravity = getattr(result, "gravity", None)
    out, _ = as_channel(batch, channel, getattr(result, "reference", None), static=static,
                        gravity=GRAVITY if gravity is None else gravity)
    return out


def _oriented(batch: Batch, static: np.ndarray, gravity: float) -> tuple[Batch, np.ndarray]:
    """The accelerometer batch of several orientations (:func:`as_channel`)."""
    gravity_reference(batch)  # the DataError where the data lack the accelerometer
    acc = np.asarray(batch.accel, float)
    mask = np.asarray(batch.mask, bool) & static
    nominal = np.zeros_like(acc)
    for i, dev in enumerate(batch.devices):
        src = batch.sources[i] if i < len(batch.sources) else None
        nominal[i], seen = faces(acc[i], mask[i], gravity, device=dev, file=src)
        if len(seen) < 2:
            raise DataError(f"the accelerometer's scale and absolute offset need several "
                            f"orientations; the rest holds {'one face' if seen else 'no face'}"
                            f" ({', '.join(seen) or 'none'})",
                            device=dev, file=src, hint="hold the six faces (each axis up, and "
                            "down), or fit bias_poly alone: its thermal change")
    meas = np.where(mask[..., None], acc, 0.0)
    out = dataclasses.replace(batch, gyro=meas, rate=nominal, mask=mask, accel=None, quat=None,
                              mag=None)
    return out, np.zeros((batch.n_devices, 3))
