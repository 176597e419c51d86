"""Was the device at rest? A per-device motion check from the recording itself.

A fit without a rate reference (no ``rx, ry, rz``) reads every rotation of the
device as sensor error: on a flight, drive or handheld log the "bias" of
``bias_poly(0)`` is the mean turn rate, and an Allan deviation is the motion's.
:func:`motion_check` finds the rotation no such model can explain.

The recording is cut into windows of ``window`` samples (about a quarter of a
second). In every window:

* the window-mean rate ``m_k`` (and specific force, where logged);
* the local noise ``s_k`` per axis from successive differences inside the window
  (``√(mean Δ²/2)``): white noise and vibration raise it, a turn does not.

The device's rest noise ``σ`` per axis is a low quantile of the local noise
(the quietest windows, corrected for the quantile's bias), so the threshold
comes from the device's own noise floor, not from a fixed rate. Slow change
(thermal drift of the bias over minutes to hours, Earth rate, a constant
offset) is the baseline: the median of the window means over blocks of about
half a minute, linearly interpolated, computed twice (the second time over the windows
the first pass left static). A window moves when its deviation from the baseline
stands out of the noise its mean can have::

    ‖ (m_k − baseline_k) / max(K·ν·max(1, s_k/σ), floor) ‖ > 1

in a run of such windows that starts or holds a jump between neighbouring windows
of the same size (a turn starts within a window or two; thermal drift changes
little from one window to the next), with ``ν`` the noise of a window mean at rest
(:func:`noise_quantiles`), ``K`` = :data:`K_SIGMA` (a white-noise window passes it with probability
below 1e-7) and a physical floor (:data:`EARTH_RATE` for the gyro: a sensor good
enough to see Earth rotate does not call it motion; :data:`ACCEL_FLOOR` for the
accelerometer). The accelerometer, where logged, catches what the gyro baseline
could absorb (a long slow turn tilts gravity); vibration of a running engine
raises ``s_k`` and averages out of ``m_k``, so it is not motion.

A moving window marks its samples and one window either side (the transitions)
as moving; :attr:`Motion.static` is the rest, what ``--static-only`` fits.

The samples are read once (:mod:`diffgyro._window_stats`: every window statistic and
the rest noise; numpy for a small batch, a compiled pass on the host's cores for a large
one); the judgement on the windows is JAX (:mod:`diffgyro._motion_windows`), and where a
recording moved, its stretches of rest are sought on the host
(:mod:`diffgyro._rest_stretches`). The rules' numbers are in
:mod:`diffgyro._motion_constants`. A long recording is first judged in longer windows (at most
:data:`MAX_WINDOWS`), and again in its rate's where anything moved or shook, or the long
windows cannot show a turn of :data:`MAX_RESOLUTION`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import threading
from collections.abc import Callable

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Bool, Float, Int

from ._jsonio import number
from ._motion_constants import (
    ACCEL_FLOOR,
    BLOCK_S,
    EARTH_RATE,
    HALF_QUANTILE,
    K_SIGMA,
    MAX_BIAS,
    MAX_RESOLUTION,
    MAX_WINDOWS,
    MIN_PEAK_RATIO,
    MIN_TILT,
    MIN_WINDOWS,
    QUANTILE_WINDOWS,
    REST_QUANTILE,
    WINDOW_S,
)
from ._motion_windows import Layout, layout
from ._rest_stretches import rest_stretches
from ._vocabulary import MAX_INTERVALS, VERDICT_NAMES
from ._window_explain import Explanation, explain_windows, half_windows
from ._window_stats import window_stats

#: Verdicts, in :attr:`Motion.verdict`.
AT_REST, IN_MOTION, UNVERIFIED = 0, 1, 2
_STATUS = ("ok", "in_motion", "rest_unverified")
_NUMBERS = ("moving_fraction", "rate_peak", "rate_rms", "turn_peak", "tilt_peak", "rest_rate",
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
        out = {k: number(getattr(self, k)[i]) for k in _NUMBERS}
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
        num = {k: np.array(getattr(self, k)) for k in _NUMBERS}
        verdict = np.array(self.verdict)
        for k in _NUMBERS:
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
                                      for k in _NUMBERS + ("verdict", "static", "window",
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


def _verdicts(num: dict) -> np.ndarray:
    """Each device's verdict from its numbers (:data:`_NUMBERS`, numpy): in motion where a
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


def window_sizes(dt: float, samples: int | None = None) -> tuple[int, int]:
    """Samples per window and windows per baseline block for a sampling interval ``dt``
    (powers of two, so nearby rates share a compiled check); for a recording of
    ``samples``, windows long enough that it holds at most :data:`MAX_WINDOWS`.

    **Arguments:**

    - ``dt``: the sampling interval, s.
    - ``samples``: the recording's length in samples (default: no limit on the number of
      windows).
    """
    dt = dt if math.isfinite(dt) and dt > 0 else 0.01
    w = int(np.clip(2 ** round(math.log2(max(WINDOW_S / dt, 1.0))), 4, 1024))
    if samples is not None and samples > w * MAX_WINDOWS:
        w = min(1 << math.ceil(math.log2(samples / MAX_WINDOWS)), max(w, 1024))
    b = int(np.clip(2 ** round(math.log2(max(BLOCK_S / (w * dt), 1.0))), 4, 4096))
    return w, b


def noise_quantiles() -> tuple[float, float, float, float]:
    """The quantiles that give a device's rest noise per axis, of one sample (σ) and of a
    window mean (:mod:`diffgyro._window_stats` forms them as it reads the samples).

    σ is the :data:`REST_QUANTILE` of the valid windows' local noise, divided by that
    quantile of the χ distribution of a window's estimate (≈ normal: the normal quantile
    ``z`` of 1 − REST_QUANTILE). A window mean's noise is at least σ/√w, and at least
    what the half-window differences show at rest (their :data:`HALF_QUANTILE`, over the
    normal quantile ``zh`` of (1 + HALF_QUANTILE)/2, halved): sensor outputs are low-pass
    filtered, and filtered noise averages more slowly than white noise does. A quantised
    output (the quantum: the smallest change between samples) has at least the rounding
    noise quantum/√12 per sample, though the quietest windows may not change at all. The
    quantiles are read from at most :data:`QUANTILE_WINDOWS` windows spread evenly over
    the recording (a quantile needs hundreds of values, not all).

    Returns REST_QUANTILE, HALF_QUANTILE, ``z`` and ``zh``."""
    return REST_QUANTILE, HALF_QUANTILE, 1.2815515655446004, 0.2533471031357997


def _intervals(batch) -> np.ndarray:
    """Each device's sampling interval (s): the median of its first intervals between valid
    samples (at most 256 of them; 0.01 where it has none)."""
    t = np.asarray(batch.t)[:, :257].astype(float)
    m = np.asarray(batch.mask)[:, :257]
    dt = np.sort(np.where(m[:, 1:] & m[:, :-1], np.diff(t, axis=1), np.nan), axis=1)  # NaN last
    count = np.sum(~np.isnan(dt), axis=1)
    rows = np.arange(len(dt))
    if not dt.shape[1]:
        return np.full(len(dt), 0.01)
    lo, hi = np.maximum(count - 1, 0) // 2, np.maximum(count, 1) // 2
    out = 0.5 * (dt[rows, lo] + dt[rows, np.minimum(hi, dt.shape[1] - 1)])
    return np.where((count > 0) & np.isfinite(out) & (out > 0), out, 0.01)


def _device_intervals(batch, dt: float | None) -> np.ndarray:
    """Each device's sampling interval: ``dt`` where given (finite, positive), else its own
    (:func:`_intervals`)."""
    if dt is None or not (math.isfinite(dt) and dt > 0):
        return _intervals(batch)
    return np.full(np.shape(batch.mask)[0], float(dt))


def _spans(mask) -> np.ndarray:
    """Each device's samples up to its last valid one (the padding of a batch is not its)."""
    mask = np.asarray(mask, bool)
    last = mask.shape[1] - np.argmax(mask[:, ::-1], axis=1)
    return np.where(mask.any(axis=1), last, 0)


def _groups(dts, spans, fine: bool = False) -> dict[tuple[int, int], np.ndarray]:
    """Devices grouped by window and block sizes (one group unless the batch mixes rates
    or lengths far apart), from each device's sampling interval and span; ``fine``: in
    the windows of its rate alone, however long the recording."""
    keys = np.stack([dts, np.zeros_like(dts) if fine else spans.astype(float)], axis=1)
    values, which = np.unique(keys, axis=0, return_inverse=True)  # (devices share a few)
    which = np.ravel(which)
    groups: dict = {}
    for j, (dt, n) in enumerate(values):
        groups.setdefault(window_sizes(float(dt), None if fine else int(n)), []).append(
            np.flatnonzero(which == j))
    return {k: np.sort(np.concatenate(v)) for k, v in groups.items()}


def _reads(batch) -> tuple[type, bool]:
    read = np.float64 if np.asarray(batch.gyro).dtype == np.float64 else np.float32
    # with a rate reference, the referenced turns tilt gravity: no news in the accelerometer
    return read, batch.accel is not None and batch.rate is None


def motion_check(batch, dt: float | None = None, explain: Explanation | None = None,
                 ahead: Callable[[], dict] | None = None) -> Motion:
    """The :class:`Motion` of every device of a :class:`~diffgyro.data.Batch` (see the
    module docstring); ``dt`` the sampling interval (default: each device's own; devices
    sampled at rates far apart are checked in windows of their own).
    ``explain``: a fitted model (no rate reference), by whose residual a device whose
    windows left the baseline is judged again (:mod:`diffgyro._window_explain`): a
    thermal change it follows is not motion; a turn no such model can follow stays. A
    rate held beyond :data:`MAX_BIAS` (a spin, which a bias term would absorb) keeps the
    recording's verdict.
    Where the batch holds a rate reference (``rx, ry, rz``), the check reads the gyro
    less the reference (the rotation the reference does not explain), and not the
    accelerometer (the referenced turns tilt gravity); a fit's status does not follow from
    that check (the residual rule judges what the model leaves), so a long recording's
    first look in long windows stands where it found motion.

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch` to judge.
    - ``dt``: the sampling interval, s (default: each device's own).
    - ``explain``: a fitted model without rate reference whose residual judges the
      recording (default: none).
    - ``ahead``: the first look's window statistics, read beside a fit
      (:func:`check_ahead` of this batch and ``dt``).
    """
    dtype, use_accel = _reads(batch)
    # the batch's arrays as stored: the pass reads each device's rows in place, and
    # subtracts the rate reference as it reads (what it does not explain)
    gyro = np.asarray(batch.gyro)
    rate = None if batch.rate is None else np.asarray(batch.rate)
    accel = np.asarray(batch.accel) if use_accel else None
    mask = np.asarray(batch.mask)
    d, n = mask.shape
    dts = _device_intervals(batch, dt)
    spans = _spans(mask)
    num = {k: np.zeros(d, dtype) for k in _NUMBERS}
    static, window = np.zeros((d, n), bool), np.zeros(d, np.int64)
    loud = np.zeros(d, bool)
    trusted = np.zeros(d, bool) if explain is None else np.asarray(explain.trusted, bool)
    if explain is not None:
        explain = functools.partial(explain_windows, batch, explain)
    read = ahead() if ahead is not None else {}

    def check(groups, final):
        for (w, b), idx in groups.items():
            pn, static[idx], window[idx], loud[idx] = _check_group(
                gyro, accel, mask, rate, idx, w, b, dts[idx], spans[idx], use_accel,
                final=final | (w <= own[idx]), explain=explain, trusted=trusted[idx],
                read=None if final else read.get((w, b)))
            for k in _NUMBERS:
                num[k][idx] = pn[k]

    rates, which = np.unique(dts, return_inverse=True)
    own = np.array([window_sizes(x)[0] for x in rates])[np.ravel(which)]
    check(_groups(dts, spans), final=False)
    # a long recording is judged first in long windows: where nothing moved in them, none
    # was shaken, and they show a turn of MAX_RESOLUTION, it was at rest. Where something
    # moved or shook, or the long windows cannot show a degree (a noisy gyro, or
    # correlated noise that averages slowly), it is judged again in the windows of its
    # rate: whether and how it moved, in the detail of its rate
    verdict = _verdicts(num)
    with np.errstate(invalid="ignore"):
        again = (window > own) & ((num["moving_fraction"] > 0) | (verdict != AT_REST) | loud)
    # (with a rate reference the check is of what the reference leaves, and a first look
    # in motion stands: the fit's status does not follow from it, and its rate's windows
    # would find the same motion in more detail)
    if rate is not None:
        again &= verdict == UNVERIFIED
    if again.any():
        idx = np.flatnonzero(again)
        check({k: idx[v] for k, v in _groups(dts[idx], spans[idx], fine=True).items()}, final=True)
    t = getattr(batch, "t", None)
    return Motion(**num, verdict=_verdicts(num), static=static,
                  t=None if t is None else np.asarray(t), window=window, window_s=window * dts)


def _check_group(gyro, accel, mask, rate, idx, w: int, b: int, dts, spans, use_accel,  # noqa: C901
                 final=True, explain=None, trusted=None, read=None):
    """The numbers (float32), static mask, window length (samples) and whether a window
    was louder than :data:`LOUDER_CAP` allows, of devices ``idx``, all checked in windows
    of ``w`` samples and blocks of ``b`` windows. A device not ``final`` (per device: a
    first look in long windows, judged again where anything moved) is not sought for its
    stretches of rest. ``explain``: the window statistics of what a fitted model leaves
    (:func:`diffgyro._window_explain.explain_windows`, bound to the batch), by which the
    devices ``trusted`` (whose fit stands) are judged. ``read``: the group's window
    statistics where already read (:func:`check_ahead`)."""
    n = mask.shape[1]
    d = len(idx)
    lay = layout(d, int(max(spans.max(initial=0), 1)), w, b, use_accel)
    rows, k = lay.shape
    referenced = rate is not None
    q = noise_quantiles()
    stats, acc, todo, at = read or (*_read_group(gyro, accel, mask, rate, idx, lay), None, None)

    def judged(stats):
        return lay.check(*(None if x is None else tuple(jax.device_put(y) for y in x)
                           for x in (stats, acc)), w, b)

    recorded_stats = stats
    if explain is None:
        todo = np.zeros(rows, bool)
    elif todo is None:  # what the model leaves is judged, where a bias can hold the rate
        todo = _explained_rows(stats, d)
    if explain is not None:  # and where the fit stands
        todo = todo & np.r_[trusted, np.zeros(rows - d, bool)]
    if todo.any():
        left, noise = explain(_pad(idx, rows), w, stats[0], stats[3], stats[2], todo, q,
                              QUANTILE_WINDOWS, at=at)
        stats = (left, stats[1], stats[2], noise)
    window_s = w * np.asarray(dts, float)
    out = _numpy_out(judged(stats), d)
    moved = todo[:d] & (_verdicts(_with_resolution(out, window_s)) == IN_MOTION)
    if moved.any():  # a residual that moves where the recording rests: the model's, not a turn
        raw = _numpy_out(judged(recorded_stats), d)
        keep = moved & (_verdicts(_with_resolution(raw, window_s)) == AT_REST)
        for key, value in out.items():
            value[keep] = raw[key][keep]
        todo[:d] &= ~keep
    num = {k: out[k] for k in _NUMBERS if k != "resolution"}
    # the rate held at rest is the recording's (the residual's is about 0)
    recorded_rate = recorded_stats[0][:d, :, 0]
    if todo.any():
        num["rest_rate"][todo[:d]] = _held_rate(
            recorded_rate, out["window_valid"] & ~out["window_moving"])[todo[:d]]
    recorded = mask[idx]
    samples = min(k * w, n)

    def per_sample(flags):  # window flags (d, k) to the samples (d, n)
        full = np.zeros((flags.shape[0], n), bool)
        full[:, :samples] = np.repeat(flags, w, axis=1)[:, :samples]
        return full

    static = ~per_sample(out["window_near"]) & recorded
    num["turn_peak"] = num["turn_peak"] * window_s  # rate × windows to rad
    num["resolution"] = num["threshold"] * window_s
    # stretches of rest either side of a motion at rates no bias change explains: the
    # one at the rest's rate is rest, the others spin (the windows of the moving devices)
    # (with a rate reference the check reads what the reference does not explain: its
    # windows stand as the compiled check left them)
    refined = (np.flatnonzero((num["moving_fraction"] > 0) & np.broadcast_to(final, (d,)))
               if not referenced else [])
    for i in refined:
        acc = ({"accel": out["window_accel"][i], "accel_thr": out["accel_threshold"][i]}
               if "window_accel" in out else {})
        level = rest_stretches(*(out[k][i] for k in
                                  ("window_rate", "window_moving", "window_valid", "threshold_axes")),
                                window_s[i], **acc)
        if level is not None:
            moving, rate_i, turn, tilt = level
            num["tilt_peak"][i] = max(num["tilt_peak"][i], tilt)
            near = moving | np.r_[moving[1:], False] | np.r_[False, moving[:-1]]
            static[i] = ~per_sample(near[None])[0] & recorded[i]
            num["moving_fraction"][i] = (per_sample(moving[None])[0] & recorded[i]).sum() / max(
                recorded[i].sum(), 1)
            num["rate_peak"][i] = max(num["rate_peak"][i], rate_i)
            still = out["window_valid"][i] & ~moving
            if still.any():
                num["rest_rate"][i] = _held_rate(recorded_rate[i:i + 1], still[None])[0]
            num["turn_peak"][i] = max(num["turn_peak"][i], turn)
    return num, static, np.full(d, w), out["loud"]


def _read_group(gyro, accel, mask, rate, idx, lay: Layout) -> tuple:
    """The window statistics (:func:`~diffgyro._window_stats.window_stats`) of devices
    ``idx`` in ``lay``'s windows: the gyro's (less ``rate``), and the accelerometer's
    where ``lay`` reads it (else None)."""
    rows, k = lay.shape
    q = noise_quantiles()
    stats = window_stats(gyro, mask, lay.w, idx, k, q, QUANTILE_WINDOWS, rows, rate)
    acc = (window_stats(accel, mask, lay.w, idx, k, q, QUANTILE_WINDOWS, rows) if lay.accel
           else None)
    return stats, acc


def _pad(idx, rows: int):
    """Devices ``idx`` padded to a layout's ``rows`` (the last repeated): one shape."""
    return idx[np.minimum(np.arange(rows), len(idx) - 1)]


def _explained_rows(stats, d: int) -> Bool[np.ndarray, " r"]:
    """Rows of a layout (``stats``' leading axis, ``d`` devices then padding) judged by a
    fitted model's residual: those whose mean rate a bias can hold (:func:`_bias_like`)."""
    todo = np.zeros(stats[0].shape[0], bool)
    todo[:d] = _bias_like(stats[0][:d, :, 0], stats[2][:d])
    return todo


def _numpy_out(out: dict, d: int) -> dict:
    """A judgement's outputs on the host, its first ``d`` rows (numpy, writable: no
    program per shape)."""
    return {k: np.array(v)[:d] for k, v in out.items()}


def _with_resolution(out: dict, window_s) -> dict:
    """A judgement's numbers with the resolution (rad) the host forms for :func:`_verdicts`:
    the threshold times the window's length (s)."""
    return out | {"resolution": out["threshold"] * window_s}


def _bias_like(mean: Float[np.ndarray, "d k 3"], valid: Bool[np.ndarray, "d k"]
               ) -> Bool[np.ndarray, " d"]:
    """Devices whose mean rate over their valid windows a bias can hold (at most
    :data:`MAX_BIAS`): a fitted model's residual judges them. A rate beyond it is a spin,
    which a bias term would absorb: its recording is judged as it is."""
    return valid.any(axis=1) & (_held_rate(mean, valid) <= MAX_BIAS)


def _held_rate(mean: Float[np.ndarray, "d k 3"], use: Bool[np.ndarray, "d k"]
               ) -> Float[np.ndarray, " d"]:
    """The rate (norm) of the mean of each device's window means over its windows ``use``
    (0 where none; NaN elsewhere left out): one contraction, not a sum per window."""
    with np.errstate(invalid="ignore"):
        total = np.einsum("dk,dkc->dc", use.astype(mean.dtype), np.where(use[..., None], mean, 0.0))
        held = total / np.maximum(use.sum(axis=1), 1)[:, None]
    return np.sqrt(np.sum(held**2, axis=1)).astype(mean.dtype)


def check_ahead(batch, dt: float | None = None, reads: frozenset[str] | None = None
                ) -> Callable[[], dict]:
    """Start what :func:`motion_check` of ``batch`` needs before a fit's model: its program
    compiled (for the largest group of devices), the first look's window statistics read
    and, for a model that reads ``reads``, the half windows it is evaluated at
    (:func:`~diffgyro._window_explain.half_windows`), on threads of their own (XLA, the
    compiled pass and numpy hold no GIL), while the caller fits. Returns a function that
    waits and gives what was read, for ``motion_check(batch, dt, ahead=...)``.

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch` to judge.
    - ``dt``: the sampling interval, s (default: each device's own).
    - ``reads``: the signals the fitted model will read (its ``requires()``), whose
      residual judges the recording; None where none will.
    """
    mask = np.asarray(batch.mask)
    dts = _device_intervals(batch, dt)
    spans = _spans(mask)
    groups = _groups(dts, spans)
    _, use_accel = _reads(batch)
    lays = {key: layout(len(idx), int(max(spans[idx].max(initial=0), 1)), *key, use_accel)
            for key, idx in groups.items()}
    (w, b), idx = max(groups.items(), key=lambda kv: len(kv[1]))
    lay = lays[(w, b)]

    def spec(*shape, dtype=np.float32):
        return jax.ShapeDtypeStruct(shape, dtype)

    rows, k = lay.shape
    stats = (spec(rows, k, 3, 3), spec(rows, k), spec(rows, k, dtype=bool), spec(rows, 2, 3))
    compiled = lay.check.compile_ahead(stats, stats if lay.accel else None, w, b)
    out: dict = {}
    rate = None if batch.rate is None else np.asarray(batch.rate)
    accel = np.asarray(batch.accel) if use_accel else None

    def read():
        try:
            for key, idx in groups.items():
                stats, acc = _read_group(np.asarray(batch.gyro), accel, mask, rate, idx, lays[key])
                todo = at = None
                if reads is not None:
                    todo = _explained_rows(stats, len(idx))
                    rows = _pad(idx, lays[key].shape[0])
                    at = half_windows(batch, rows, key[0], stats[0], todo, reads) \
                        if todo.any() else None
                out[key] = (stats, acc, todo, at)
        except Exception:  # noqa: BLE001 - motion_check reads what is missing, and raises there
            pass

    thread = threading.Thread(target=read, name="diffgyro-motion-ahead", daemon=True)
    thread.start()

    def wait() -> dict:
        compiled.join()
        thread.join()
        return out

    return wait


__all__ = ["motion_check", "Motion", "rest_kept", "describe", "reason", "check_ahead",
           "window_sizes", "AT_REST", "IN_MOTION", "UNVERIFIED", "VERDICT_NAMES", "ACCEL_FLOOR",
           "EARTH_RATE", "K_SIGMA", "MAX_RESOLUTION", "MIN_PEAK_RATIO", "MIN_TILT", "MIN_WINDOWS"]
