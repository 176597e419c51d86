"""The motion check's result: :class:`Motion` (per device, the judgement's numbers, its
verdict and the samples at rest), the verdict each device's numbers give, the rest a fit
of the rest only keeps, and the judgement in words. :mod:`diffgyro.motion` forms it."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import numpy as np
from jaxtyping import Bool, Float, Int

from ._jsonio import number
from ._motion_constants import MAX_BIAS, MAX_RESOLUTION, MIN_PEAK_RATIO, MIN_TILT, MIN_WINDOWS
from ._vocabulary import MAX_INTERVALS, VERDICT_NAMES

#: The verdict of a device judged at rest (:attr:`Motion.verdict`).
AT_REST = 0
#: The verdict of a device that moved.
IN_MOTION = 1
#: The verdict of a device whose rest its recording cannot show.
UNVERIFIED = 2
_STATUS = ("ok", "in_motion", "rest_unverified")
NUMBERS = ("moving_fraction", "rate_peak", "rate_rms", "turn_peak", "tilt_peak", "rest_rate",
            "rest_noise", "threshold", "resolution", "n_windows")


class Motion(eqx.Module):
    """Motion check of every device (leading device axis).

    ``moving_fraction`` (0..1 of the valid samples), ``rate_peak`` and
    ``rate_rms`` (rad/s, the window-mean rate of the moving windows less the
    baseline, over the moving windows; 0 when none moved), ``turn_peak`` (rad, the
    largest angle turned within one run of moving windows, from the rate less the
    baseline), ``tilt_peak`` (rad, the largest tilt of gravity within a stretch between
    moves, where the accelerometer is read), ``rest_rate`` (rad/s, the mean rate of the
    windows judged at rest: a bias, unless it exceeds :data:`MAX_BIAS`), ``rest_noise``
    (rad/s per sample, RMS over axes), ``threshold`` (rad/s, the deviation of a
    window mean at rest noise that counts as moving, RMS over axes), ``resolution``
    (rad: the turn a window at rest noise shows, threshold × window length),
    ``n_windows`` (valid windows), the ``verdict`` (:data:`AT_REST`,
    :data:`IN_MOTION` or :data:`UNVERIFIED`) and the per-sample ``static`` mask (valid,
    not moving, not next to a moving window, at the rest's rate). A judgement the host
    reads, so numpy arrays.
    """

    moving_fraction: Float[np.ndarray, " d"]
    rate_peak: Float[np.ndarray, " d"]
    rate_rms: Float[np.ndarray, " d"]
    turn_peak: Float[np.ndarray, " d"]
    tilt_peak: Float[np.ndarray, " d"]
    rest_rate: Float[np.ndarray, " d"]
    rest_noise: Float[np.ndarray, " d"]
    threshold: Float[np.ndarray, " d"]
    resolution: Float[np.ndarray, " d"]
    n_windows: Float[np.ndarray, " d"]
    verdict: Int[np.ndarray, " d"]
    static: Bool[np.ndarray, "d n"]
    #: The samples' times (s), for the intervals of rest; None where not given.
    t: Float[np.ndarray, "d n"] | None = None
    #: Samples per window, and the window's length (s), per device.
    window: Int[np.ndarray, " d"] | None = None
    window_s: Float[np.ndarray, " d"] | None = None
    #: Whether the verdict is of the rest kept (``static_only``: :func:`rest_kept`).
    kept: bool = eqx.field(static=True, default=False)

    def record(self, i: int) -> dict:
        """Device ``i``'s ``motion`` object (JSON-ready; null where not computed): the
        numbers, the ``verdict`` and, unless at rest, the ``reason`` in words; of a fit of
        the rest only, the intervals kept (``rest_intervals``: start, end, length in s)."""
        out = {k: number(getattr(self, k)[i]) for k in NUMBERS}
        out["n_windows"] = None if out["n_windows"] is None else int(out["n_windows"])
        out["window_s"] = number(self.window_s[i])
        out["verdict"] = VERDICT_NAMES[int(self.verdict[i])]
        if self.kept:
            spans = self.intervals(i)
            out["rest_kept_s"] = number(sum(s[2] for s in spans))
            out["rest_intervals"] = spans[:MAX_INTERVALS]
            if len(spans) > MAX_INTERVALS:
                out["rest_intervals_left_out"] = len(spans) - MAX_INTERVALS
        if out["verdict"] != "at_rest":
            out["reason"] = reason(out) if not self.kept else self._kept_reason(i, out)
        return out

    def intervals(self, i: int) -> list[list[float]]:
        """The intervals of device ``i``'s static samples: ``[start, end, length]`` in s
        (length counts the samples kept, one sampling interval each)."""
        keep = np.asarray(self.static[i], bool)
        edges = np.flatnonzero(np.diff(np.r_[0, keep.astype(np.int8), 0]))
        if self.t is None or not edges.size:
            return []
        t = np.asarray(self.t[i], float)
        dt = float(self.window_s[i]) / max(int(self.window[i]), 1)
        return [[float(t[a]), float(t[b - 1]), float((b - a) * dt)]
                for a, b in zip(edges[::2], edges[1::2])]

    def _kept_reason(self, i: int, rec: dict) -> str:
        if rec.get("rest_rate") is not None and rec["rest_rate"] > MAX_BIAS:
            return (f"the rest it keeps turns at {rec['rest_rate']:.2g} rad/s, more than any "
                    f"gyro's bias ({MAX_BIAS:g} rad/s): a spin, and no rest was found")
        need = MIN_WINDOWS * float(self.window_s[i])
        if rec.get("rest_kept_s") is not None and rec["rest_kept_s"] < need:
            return (f"too little rest left to fit: {rec['rest_kept_s']:.3g} s of rest kept "
                    f"(at least {need:.3g} s needed)")
        return reason({**rec, "verdict": "unverified"})

    def put(self, idx, other: Motion) -> Motion:
        """Devices ``idx`` with ``other``'s numbers and verdict (``other`` holds those
        devices only, in that order); the static mask stays this one's."""
        num = {k: np.array(getattr(self, k)) for k in NUMBERS}
        verdict = np.array(self.verdict)
        for k in NUMBERS:
            num[k][idx] = np.asarray(getattr(other, k))
        verdict[idx] = np.asarray(other.verdict)
        return dataclasses.replace(self, verdict=verdict, **num)

    def moved_all(self) -> Bool[np.ndarray, " d"]:
        """Whether each device moved (verdict :data:`IN_MOTION`)."""
        return np.asarray(self.verdict) == IN_MOTION

    def unverified_all(self) -> Bool[np.ndarray, " d"]:
        """Whether each device's rest cannot be judged from its recording (verdict
        :data:`UNVERIFIED`: too short, or too noisy to show a turn of a degree)."""
        return np.asarray(self.verdict) == UNVERIFIED

    def status(self, i: int) -> str:
        """Device ``i``'s status for a result that assumes rest: ``ok``, ``in_motion`` or
        ``rest_unverified``."""
        return _STATUS[int(self.verdict[i])]

    def status_detail(self, i: int, consequence: str = "") -> str:
        """``ok``, or the status, why in words and ``consequence`` (what it means for the
        result at hand)."""
        name = self.status(i)
        if name == "ok":
            return name
        return f"{name}: {self.record(i)['reason']}" + (f"; {consequence}" if consequence else "")

    def moved(self, i: int) -> bool:
        """Whether device ``i`` moved (:meth:`moved_all`)."""
        return bool(self.moved_all()[i])

    def at_rest(self, i: int) -> bool:
        """Whether device ``i`` was judged at rest."""
        return int(self.verdict[i]) == AT_REST

    def select(self, idx) -> Motion:
        """The devices ``idx`` (an index array)."""
        idx = np.asarray(idx)
        return dataclasses.replace(self, t=None if self.t is None else np.asarray(self.t)[idx],
                                   **{k: np.asarray(getattr(self, k))[idx]
                                      for k in NUMBERS + ("verdict", "static", "window",
                                                           "window_s")})


def rest_kept(motion: Motion) -> Motion:
    """The verdict on the rest :attr:`Motion.static` keeps (a fit of the rest only): at rest
    where at least :data:`MIN_WINDOWS` windows of it are kept, the recording resolves a
    turn of :data:`MAX_RESOLUTION` and the rest kept turns no faster than a bias
    (:data:`MAX_BIAS`), else unverified (too little rest, too noisy to show it, or a
    spin).

    **Arguments:**

    - ``motion``: the :class:`Motion` of a recording.
    """
    kept = np.asarray(motion.static).sum(axis=1) / np.maximum(motion.window, 1)
    with np.errstate(invalid="ignore"):
        fine = ((kept >= MIN_WINDOWS) & (np.asarray(motion.resolution, float) <= MAX_RESOLUTION)
                & ~(np.asarray(motion.rest_rate, float) > MAX_BIAS))
    return dataclasses.replace(motion, kept=True,
                               verdict=np.where(fine, AT_REST, UNVERIFIED).astype(np.int8))


def verdicts(num: dict) -> np.ndarray:
    """Each device's verdict from its numbers (:data:`NUMBERS`, numpy): in motion where a
    run of moving windows reached :data:`MIN_PEAK_RATIO` times the threshold, gravity
    tilted by :data:`MIN_TILT`, or the windows left at rest turn faster than any bias
    (:data:`MAX_BIAS`); else unverified where the recording is too short
    (:data:`MIN_WINDOWS`) or too noisy to show a turn of :data:`MAX_RESOLUTION`; else at
    rest."""
    with np.errstate(invalid="ignore"):
        frac = np.nan_to_num(np.asarray(num["moving_fraction"], float))
        peak = np.asarray(num["rate_peak"], float)
        thr = np.asarray(num["threshold"], float)
        tilt = np.asarray(num["tilt_peak"], float)
        moved = (frac > 0) & ((peak >= MIN_PEAK_RATIO * thr) | (tilt >= MIN_TILT))
        moved |= np.asarray(num["rest_rate"], float) > MAX_BIAS  # a steady turn, no bias
        short = ~(np.asarray(num["n_windows"], float) >= MIN_WINDOWS)
        coarse = ~(np.asarray(num["resolution"], float) <= MAX_RESOLUTION)
    return np.where(moved, IN_MOTION, np.where(short | coarse, UNVERIFIED, AT_REST)).astype(np.int8)


def pct_of(rec: dict) -> str:
    """A ``motion`` record's moving fraction in percent, as text."""
    frac = rec.get("moving_fraction")
    return "?" if frac is None else f"{100 * frac:.0f}" if frac >= 0.01 else f"{100 * frac:.1g}"


def describe(rec: dict) -> str:
    """How much of a recording moved and how fast, from a ``motion`` record.

    **Arguments:**

    - ``rec``: a device's ``motion`` record (:meth:`Motion.record`).
    """
    def g(x):
        return "—" if x is None else f"{x:.2g}"

    pct = pct_of(rec)
    turn, tilt, steady = rec.get("turn_peak"), rec.get("tilt_peak"), rec.get("rest_rate")
    if steady is not None and steady > MAX_BIAS:
        return (f"it turns steadily at {steady:.2g} rad/s, more than any gyro's bias "
                f"({MAX_BIAS:g} rad/s): a spin, not rest; {pct_of(rec)} % of the recording "
                f"moved besides")
    turned = "" if turn is None else f", turns up to {math.degrees(turn):.2g}°"
    if tilt:
        turned += f", gravity tilted by up to {math.degrees(tilt):.2g}°"
    return (f"{pct} % of the recording moved (rates up to {g(rec.get('rate_peak'))} rad/s, "
            f"{g(rec.get('rate_rms'))} rad/s RMS{turned}, against a rest noise of "
            f"{g(rec.get('rest_noise'))} rad/s)")


def reason(rec: dict) -> str:
    """Why a ``motion`` record's device is not at rest, in words.

    **Arguments:**

    - ``rec``: a device's ``motion`` record (:meth:`Motion.record`).
    """
    if rec.get("verdict") == "in_motion":
        return describe(rec)
    n, tw = rec.get("n_windows"), rec.get("window_s") or 0.0
    if not n:
        return "no valid window: whether the device was at rest cannot be judged"
    if n < MIN_WINDOWS:
        return (f"too short to judge whether the device was at rest: {n * tw:.3g} s "
                f"({n} window{'s' * (n != 1)} of {tw:.2g} s); the check needs {MIN_WINDOWS * tw:.3g} s "
                f"({MIN_WINDOWS} windows)")
    res = rec.get("resolution")
    return (f"cannot show whether the device was at rest: its quietest windows ({tw:.2g} s) "
            f"only resolve a turn of {math.degrees(res):.2g}° (rest noise "
            f"{rec.get('rest_noise'):.2g} rad/s), and rest must be shown to "
            f"{math.degrees(MAX_RESOLUTION):.0f}°; record at rest at a higher rate, or "
            f"give a rate reference")


__all__ = ["AT_REST", "IN_MOTION", "NUMBERS", "UNVERIFIED", "Motion", "describe", "pct_of", "reason",
           "rest_kept", "verdicts"]
