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

Terms that read a reference rate (scale, misalignment) or the accelerometer itself
(``g_sens``) have no meaning on this channel and are refused. The motion check stays the
IMU's (:func:`diffgyro.fit.fit` judges rest on the gyro and accelerometer as loaded).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from jaxtyping import Float

from ._vocabulary import CHANNELS, UNITS
from .data import Batch, Recording, as_batch
from .errors import DataError, SpecError

__all__ = ["CHANNELS", "UNITS", "check_channel", "split_spec", "resolve", "check_model",
           "gravity_reference", "as_channel"]

#: Signals a model may not read on the accelerometer channel, and why.
_NOT_ON_ACCEL = {
    "rate": "a reference rate is the gyro's input; the accelerometer's scale needs gravity "
            "in several orientations (diffgyro recipe six-position)",
    "accel": "the accelerometer is the measurement on this channel, not an input",
}


def check_channel(channel: str | None) -> str:
    """``channel`` checked (None: the gyro)."""
    channel = "gyro" if channel is None else str(channel).strip().lower()
    if channel not in CHANNELS:
        raise SpecError(f"unknown channel {channel!r}", hint=f"one of {', '.join(CHANNELS)}")
    return channel


def split_spec(spec: str) -> tuple[str | None, str]:
    """A spec's channel prefix (``"accel: bias_poly(3)"``) and the spec without it."""
    head, sep, rest = str(spec).partition(":")
    if sep and head.strip().lower() in CHANNELS:
        return head.strip().lower(), rest.strip()
    return None, str(spec)


def resolve(spec: str, channel: str | None = None) -> tuple[str, str]:
    """The channel (named by the spec, by ``channel``, or the gyro) and the bare spec; a
    SpecError where the two name different channels."""
    named, bare = split_spec(spec)
    if named is not None and channel is not None and check_channel(channel) != named:
        raise SpecError(f"model {spec!r} names channel {named}, but channel {channel} was asked "
                        "for", hint="drop the prefix or the --channel option")
    return check_channel(named if named is not None else channel), bare


def check_model(model, channel: str) -> None:
    """A SpecError naming the first term the channel cannot hold (``model``: an ErrorModel)."""
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


def gravity_reference(batch: Batch) -> Float[np.ndarray, "d 3"]:
    """Each device's median specific force over its valid samples (m/s²): the reading at
    rest that the accelerometer channel's offsets are relative to."""
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
               reference: Float[np.ndarray, "d 3"] | None = None) -> tuple[Batch, np.ndarray | None]:
    """The batch the engine fits for ``channel`` and the gravity reference it subtracted
    (None for the gyro, whose batch is returned as it is).

    Accelerometer: the measured triad is ``accel − reference`` (``reference`` default:
    :func:`gravity_reference`); the batch keeps time, temperatures, extra columns and
    mask, and drops the accelerometer and reference-rate inputs."""
    batch = as_batch(data)
    if check_channel(channel) == "gyro":
        return batch, None
    ref = gravity_reference(batch) if reference is None else np.asarray(reference, float)
    if ref.shape != (batch.n_devices, 3):
        raise DataError(f"gravity reference has shape {ref.shape}, expected "
                        f"({batch.n_devices}, 3)")
    meas = np.asarray(batch.accel, float) - ref[:, None, :]
    meas = np.where(np.asarray(batch.mask, bool)[..., None], meas, 0.0)
    out = dataclasses.replace(batch, gyro=meas, accel=None, rate=None, quat=None, mag=None)
    return out, ref
