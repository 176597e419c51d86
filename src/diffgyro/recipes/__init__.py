"""The published calibration methods as faithful recipes, plus the
classic six-position and multi-position calibrations.

Each recipe reproduces its procedure step by step and returns a
:class:`RecipeResult` (plain numpy fields, ``to_dict()`` for JSON). Where a
step is a regression it is written with the toolkit's effect terms, so the
same data can then be handed to :func:`diffgyro.fit.fit` with a richer
model. ``RECIPES`` maps the command-line name to a :class:`Recipe`, whose
``run(recording, **options)`` takes a :class:`~diffgyro.data.Recording` in SI
units.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from dataclasses import dataclass

from ..errors import DataError
from ._attitude_reference import AttitudeReferenceResult, attitude_reference
from ._binned_thermal import BinnedThermalResult, binned_thermal
from ._common import RecipeResult, jsonable, require, single_axis, toolkit_compensate
from ._cube_bias import CubeBiasResult, cube_bias, read_sets
from ._fog_one_run import FogOneRunResult, fog_one_run
from ._multi_position import MultiPositionResult, multi_position
from ._six_position import SixPositionResult, read_sections, six_position
from ._static_intervals import static_intervals
from ._static_kalman import StaticKalmanResult, heading_errors, static_kalman


@dataclass(frozen=True)
class Recipe:
    """A named recipe: what it reproduces, what it needs, and how to run it."""

    name: str
    source: str
    summary: str
    needs: tuple[str, ...]
    run: Callable[..., RecipeResult]

    def options(self) -> tuple[str, ...]:
        """Keyword options ``run`` accepts (besides the recording)."""
        sig = inspect.signature(self.run)
        return tuple(p for p in list(sig.parameters)[1:])


# Adapters: a Recording in SI units (rad/s, m/s², °C, s) -> the recipe's function.


def _binned_thermal(rec, *, bin_width=0.1, edge="low", per_bin=None, min_count=10, r_min=0.999):
    require(rec, "temp", recipe="binned-thermal")
    return binned_thermal(rec.gyro, rec.temp, bin_width=bin_width, edge=edge, per_bin=per_bin,
                          min_count=min_count, r_min=r_min)


def _static_kalman(rec, *, init=1000, window=100, margin=1.5, q=1e-4, q_unit="deg/s"):
    require(rec, "accel", recipe="static-kalman")
    return static_kalman(rec.gyro, rec.accel, rec.t, quat=rec.quat, init=init, window=window,
                         margin=margin, q=q, q_unit=q_unit)


def _fog_one_run(rec, *, axis="z", k0=1.0, n=6, m=3, signs_from="rate"):
    require(rec, "temp", "temp_ext", "rate", recipe="fog-one-run")
    ax = "xyz".index(axis) if isinstance(axis, str) else int(axis)
    return fog_one_run(rec.gyro, rec.temp, rec.temp_ext, rec.rate, axis=ax, k0=k0, n=n, m=m,
                       signs_from=signs_from)


def _attitude_reference(rec, *, gravity=9.81, accel_band=0.02, ratio=0.02, reference="am",
                        interval=1, forget=1.0):
    require(rec, "accel", "mag", recipe="attitude-reference")
    return attitude_reference(rec.gyro, rec.accel, rec.mag, rec.t, gravity=gravity,
                              accel_band=accel_band, ratio=ratio, reference=reference,
                              interval=interval, forget=forget)


def _cube_bias(rec, sections, *, all_faces=False):
    require(rec, "accel", recipe="cube-bias")
    return cube_bias(rec.gyro, rec.accel, read_sets(sections, n_samples=rec.n),
                     published=not all_faces)


def _six_position(rec, sections, *, sampling_rate=None, rotation_angle=-360.0, gravity=9.81):
    """``rotation_angle`` in degrees; the recording is in SI units (rad/s, m/s²)."""

    require(rec, "accel", recipe="six-position")
    return six_position(rec.gyro, rec.accel, sections, t=rec.t, sampling_rate=sampling_rate,
                        rotation_angle=math.radians(rotation_angle), gravity=gravity)


def _multi_position(rec, *, gravity=9.81, init_seconds=50.0, window=101, n_samples=100,
                    min_intervals=12, gyro_scale_init=None, pose_means=False):
    require(rec, "accel", recipe="multi-position")
    return multi_position(rec.accel, rec.gyro, rec.t, gravity=gravity, init_seconds=init_seconds,
                          window=window, n_samples=n_samples, min_intervals=min_intervals,
                          gyro_scale_init=gyro_scale_init, pose_means=pose_means)


RECIPES: dict[str, Recipe] = {
    r.name: r
    for r in (
        Recipe("binned-thermal", "CN102230806 (Institute of Software, CAS, 2011)",
               "static warm-up: 0.1 °C bins, even sub-sampling, a straight bias line per axis "
               "accepted when |r| > 0.999", ("gyro", "temp"), _binned_thermal),
        Recipe("static-kalman", "Wuxi Lingsi Technology patent, 2018",
               "thresholds from a 1000-sample rest, static windows, scalar Kalman offset "
               "(Q = 1e-4), heading with and without it", ("gyro", "accel"), _static_kalman),
        Recipe("fog-one-run", "fibre-optic gyro patent: one chamber run for scale factor and bias",
               "[D, T·D, T²·D, T, T − T_out, dT] regressed on K0·Ω after removing ±m samples "
               "around rate sign changes", ("gyro", "temp", "temp_ext", "rate"), _fog_one_run),
        Recipe("attitude-reference", "Goertek patent, 2018",
               "accelerometer + magnetometer attitude, |a| gate, alternating scale/bias, "
               "complementary fusion; joint least squares beside it",
               ("gyro", "accel", "mag"), _attitude_reference),
        Recipe("cube-bias", "Shaanxi Zhongtian Rocket Technology patent, 2020",
               "cube fixture, up/down faces × four headings: accelerometer and gyro biases "
               "without a level table", ("gyro", "accel"), _cube_bias),
        Recipe("six-position", "Ferraris et al. 1995, as implemented by imucal",
               "six static faces and a known turn about each axis: accelerometer and gyro "
               "bias, scale, misalignment and g-sensitivity", ("gyro", "accel"), _six_position),
        Recipe("multi-position", "Tedaldi, Pretto, Menegatti, ICRA 2014 (IMU-TK)",
               "hand-placed static poses, no turntable: accelerometer from |a| = g, gyro by "
               "integrating between poses", ("gyro", "accel"), _multi_position),
    )
}


def get(name: str) -> Recipe:
    """The recipe called ``name``; a DataError lists the valid names otherwise.

    **Arguments:**

    - ``name``: the recipe's name, as the command line spells it (``"six-position"``, …).
    """
    try:
        return RECIPES[name]
    except KeyError:
        raise DataError(f"unknown recipe {name!r}",
                        hint="valid recipes: " + ", ".join(RECIPES)) from None


__all__ = ["get", "RECIPES", "Recipe", "RecipeResult", "AttitudeReferenceResult",
           "BinnedThermalResult", "CubeBiasResult", "FogOneRunResult", "MultiPositionResult",
           "SixPositionResult", "StaticKalmanResult", "attitude_reference", "binned_thermal",
           "cube_bias", "fog_one_run", "jsonable", "multi_position", "read_sections", "read_sets",
           "six_position", "static_intervals", "static_kalman", "single_axis",
           "toolkit_compensate", "heading_errors"]
