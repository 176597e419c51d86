"""Recordings shared by the tests: one place builds each, so that a test file never imports
another test file for its data.

:func:`turning_chamber_run` is a device in a temperature chamber on a turning, tilting
fixture: every signal an effect term can read (temperature ramps both ways with soaks, an
external temperature, rotation on every axis, a changing specific force, an extra column).
"""

from __future__ import annotations

import numpy as np

from diffgyro.data import Recording


def turning_chamber_run(duration: int, knots: list[float], seed: int,
                        temps: tuple[float, ...] = (20, 20, 50, 50, 10, 10), gain: float = 1.5,
                        noise: float = 0.01, ext_offset: float = 4.0,
                        reference: bool = False) -> Recording:
    """``duration`` s at 1 Hz: the chamber at ``temps`` at the times ``knots`` (soak, ramp
    up, soak, ramp down, soak), turning on all axes (gyro ``gain`` × the rate plus white
    noise of σ ``noise``), tilting, an external temperature ``ext_offset`` °C below, and an
    extra column ``vdd``; ``reference`` adds the true rate as the reference rate."""
    rng = np.random.default_rng(seed)
    t = np.arange(float(duration))
    temp = np.interp(t, knots, list(temps))
    temp = temp + 0.02 * rng.standard_normal(t.size)
    w = np.stack([np.sin(2 * np.pi * t / p + ph) for p, ph in ((97, 0), (61, 1), (43, 2))], 1)
    accel = 9.81 * np.stack([np.sin(t / 200), np.cos(t / 200) * np.sin(t / 310),
                             np.cos(t / 200) * np.cos(t / 310)], 1)
    return Recording(t=t, gyro=gain * w + noise * rng.standard_normal(w.shape), temp=temp,
                     temp_ext=temp - ext_offset + np.sin(t / 150), accel=accel,
                     rate=w if reference else None,
                     aux={"vdd": 3.3 + 0.2 * np.sin(t / 400)}, device="imu0")
