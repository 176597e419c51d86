"""How a group of devices is judged from its window statistics (:mod:`diffgyro._window_stats`):
the shape of its window statistics and which judgement reads them. The judgement (the
baseline of the window means, the windows that leave it, the rule on runs, the angle
turned and gravity's tilt, and the numbers the host reads; :func:`diffgyro.motion.motion_check`
says what they mean) is numpy over the devices for a small batch
(:mod:`diffgyro._motion_host`, which says what each step does), and one compiled loop over
the devices (numba, :mod:`diffgyro._judgement_pass`) where the window statistics were read
by the compiled pass: the same rules, flags and windows, the numbers to float32's last bits.
"""

from __future__ import annotations

from typing import NamedTuple

from ._motion_constants import PAD_SAMPLES
from ._motion_host import judge as judge_on_host
from ._window_stats import compiled
from .data import device_bucket


class Layout(NamedTuple):
    """How a group of devices is checked: window and block sizes, the shape of its window
    sums (devices, windows; padded for a small batch) and whether the accelerometer is
    read."""

    w: int
    b: int
    shape: tuple[int, int]
    accel: bool

    @property
    def check(self):
        """The judgement (called with the gyro's and accelerometer's window statistics,
        ``w`` and ``b``): the compiled loop (:mod:`diffgyro._judgement_pass`) where the
        process reads window statistics by the compiled pass (a large batch, and once it
        has read one, every group: numba is loaded), else numpy on the host
        (:mod:`diffgyro._motion_host`: a small batch's command imports no numba)."""
        if compiled(0):  # (no samples: whether the process has loaded the compiled pass)
            from ._judgement_pass import judge  # numba: once the compiled pass is loaded

            return judge
        return judge_on_host


def layout(devices: int, samples: int, w: int, b: int, accel: bool) -> Layout:
    """How a group of devices is judged: its window sums' shape (padded for a small batch,
    which a few shapes serve: a device's numbers do not depend on the padding) and its
    judgement (:attr:`Layout.check`).

    **Arguments:**

    - ``devices``: the devices in the group.
    - ``samples``: the most samples one of them holds.
    - ``w``, ``b``: samples per window, windows per baseline block.
    - ``accel``: whether the accelerometer's windows are judged too.
    """
    k = -(-samples // w)
    if devices * samples > PAD_SAMPLES:
        return Layout(w, b, (devices, k), accel)
    # small batches share a shape: devices to a bucket, windows to a power of two of blocks
    blocks = 1 << (-(-k // b) - 1).bit_length()
    return Layout(w, b, (device_bucket(devices, minimum=1), blocks * b), accel)


__all__ = ["layout", "Layout"]
