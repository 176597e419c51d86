"""The names that files, commands and engines share, defined without JAX.

A calibration file is validated against these (its statuses, motion verdicts, channel),
``export`` judges a device's residual with them, and a command checks a recording's
length for a model with them; keeping them here lets the commands that compile nothing
(``export``, ``effects``, ``compensate``, a bad input's error) answer without starting
JAX. :mod:`diffgyro.status`, :mod:`diffgyro.motion`, :mod:`diffgyro.channel` and
:mod:`diffgyro.data` re-export them."""

from __future__ import annotations

import math
from collections.abc import Iterable

__all__ = ["STATUS_NAMES", "VERDICT_NAMES", "MAX_INTERVALS", "CHANNELS", "UNITS", "AUX_PREFIX",
           "aux_names", "min_samples", "RESIDUAL_WARN", "RESIDUAL_REFUSE", "residual_verdict", "residual_note"]

#: A device's fit status, by its code (:func:`diffgyro.status.fit_status`).
STATUS_NAMES = ("ok", "not_converged", "rank_deficient", "insufficient_range",
                "insufficient_data", "failed", "in_motion", "rest_unverified")
#: The motion check's verdicts, by their code (:attr:`diffgyro.motion.Motion.verdict`).
VERDICT_NAMES = ("at_rest", "in_motion", "unverified")
#: Intervals of rest listed in a motion record (the rest are counted).
MAX_INTERVALS = 100
#: The channels, the first the default.
CHANNELS = ("gyro", "accel")
#: The unit of each channel's measurement (and of its bias coefficients per unit of signal).
UNITS = {"gyro": "rad/s", "accel": "m/s²"}
#: The prefix of an extra column's signal name (``aux:NAME``).
AUX_PREFIX = "aux:"


def aux_names(required: Iterable[str]) -> tuple[str, ...]:
    """Extra-column names among a model's required signals (``aux:NAME``), sorted."""
    return tuple(sorted(s[len(AUX_PREFIX):] for s in required if s.startswith(AUX_PREFIX)))


def min_samples(n_unknowns: int) -> int:
    """Fewest valid samples for a least-squares fit of ``n_unknowns`` parameters per axis.

    **Arguments:**

    - ``n_unknowns``: the parameters per axis.
    """
    return max(2 * n_unknowns, n_unknowns + 4)


#: Held-out RMS over the noise floor above which a calibration carries a warning: the
#: model misses an effect (``model_limit``), and ``diffgyro diagnose`` names it.
RESIDUAL_WARN = 3.0
#: ... above which the number is not the sensor's to any use (``unexplained``): export
#: refuses it unless ``--force``.
RESIDUAL_REFUSE = 10.0


def residual_verdict(heldout_rms, noise_floor) -> tuple[str, float | None]:
    """``ok``, ``model_limit`` or ``unexplained`` for a device's held-out RMS against its
    noise floor (:data:`RESIDUAL_WARN`, :data:`RESIDUAL_REFUSE`), and their ratio (None
    where either is missing).

    **Arguments:**

    - ``heldout_rms``: the device's held-out RMS, rad/s (None: not known).
    - ``noise_floor``: its noise floor, rad/s (None: not known).
    """
    try:
        ratio = float(heldout_rms) / float(noise_floor)
    except (TypeError, ValueError, ZeroDivisionError):
        return "ok", None
    if not math.isfinite(ratio):
        return "ok", None
    if ratio > RESIDUAL_REFUSE:
        return "unexplained", ratio
    return ("model_limit" if ratio > RESIDUAL_WARN else "ok"), ratio


def residual_note(device: str, heldout_rms, noise_floor) -> str | None:
    """One line for a device whose residual stands above its noise floor, else None.

    **Arguments:**

    - ``device``: the device's name.
    - ``heldout_rms``: its held-out RMS, rad/s.
    - ``noise_floor``: its noise floor, rad/s.
    """
    verdict, ratio = residual_verdict(heldout_rms, noise_floor)
    if verdict == "ok":
        return None
    line = (f"{device}: held-out RMS {ratio:.3g}x its noise floor: the model misses an effect "
            f"that diffgyro diagnose can name")
    if verdict == "unexplained":
        line += (f"; above {RESIDUAL_REFUSE:g}x the calibration is not the sensor's, and export "
                 f"refuses it unless --force")
    return line
