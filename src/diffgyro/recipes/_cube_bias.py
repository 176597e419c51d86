"""cube-bias (Shaanxi Zhongtian Rocket patent, 2020): zero-rate and accelerometer biases
without a level table, from a cube fixture.

The published procedure: the IMU sits in a cube fixture (axes along the
faces) on any table. Z up: static data at four headings, turning 90°
clockwise between them; Z down: four headings likewise; then Y up ×4 and
Y down ×4. For an axis, the *up* value is its mean over the four headings of
the up set and the *down* value its mean over the down set; the bias is
``(up + down) / 2``:

* averaging over four headings 90° apart cancels what the table's tilt and
  the horizontal Earth rate put on the axes lying in the table plane;
* up / down cancels what flips with the face: gravity and the vertical
  Earth rate seen through misalignment, g-sensitivity, fixture errors.

As published, the Z-up/down sets give the biases of the x and y axes and
the Y-up/down sets the z axis. With all six faces recorded (``x_up``,
``x_down`` as well) every axis averages over both perpendicular face pairs.

Sets are keyed ``{axis}_{up|down}_{heading}``, e.g. ``z_up_1`` … ``z_up_4``,
as sample ranges ``[start, end)``.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import DataError
from ._common import RecipeResult

AXES = "xyz"
#: Published assignment: which face pair gives the bias of each axis.
PUBLISHED = {"x": ("z",), "y": ("z",), "z": ("y",)}


@dataclass(frozen=True)
class CubeBiasResult(RecipeResult):
    """Accelerometer and gyro biases and the face means they come from."""

    gyro_bias: np.ndarray        # (3,)
    accel_bias: np.ndarray       # (3,)
    face_gyro: dict              # "{axis}_{up|down}" -> (3,) mean over its headings
    face_accel: dict
    pairs_used: dict             # axis -> face axes whose up/down pair gave its bias

    name = "cube-bias"


def read_sets(source: str | Path | Mapping, n_samples: int | None = None) -> dict:
    """Sample ranges of the static sets from JSON (``{"z_up_1": {"start": 0, "end": 900}, ...}``).

    **Arguments:**

    - ``source``: a JSON file's path, or the mapping itself.
    - ``n_samples``: the recording's length; a set ending beyond it is refused (default:
      unchecked).
    """
    where = None
    if isinstance(source, Mapping):
        raw = source
    else:
        where = str(source)
        try:
            raw = json.loads(Path(source).read_text())
        except (FileNotFoundError, json.JSONDecodeError) as err:
            raise DataError(f"cannot read the set file ({err})", file=where) from None
    out = {}
    for key, v in raw.items():
        parts = key.split("_")
        if len(parts) != 3 or parts[0] not in AXES or parts[1] not in ("up", "down"):
            raise DataError(f"set name {key!r} is not axis_up|down_heading (e.g. z_up_1)",
                            file=where)
        start, end = (v["start"], v["end"]) if isinstance(v, Mapping) else v
        start, end = int(start), int(end)
        if not 0 <= start < end or (n_samples is not None and end > n_samples):
            raise DataError(f"set {key!r} has an invalid range [{start}, {end})", file=where)
        out[key] = (start, end)
    return out


def cube_bias(gyro: np.ndarray, accel: np.ndarray, sets: Mapping | str | Path,
              *, published: bool = True) -> CubeBiasResult:
    """Biases from up/down face sets, each over four (or more) headings.

    ``published=True`` uses the patent's assignment (z faces → x, y; y faces
    → z); ``False`` averages every perpendicular face pair present.

    **Arguments:**

    - ``gyro``: the measured rate (n, 3).
    - ``accel``: the specific force (n, 3).
    - ``sets``: the static sets' sample ranges, or a JSON file of them (:func:`read_sets`).
    - ``published``: the patent's assignment of faces to axes, or every perpendicular pair.
    """
    gyro = np.asarray(gyro, float)
    accel = np.asarray(accel, float)
    if not isinstance(sets, Mapping) or not all(isinstance(v, tuple) for v in sets.values()):
        sets = read_sets(sets, n_samples=gyro.shape[0])
    face_g: dict[str, np.ndarray] = {}
    face_a: dict[str, np.ndarray] = {}
    groups: dict[str, list[tuple[int, int]]] = {}
    for key, rng in sets.items():
        ax, side, _ = key.split("_")
        groups.setdefault(f"{ax}_{side}", []).append(rng)
    for face, ranges in groups.items():
        if len(ranges) < 4:
            raise DataError(f"face {face} has {len(ranges)} headings; the method needs four "
                            "(90° apart) to cancel the table tilt")
        face_g[face] = np.mean([gyro[a:b].mean(0) for a, b in ranges], axis=0)
        face_a[face] = np.mean([accel[a:b].mean(0) for a, b in ranges], axis=0)
    gb = np.full(3, np.nan)
    ab = np.full(3, np.nan)
    used: dict[str, list[str]] = {}
    for i, ax in enumerate(AXES):
        candidates = PUBLISHED[ax] if published else tuple(a for a in AXES if a != ax)
        pairs = [f for f in candidates if f"{f}_up" in face_g and f"{f}_down" in face_g]
        if not pairs:
            need = " or ".join(f"{f}_up/{f}_down" for f in candidates)
            raise DataError(f"no face pair for the {ax} axis", hint=f"record {need}")
        gb[i] = np.mean([(face_g[f"{f}_up"][i] + face_g[f"{f}_down"][i]) / 2 for f in pairs])
        ab[i] = np.mean([(face_a[f"{f}_up"][i] + face_a[f"{f}_down"][i]) / 2 for f in pairs])
        used[ax] = pairs
    return CubeBiasResult(gyro_bias=gb, accel_bias=ab, face_gyro=face_g, face_accel=face_a,
                          pairs_used=used)
