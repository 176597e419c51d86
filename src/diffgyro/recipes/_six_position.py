"""six-position: Ferraris-style calibration from six static faces and three known turns.

The procedure imucal implements (Ferraris et al., 1995): the sensor rests
with each axis pointing up (``x_p``, ``y_p``, ``z_p``) and down (``x_a``,
``y_a``, ``z_a``), then turns by a known angle about each axis while that
axis points up (``x_rot``, ``y_rot``, ``z_rot``). Sections are sample ranges
``[start, end)``.

Accelerometer (closed form, the published algebra): with ``U_p`` and ``U_a``
the 3×3 matrices whose columns are the face means (x, y, z up / down),
``accel_bias = diag(U_p + U_a) / 2`` and ``accel_matrix = 2g · (U_p − U_a)⁻¹``.

Gyroscope, solved with the toolkit's terms:

* static faces: the model ``bias_poly(0) + g_sens`` (true rate zero,
  specific force = the calibrated accelerometer) fitted by least squares over
  all face samples gives ``gyro_bias`` and ``g_sens`` — Earth rate is ignored,
  as in the published method;
* turns: the same linear terms ``scale_poly(0) + misalignment`` applied to the
  *integrated* rate. Each turn's corrected, integrated output ``W[:, i]``
  equals ``(I + S + M) · angle · e_i``, three equations per axis for three
  coefficients per axis, so ``gyro_matrix = (I + S + M)⁻¹ = angle · W⁻¹``.

Conventions are imucal's: ``ω = gyro_matrix · (ω_raw − gyro_bias − g_sens · a)``
and ``a = accel_matrix · (a_raw − accel_bias)`` in the input units; a
clockwise turn (negative rate) by default (``rotation_angle = −360``).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..model import ErrorModel
from ._common import RecipeResult, least_squares_params, signals_for

FACES = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
TURNS = ("x_rot", "y_rot", "z_rot")
SECTIONS = FACES + TURNS

STATIC_MODEL = "bias_poly(0)+g_sens"
TURN_MODEL = "scale_poly(0)+misalignment"


def read_sections(source: str | Path | Mapping, n_samples: int | None = None,
                  file: str | None = None) -> dict[str, tuple[int, int]]:
    """Sample ranges ``{section: (start, end)}`` from imucal's JSON shape.

    Accepts ``{"x_p": {"start": 540, "end": 1271}, ...}`` or ``{"x_p": [540, 1271]}``;
    ``end`` is exclusive. Every one of the nine sections is required.

    **Arguments:**

    - ``source``: a JSON file's path, or the mapping itself.
    - ``n_samples``: the recording's length; a section ending beyond it is refused (default:
      unchecked).
    - ``file``: the file's name for errors when ``source`` is a mapping.
    """
    if isinstance(source, Mapping):
        raw, where = source, file
    else:
        where = str(source)
        try:
            raw = json.loads(Path(source).read_text())
        except FileNotFoundError:
            raise DataError("section file not found", file=where,
                            hint="give --sections FILE with the sample ranges") from None
        except json.JSONDecodeError as err:
            raise DataError(f"section file is not valid JSON ({err.msg} at line {err.lineno})",
                            file=where) from None
    if not isinstance(raw, Mapping):
        raise DataError("section file must hold a JSON object", file=where)
    out: dict[str, tuple[int, int]] = {}
    for key in SECTIONS:
        if key not in raw:
            raise DataError(f"section {key!r} missing", file=where,
                            hint="needs " + ", ".join(SECTIONS))
        v = raw[key]
        try:
            start, end = (v["start"], v["end"]) if isinstance(v, Mapping) else v
            start, end = int(start), int(end)
        except (KeyError, TypeError, ValueError):
            raise DataError(f"section {key!r} must be {{\"start\": i, \"end\": j}} or [i, j]",
                            file=where) from None
        if not 0 <= start < end:
            raise DataError(f"section {key!r} has start {start} and end {end}",
                            file=where, hint="need 0 <= start < end")
        if n_samples is not None and end > n_samples:
            raise DataError(f"section {key!r} ends at sample {end}, the data has {n_samples}",
                            file=where)
        out[key] = (start, end)
    return out


@dataclass(frozen=True)
class SixPositionResult(RecipeResult):
    """Calibration in the input units (imucal's meaning, see the module docstring)."""

    gyro_bias: np.ndarray     # (3,)
    gyro_matrix: np.ndarray   # (3, 3)
    g_sens: np.ndarray        # (3, 3)  gyro unit per accel unit
    accel_bias: np.ndarray    # (3,)
    accel_matrix: np.ndarray  # (3, 3)
    turn_integrals: np.ndarray  # (3, 3): corrected integrated rate of each turn (columns)
    gravity: float
    rotation_angle: float

    name = "six-position"

    def calibrate_accel(self, accel: np.ndarray) -> np.ndarray:
        return (np.asarray(accel) - self.accel_bias) @ self.accel_matrix.T

    def calibrate_gyro(self, gyro: np.ndarray, accel_calibrated: np.ndarray) -> np.ndarray:
        raw = np.asarray(gyro) - self.gyro_bias - np.asarray(accel_calibrated) @ self.g_sens.T
        return raw @ self.gyro_matrix.T

    def contract(self) -> dict:
        """The ``recipe six-position --json`` object."""
        return {
            "gyro_bias": self.gyro_bias.tolist(),
            "gyro_matrix": self.gyro_matrix.tolist(),
            "g_sens": self.g_sens.tolist(),
            "accel_bias": self.accel_bias.tolist(),
            "accel_matrix": self.accel_matrix.tolist(),
        }

    def to_dict(self) -> dict:
        return self.contract()

    def scaled(self, gyro_factor: float, accel_factor: float) -> SixPositionResult:
        """The same calibration for data whose units are ``factor ×`` these (unit change)."""
        return SixPositionResult(
            gyro_bias=self.gyro_bias * gyro_factor,
            gyro_matrix=self.gyro_matrix,
            g_sens=self.g_sens * gyro_factor / accel_factor,
            accel_bias=self.accel_bias * accel_factor,
            accel_matrix=self.accel_matrix,
            turn_integrals=self.turn_integrals * gyro_factor,
            gravity=self.gravity * accel_factor,
            rotation_angle=self.rotation_angle * gyro_factor,
        )


def _sample_intervals(t: np.ndarray | None, n: int, sampling_rate: float | None) -> np.ndarray:
    """Per-sample integration step (rectangle rule, as imucal sums ``ω / fs``)."""
    if t is None:
        if not sampling_rate or sampling_rate <= 0:
            raise DataError("six-position needs a sampling rate or a time column",
                            hint="give --sampling-rate HZ")
        return np.full(n, 1.0 / sampling_rate)
    t = np.asarray(t, float)
    if sampling_rate:
        return np.full(n, 1.0 / sampling_rate)
    dt = np.diff(t)
    return np.concatenate([dt, dt[-1:]])


def six_position(
    gyro: np.ndarray,
    accel: np.ndarray,
    sections: Mapping[str, tuple[int, int]] | str | Path,
    *,
    t: np.ndarray | None = None,
    sampling_rate: float | None = None,
    rotation_angle: float = -360.0,
    gravity: float = 9.81,
) -> SixPositionResult:
    """Calibrate accelerometer and gyroscope from six faces and three turns.

    ``gyro`` and ``accel`` are ``(n, 3)`` in any units; ``rotation_angle`` is
    in the gyro's angle unit (−360 for deg/s, −2π for rad/s) and ``gravity``
    in the accelerometer's. Integration uses ``1 / sampling_rate`` per sample
    when given, otherwise the spacing of ``t``.

    **Arguments:**

    - ``gyro``: the gyro's output (n, 3).
    - ``accel``: the accelerometer's output (n, 3).
    - ``sections``: the nine sections' sample ranges, or a JSON file of them
      (:func:`read_sections`).
    - ``t``: sample times (n,), s (when ``sampling_rate`` is not given).
    - ``sampling_rate``: samples per second.
    - ``rotation_angle``: each turn's angle in the gyro's angle unit.
    - ``gravity``: the magnitude of gravity in the accelerometer's unit.
    """
    gyro = np.asarray(gyro, float)
    accel = np.asarray(accel, float)
    if gyro.ndim != 2 or gyro.shape[1] != 3 or accel.shape != gyro.shape:
        raise DataError("six-position needs gyro and accel arrays of shape (n, 3)")
    n = gyro.shape[0]
    if not isinstance(sections, Mapping) or not all(isinstance(v, tuple) for v in sections.values()):
        sections = read_sections(sections, n_samples=n)
    sec = {k: slice(*sections[k]) for k in SECTIONS}
    for k, s in sec.items():
        if s.stop > n:
            raise DataError(f"section {k!r} ends at sample {s.stop}, the data has {n}")
    dt = _sample_intervals(t, n, sampling_rate)

    # Accelerometer: face means, the published closed form.
    u_p = np.stack([accel[sec[f]].mean(0) for f in ("x_p", "y_p", "z_p")], axis=1)
    u_a = np.stack([accel[sec[f]].mean(0) for f in ("x_a", "y_a", "z_a")], axis=1)
    accel_bias = np.diag(u_p + u_a) / 2.0
    diff = u_p - u_a
    if np.linalg.cond(diff) > 1e8:
        raise DataError("the six faces do not span three axes (face means are collinear)",
                        hint="check the section ranges: each face must point one axis up or down")
    accel_matrix = 2.0 * gravity * np.linalg.inv(diff)

    def cal_acc(a):
        return (a - accel_bias) @ accel_matrix.T

    # Gyro, static faces: bias_poly(0) + g_sens, least squares over every face sample.
    idx = np.concatenate([np.arange(n)[sec[f]] for f in FACES])
    static = ErrorModel.from_spec(STATIC_MODEL)
    sig = signals_for(gyro=gyro[idx], accel=cal_acc(accel[idx]))
    beta = least_squares_params(static, sig, gyro[idx])
    gyro_bias = beta[:, 0]
    g_sens = beta[:, 1:4]

    # Gyro, turns: integrated corrected rate = (I + S + M) · angle · e_i.
    w = np.zeros((3, 3))
    for i, k in enumerate(TURNS):
        s = sec[k]
        corrected = gyro[s] - gyro_bias - cal_acc(accel[s]) @ g_sens.T
        w[:, i] = (corrected * dt[s, None]).sum(0)
    turn = ErrorModel.from_spec(TURN_MODEL)
    tsig = signals_for(gyro=w.T, rate=rotation_angle * np.eye(3))
    beta_turn = least_squares_params(turn, tsig, w.T - rotation_angle * np.eye(3))
    forward = np.asarray(jnp.einsum("nip,ip->ni", turn.design(tsig, jnp.zeros(0)), beta_turn))
    forward = forward / rotation_angle + np.eye(3)   # rows: turns, columns: axes -> (I+S+M)^T
    gyro_matrix = np.linalg.inv(forward.T)
    return SixPositionResult(
        gyro_bias=np.asarray(gyro_bias), gyro_matrix=gyro_matrix, g_sens=np.asarray(g_sens),
        accel_bias=accel_bias, accel_matrix=accel_matrix, turn_integrals=w,
        gravity=float(gravity), rotation_angle=float(rotation_angle))
