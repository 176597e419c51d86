"""The published calibration methods as faithful recipes (SEEDS.md), plus the
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
from collections.abc import Callable
from dataclasses import dataclass

from ..errors import DataError
from ._common import RecipeResult
from .multi_position import MultiPositionResult, multi_position
from .six_position import SixPositionResult, read_sections, six_position
from .static_intervals import static_intervals


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


def _six_position_run(rec, sections, *, sampling_rate=None, rotation_angle=-360.0,
                      gravity=9.81):
    """``rotation_angle`` in degrees; the recording is in SI units (rad/s, m/s²)."""
    import numpy as np

    from ._common import require

    require(rec, "accel", recipe="six-position")
    return six_position(rec.gyro, rec.accel, sections, t=rec.t, sampling_rate=sampling_rate,
                        rotation_angle=float(np.deg2rad(rotation_angle)), gravity=gravity)


def _multi_position_run(rec, *, gravity=9.81, init_seconds=50.0, window=101, n_samples=100,
                        min_intervals=12, gyro_scale_init=None, pose_means=False):
    from ._common import require

    require(rec, "accel", recipe="multi-position")
    return multi_position(rec.accel, rec.gyro, rec.t, gravity=gravity, init_seconds=init_seconds,
                          window=window, n_samples=n_samples, min_intervals=min_intervals,
                          gyro_scale_init=gyro_scale_init, pose_means=pose_means)


RECIPES: dict[str, Recipe] = {
    r.name: r
    for r in (
        Recipe("six-position", "Ferraris et al. 1995, as implemented by imucal",
               "six static faces and a known turn about each axis: accelerometer and gyro "
               "bias, scale, misalignment and g-sensitivity", ("gyro", "accel"),
               _six_position_run),
        Recipe("multi-position", "Tedaldi, Pretto, Menegatti, ICRA 2014 (IMU-TK)",
               "hand-placed static poses, no turntable: accelerometer from |a| = g, gyro by "
               "integrating between poses", ("gyro", "accel"), _multi_position_run),
    )
}


def get(name: str) -> Recipe:
    """The recipe called ``name``; a DataError lists the valid names otherwise."""
    try:
        return RECIPES[name]
    except KeyError:
        raise DataError(f"unknown recipe {name!r}",
                        hint="valid recipes: " + ", ".join(RECIPES)) from None


__all__ = ["RECIPES", "MultiPositionResult", "Recipe", "RecipeResult", "SixPositionResult",
           "get", "multi_position", "read_sections", "six_position", "static_intervals"]
