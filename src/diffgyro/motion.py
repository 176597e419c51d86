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
one); the
judgement on the windows is JAX, vmapped over chunks of devices and compiled once per
shape and window sizes. A long recording is first judged in longer windows (at most
:data:`MAX_WINDOWS`), and again in its rate's where anything moved or shook, or the long
windows cannot show a turn of :data:`MAX_RESOLUTION`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
import functools
import math
import threading
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, Int

from ._jit import filter_jit
from ._jsonio import number
from ._vocabulary import MAX_INTERVALS, VERDICT_NAMES
from ._window_explain import Explanation, explain_windows, half_windows
from ._window_stats import window_stats
from ._xla_options import FAST_COMPILE
from .data import device_bucket

#: Earth's rotation rate (rad/s): the gyro's floor on a window-mean deviation.
EARTH_RATE = 7.292115e-5
#: The accelerometer's floor on a window-mean deviation (m/s², about 0.2 mg).
ACCEL_FLOOR = 2e-3
#: Deviations of a window mean, in its own noise, above which the window moves.
K_SIGMA = 6.0
#: Quantile of the windows' local noise taken as the rest noise.
REST_QUANTILE = 0.1
#: Quantile of the windows' half-window differences that gives a window mean's rest noise.
HALF_QUANTILE = 0.2
#: Window length (s) and baseline block (s) aimed at.
WINDOW_S = 0.25
BLOCK_S = 30.0
#: Most windows per device in a first look: a long recording at rest is shown at rest in
#: longer windows (the work on the windows then stays below the pass over the samples);
#: one that moved, or whose longer windows cannot show a turn of :data:`MAX_RESOLUTION`,
#: is judged again in the windows of its rate (:func:`motion_check`).
MAX_WINDOWS = 512
#: A recording moved where a run of its moving windows reached this many times the
#: threshold (at any moving fraction), or gravity tilted by :data:`MIN_TILT` within a
#: stretch between moves. A slow unexplained change of the bias (a supply or duty step)
#: leaves the baseline by a few thresholds, and for long enough it adds up to a degree;
#: a turn by hand or vehicle leaves it by hundreds.
MIN_PEAK_RATIO = 10.0
MIN_TILT = math.radians(0.5)
#: The coarsest resolution (rad) at which a recording can be called at rest: a window at
#: the recording's rest noise must show a turn of this angle. A recording that cannot (too
#: noisy, too slowly sampled, or with no quiet part, whose own motion sets its noise) is
#: ``unverified``, never at rest.
MAX_RESOLUTION = math.radians(1.0)
#: Fewest valid windows a judgement needs (the rest noise is a quantile over them).
MIN_WINDOWS = 16
#: A window's noise may raise its threshold (vibration) at most this many times.
LOUDER_CAP = 8.0
#: Windows read for the rest noise's quantiles, and per baseline block for its median.
QUANTILE_WINDOWS = 512
BLOCK_WINDOWS = 16
#: Fastest change of a bias at rest (rad/s per s): a fast warm-up's (0.5 mrad/s/°C at
#: 0.1 °C/s). Two stretches of rest
#: either side of a motion whose rates differ by more than this allows (and their noise)
#: are not both rest: one of them spins (:func:`_rest_stretches`).
BIAS_SLEW = 5e-5
#: Gravity's change that a stretch of rest may not show (m/s²: a tilt of half a degree),
#: over chunks of this many windows (slow enough that a bias's thermal drift shows
#: nothing), and the fewest windows of a stretch of rest between two moves.
TILT_FLOOR = 9.80665 * math.sin(math.radians(0.5))
STRETCH_CHUNK = 32
MIN_STRETCH = 4
#: Levels held at least this share as long as the longest are candidates for the rest.
REST_SHARE = 0.5
#: The largest rate a gyro's bias reaches (rad/s, about 29 °/s: beyond the zero-rate
#: offsets that consumer MEMS datasheets allow); a level above it is a turn.
MAX_BIAS = 0.5

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


def _masked_quantile(x, valid, q: float, axis: int = 0):
    """The ``q`` quantile (linear between order statistics) of the ``valid`` entries of ``x``
    along ``axis``, NaN where none: for a few values (up to 16) a sorting network of
    elementwise min/max, else one integer sort (XLA on CPU sorts integers several times
    faster than floats, whose comparator must also order NaN)."""
    n = jnp.sum(valid, axis=axis, keepdims=True)
    h = q * (jnp.maximum(n, 1) - 1).astype(x.dtype)
    lo = jnp.floor(h).astype(jnp.int32)
    hi = jnp.minimum(lo + 1, jnp.maximum(n - 1, 0)).astype(jnp.int32)
    if x.shape[axis] <= 16:  # a few values (a baseline block): a sorting network
        col = list(jnp.moveaxis(jnp.where(valid, x, jnp.inf), axis, 0))
        for r in range(len(col)):  # odd-even transposition: len(col) rounds sort
            for j in range(r % 2, len(col) - 1, 2):
                col[j], col[j + 1] = jnp.minimum(col[j], col[j + 1]), jnp.maximum(col[j], col[j + 1])
        a = sum(jnp.where(lo == j, jnp.expand_dims(v, axis), 0.0) for j, v in enumerate(col))
        b = sum(jnp.where(hi == j, jnp.expand_dims(v, axis), 0.0) for j, v in enumerate(col))
    else:
        itype = jnp.int32 if x.dtype == jnp.float32 else jnp.int64
        top = jnp.iinfo(itype).max
        i = jax.lax.bitcast_convert_type(x, itype)
        key = jnp.where(i < 0, i ^ top, i)  # the float order as integers
        key = jnp.sort(jnp.where(valid, key, top), axis=axis)
        key = jnp.where(key < 0, key ^ top, key)
        s = jax.lax.bitcast_convert_type(key, x.dtype)
        a = jnp.take_along_axis(s, lo, axis=axis)
        b = jnp.take_along_axis(s, hi, axis=axis)
    out = jnp.where(n > 0, a + (b - a) * (h - lo), jnp.nan)
    return jnp.squeeze(out, axis)


def _spread(has, limit: int):
    """At most ``limit`` window indices spread evenly from the first window to the last one
    ``has`` (along its last axis): those the windows hold, not the padded batch's; and
    which of them lie in that span (all, unless it holds fewer windows)."""
    k = has.shape[-1]
    span = jnp.max(jnp.where(has, jnp.arange(k), -1), axis=-1, keepdims=True) + 1
    j = jnp.arange(limit)
    return jnp.where(span > limit, (j * span) // limit, j), j < span


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


def _baseline(mean, use, valid, b: int):
    """Slow baseline of the window means: the median over blocks of ``b`` windows of the
    windows in ``use`` (of the ``valid`` ones; at most :data:`BLOCK_WINDOWS` of them spread
    evenly over the block), linearly interpolated between block centres."""
    k = mean.shape[0]
    kb = -(-k // b)
    pad = kb * b - k
    vals = jnp.concatenate([mean, jnp.zeros((pad, mean.shape[1]), mean.dtype)])
    ok = jnp.concatenate([use, jnp.zeros((pad,), bool)])
    vals, ok = vals.reshape(kb, b, -1), ok.reshape(kb, b)
    if b > BLOCK_WINDOWS:  # spread over the windows each block holds (a last block may be short)
        pick, inside = _spread(jnp.concatenate([valid, jnp.zeros((pad,), bool)]).reshape(kb, b),
                               BLOCK_WINDOWS)
        vals = jnp.take_along_axis(vals, pick[..., None], axis=1)
        ok = jnp.take_along_axis(ok, pick, axis=1) & inside
    med = _masked_quantile(vals, jnp.broadcast_to(ok[..., None], vals.shape), 0.5, axis=1)  # (kb, c)
    # a block without windows in use (all moving) holds the last block before it that has
    # some (the first such block before any)
    has = ~jnp.isnan(med[:, 0])
    idx = jnp.arange(kb)
    last = jax.lax.cummax(jnp.where(has, idx, -1))
    first = jnp.argmax(has)
    med = med[jnp.where(last >= 0, last, first)]  # NaN only where no window is in use
    # past the recording's end (padding), the line through its last two blocks: the last
    # block's second half is then extrapolated as without the padding, so a device's
    # baseline does not depend on the length of the batch it is checked in
    data = jnp.any(jnp.concatenate([valid, jnp.zeros((pad,), bool)]).reshape(kb, b), axis=1)
    end = jnp.max(jnp.where(data, idx, 0))
    line = 2.0 * med[end] - med[jnp.maximum(end - 1, 0)]
    med = jnp.where((idx > end)[:, None], line[None, :], med)
    if kb == 1:
        return jnp.broadcast_to(med, mean.shape)
    # linear between block centres, and extrapolated from the nearest two at the ends
    # (a warm-up's drift is fastest in the first half block): window i of block B lies
    # between the centres of blocks j = B − 1 (first half) or B (second half), clipped;
    # the block values are spread over the windows by broadcasting, not gathered
    dtype = np.dtype(mean.dtype.name)
    pos = (np.arange(k).astype(dtype) + dtype.type(0.5)) / dtype.type(b) - dtype.type(0.5)
    j = np.clip(np.floor(pos).astype(np.int32), 0, kb - 2)
    frac = jnp.asarray((pos - j.astype(dtype))[:, None])
    blocks = np.arange(kb)
    second = (np.arange(b) >= b // 2)[None, :, None]

    def spread(jb_first, jb_second):  # med[j] per window, j per block and half
        v = jnp.where(second, med[jb_second][:, None, :], med[jb_first][:, None, :])
        return v.reshape(kb * b, -1)[:k]

    first_j, second_j = np.clip(blocks - 1, 0, kb - 2), np.clip(blocks, 0, kb - 2)
    lo, hi = spread(first_j, second_j), spread(first_j + 1, second_j + 1)
    return lo + frac * (hi - lo)


def _run_start(flag):
    """Per window, the index of the last window at or before it that is not ``flag`` (−1
    where none): the window before the run of ``flag`` it belongs to."""
    idx = jnp.arange(flag.shape[0])
    return jax.lax.cummax(jnp.where(flag, -1, idx))


def _runs_with(flag, mark):
    """``flag`` with every run of True that holds no ``mark`` cleared (running maxima
    forwards and minima backwards: no scatter, no sort)."""
    k = flag.shape[0]
    idx = jnp.arange(k)
    ahead = jax.lax.cummax(jnp.where(flag & mark, idx, -1)) > _run_start(flag)
    end = jax.lax.cummin(jnp.where(flag, k, idx), reverse=True)
    behind = jax.lax.cummin(jnp.where(flag & mark, idx, k), reverse=True) < end
    return flag & (ahead | behind)


class _Windows(NamedTuple):
    """One signal's windows as the judgement reads them: means and validity, the rest noise
    and threshold per axis, the variance a window mean has at rest (raised by its own
    noise), the jumps between neighbouring windows, and the floor."""

    mean: Float[jax.Array, "k 3"]
    valid: Bool[jax.Array, " k"]
    sigma: Float[jax.Array, " 3"]
    threshold: Float[jax.Array, " 3"]
    var: Float[jax.Array, "k 3"]
    jump: Bool[jax.Array, " k"]
    loud: Bool[jax.Array, ""]
    floor: float


def _windows(stats, w: int, floor: float) -> _Windows:
    """A signal's :class:`_Windows` from its window statistics (:mod:`diffgyro._window_stats`)."""
    wins, c, valid, noise = stats
    mean, local = wins[:, 0], wins[:, 1]
    sigma, mean_noise = noise[0], noise[1]
    sigma = jnp.where(jnp.isnan(sigma), 0.0, sigma)
    mean_noise = jnp.where(jnp.isnan(mean_noise), 0.0, mean_noise)
    thr0 = jnp.maximum(K_SIGMA * mean_noise, floor)
    # vibration raises the local noise, and with it what a window mean may scatter; but a
    # window may not hide a turn of more than the resolution a window at rest noise has
    # (motion raises the local noise of a slowly sampled recording too)
    louder = jnp.clip(local / jnp.where(sigma > 0, sigma, jnp.inf)[None, :], 1.0, LOUDER_CAP)
    var = (mean_noise[None, :] * louder) ** 2 * (w / jnp.maximum(c, 1.0))[:, None]
    prev = jnp.concatenate([mean[:1], mean[:-1]])
    ok = valid & jnp.concatenate([jnp.zeros((1,), bool), valid[:-1]])
    var_prev = jnp.concatenate([var[:1], var[:-1]])
    jump = _flag(mean - prev, var + var_prev, ok, floor)  # a change between neighbours
    # a window louder than the cap allows: shaken or knocked, though its mean may not show it
    loud = jnp.any(valid[:, None] & (local > LOUDER_CAP * sigma[None, :]))
    return _Windows(mean, valid, sigma, thr0, var, jump, loud, floor)


def _flag(dev, var, ok, floor: float):
    """Windows whose deviation ``dev`` stands out of the noise ``var`` its mean can have."""
    thr = jnp.maximum(K_SIGMA * jnp.sqrt(var), floor)
    z = jnp.sqrt(jnp.sum((dev / thr) ** 2, axis=1))
    return (z > 1.0) & ok


def _first_pass(win: _Windows, b: int):
    """The deviation of each window from the baseline of all valid windows, and the windows
    that leave it (before the rule on runs)."""
    dev = win.mean - _baseline(win.mean, win.valid, win.valid, b)
    dev = jnp.where(jnp.isnan(dev), 0.0, dev)
    return dev, _flag(dev, win.var, win.valid, win.floor)


def _runs(win: _Windows, dev, flags, b: int):
    """The moving windows and their deviations, where some window left the first pass's
    baseline: a run of such windows is motion when it starts or holds a jump (a turn
    starts within a window or two; thermal drift creeps). Then again, with the baseline
    of the windows the first pass left static."""
    jump = win.jump | jnp.concatenate([win.jump[1:], jnp.zeros((1,), bool)])
    moving = _runs_with(flags, jump)
    again = win.mean - _baseline(win.mean, win.valid & ~moving, win.valid, b)
    # where the first pass left no window static, its own baseline stands
    dev = jnp.where(jnp.isnan(again), dev, again)
    return _runs_with(_flag(dev, win.var, win.valid, win.floor), jump), dev


def _turned(moving, dev):
    """The largest angle turned within one run of moving windows (in window-mean rate ×
    windows; the host scales it by the window's length): the rate less the baseline,
    summed from the run's start."""
    turned = jnp.cumsum(jnp.where(moving[:, None], dev, 0.0), axis=0)
    before = _run_start(moving)
    turned = turned - jnp.where(before[:, None] >= 0, turned[jnp.maximum(before, 0)], 0.0)
    return jnp.max(jnp.where(moving, jnp.sqrt(jnp.sum(turned**2, axis=1)), 0.0))


def _tilted(accel, valid, moving, thr):
    """Windows whose specific force leaves the mean of its chunk of :data:`STRETCH_CHUNK`
    windows by more than a tilt of :data:`TILT_FLOOR` (or the accelerometer's threshold),
    in chunks where nothing else moved (a chunk with a move in it is left to
    :func:`_rest_stretches`, which splits it there), and the largest such tilt (rad)."""
    k = accel.shape[0]
    c = STRETCH_CHUNK
    kc = -(-k // c)
    pad = kc * c - k
    a = jnp.concatenate([accel, jnp.zeros((pad, 3), accel.dtype)]).reshape(kc, c, 3)
    use = jnp.concatenate([valid & ~moving, jnp.zeros((pad,), bool)]).reshape(kc, c)
    still = ~jnp.any(jnp.concatenate([moving, jnp.zeros((pad,), bool)]).reshape(kc, c), axis=1)
    count = jnp.sum(use, axis=1)
    mean = jnp.sum(jnp.where(use[..., None], a, 0.0), axis=1) / jnp.maximum(count, 1)[:, None]
    off = jnp.sqrt(jnp.sum((a - mean[:, None, :]) ** 2, axis=2))
    floor = jnp.maximum(TILT_FLOOR, jnp.sqrt(jnp.sum(thr**2)))
    flag = use & (still & (count >= c // 2))[:, None] & (off > floor)
    g = jnp.maximum(jnp.sqrt(jnp.sum(mean**2, axis=1)), 1e-9)[:, None]
    tilt = jnp.max(jnp.where(flag, jnp.arcsin(jnp.minimum(off / g, 1.0)), 0.0))
    return flag.reshape(-1)[:k], tilt


def _chunk(gyro, accel, w: int, b: int):
    """The judgement of a chunk of devices (leading axis) from their window statistics
    (gyro, and accelerometer or None): the numbers, and per window the flags and means
    the host reads. The rule on runs, and the angle turned, are worked out only in a chunk
    where some window moved (at rest, nothing does)."""
    each = jax.vmap
    win = each(lambda st: _windows(st, w, 2.0 * EARTH_RATE))(gyro)
    dev, flags = each(lambda v: _first_pass(v, b))(win)
    moving, dev = jax.lax.cond(jnp.any(flags), each(lambda v, d, f: _runs(v, d, f, b)),
                               lambda v, d, f: (jnp.zeros_like(f), d), win, dev, flags)
    out = dict(window_rate=win.mean, window_valid=win.valid, threshold_axes=win.threshold)
    tilt = jnp.zeros(moving.shape[:1], jnp.float32)
    if accel is not None:
        acc = each(lambda st: _windows(st, w, ACCEL_FLOOR))(accel)
        moving = moving | acc.jump
        tilted, tilt = each(_tilted)(acc.mean, win.valid, moving, acc.threshold)
        moving = moving | tilted
        out |= dict(window_accel=acc.mean, accel_threshold=acc.threshold)
    turn = jax.lax.cond(jnp.any(moving), each(_turned),
                        lambda m, d: jnp.zeros(m.shape[:1], d.dtype), moving, dev)
    return out | each(_numbers)(win, moving, dev, turn, tilt, gyro[1]) | dict(window_moving=moving)


def _numbers(win: _Windows, moving, dev, turn, tilt, count):
    """One device's numbers (:data:`_NUMBERS`, but the resolution the host forms) and its
    windows not at rest (moving, or next to a moving one: the transitions)."""
    rate = jnp.sqrt(jnp.sum(dev**2, axis=1))
    n_mov = jnp.sum(moving)
    peak = jnp.max(jnp.where(moving, rate, 0.0))
    rms = jnp.sqrt(jnp.sum(jnp.where(moving, rate**2, 0.0)) / jnp.maximum(n_mov, 1))
    near = moving | jnp.concatenate([moving[1:], jnp.zeros((1,), bool)]) | jnp.concatenate(
        [jnp.zeros((1,), bool), moving[:-1]])
    still = win.valid & ~moving
    rest_rate = jnp.sqrt(jnp.sum((jnp.sum(jnp.where(still[:, None], win.mean, 0.0), axis=0)
                                  / jnp.maximum(jnp.sum(still), 1)) ** 2))
    some = jnp.any(win.valid)
    frac = jnp.where(some, jnp.sum(jnp.where(moving, count, 0.0))
                     / jnp.maximum(jnp.sum(count), 1.0), jnp.nan)
    nan = jnp.asarray(jnp.nan, jnp.float32)
    return dict(moving_fraction=frac, rate_peak=jnp.where(some, peak, nan),
                rate_rms=jnp.where(some, rms, nan), turn_peak=jnp.where(some, turn, nan),
                tilt_peak=jnp.where(some, tilt, nan), rest_rate=jnp.where(some, rest_rate, nan),
                rest_noise=jnp.where(some, jnp.sqrt(jnp.mean(win.sigma**2)), nan),
                threshold=jnp.where(some, jnp.sqrt(jnp.mean(win.threshold**2)), nan),
                n_windows=jnp.sum(win.valid).astype(jnp.float32), window_near=near, loud=win.loud)


def _vmapped(gyro, accel, w: int, b: int):
    """The check of every device from its window statistics (devices first, a multiple of
    :data:`CHECK_CHUNK` or fewer): chunk by chunk."""
    d = gyro[0].shape[0]
    if d <= CHECK_CHUNK:
        return _chunk(gyro, accel, w, b)

    def split(x):
        return None if x is None else jax.tree.map(
            lambda y: y.reshape((d // CHECK_CHUNK, CHECK_CHUNK) + y.shape[1:]), x)

    out = jax.lax.map(lambda ga: _chunk(*ga, w, b), (split(gyro), split(accel)))
    return jax.tree.map(lambda y: y.reshape((d,) + y.shape[2:]), out)


#: Devices checked side by side (vmapped) in one step of the compiled loop over a batch's
#: devices: on a 2-core CPU the window statistics with their consumers run about twice as
#: fast in chunks of 8 as vmapped over a batch of 1000.
CHECK_CHUNK = 8


#: The check of a large batch, and of a small (padded) one: a small batch's check runs in
#: milliseconds, and compiles in about 60 % of the time with XLA's loop emitters.
_check = filter_jit(_vmapped)
_check_small = filter_jit(_vmapped, compiler_options=FAST_COMPILE)


class _Layout(NamedTuple):
    """How a group of devices is checked: window and block sizes, the shape of its window
    sums (devices, windows; padded for a small batch) and whether the accelerometer is
    read."""

    w: int
    b: int
    shape: tuple[int, int]
    accel: bool
    padded: bool

    @property
    def check(self):
        return _check_small if self.padded else _check


def _layout(devices: int, samples: int, w: int, b: int, accel: bool) -> _Layout:
    """The layout of ``devices`` holding up to ``samples`` samples each, in windows of
    ``w`` samples and blocks of ``b`` windows."""
    k = -(-samples // w)
    if devices * samples > PAD_SAMPLES:  # devices in whole chunks
        rows = devices if devices <= CHECK_CHUNK else -(-devices // CHECK_CHUNK) * CHECK_CHUNK
        return _Layout(w, b, (rows, k), accel, False)
    # small batches share a compiled check: devices to a bucket, windows to a power of
    # two of blocks
    blocks = 1 << (-(-k // b) - 1).bit_length()
    rows = device_bucket(devices, minimum=1)
    rows = rows if rows <= CHECK_CHUNK else -(-rows // CHECK_CHUNK) * CHECK_CHUNK
    return _Layout(w, b, (rows, blocks * b), accel, True)


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
    lay = _layout(d, int(max(spans.max(initial=0), 1)), w, b, use_accel)
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
    out = _numpy_out(judged(stats), d)
    moved = todo[:d] & (_verdicts(_with_resolution(out, w, dts)) == IN_MOTION)
    if moved.any():  # a residual that moves where the recording rests: the model's, not a turn
        raw = _numpy_out(judged(recorded_stats), d)
        keep = moved & (_verdicts(_with_resolution(raw, w, dts)) == AT_REST)
        for key, value in out.items():
            value[keep] = raw[key][keep]
        todo[:d] &= ~keep
    num = {k: out[k] for k in _NUMBERS if k != "resolution"}
    if todo.any():  # the rate held at rest is the recording's (the residual's is about 0)
        num["rest_rate"][todo[:d]] = _rest_rate(recorded_stats[0][:d, :, 0], out["window_valid"],
                                                out["window_moving"])[todo[:d]]
    recorded = mask[idx]
    samples = min(k * w, n)

    def per_sample(flags):  # window flags (d, k) to the samples (d, n)
        full = np.zeros((flags.shape[0], n), bool)
        full[:, :samples] = np.repeat(flags, w, axis=1)[:, :samples]
        return full

    static = ~per_sample(out["window_near"]) & recorded
    window_s = w * np.asarray(dts, float)
    num["turn_peak"] = num["turn_peak"] * window_s  # rate × windows to rad
    num["resolution"] = num["threshold"] * window_s
    # stretches of rest either side of a motion at rates no bias change explains: the
    # one at the rest's rate is rest, the others spin (the windows of the moving devices)
    # (with a rate reference the check reads what the reference does not explain: its
    # windows stand as the compiled check left them)
    refined = (np.flatnonzero((num["moving_fraction"] > 0) & np.broadcast_to(final, (d,)))
               if not referenced else [])
    win = out
    for i in refined:
        acc = ({"accel": win["window_accel"][i], "accel_thr": win["accel_threshold"][i]}
               if "window_accel" in win else {})
        level = _rest_stretches(*(win[k][i] for k in
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
            still = win["window_valid"][i] & ~moving
            if still.any():
                num["rest_rate"][i] = np.linalg.norm(win["window_rate"][i][still].mean(axis=0))
            num["turn_peak"][i] = max(num["turn_peak"][i], turn)
    return num, static, np.full(d, w), out["loud"]


def _read_group(gyro, accel, mask, rate, idx, lay: _Layout) -> tuple:
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


def _with_resolution(out: dict, w: int, dts) -> dict:
    """A judgement's numbers with the resolution (rad) the host forms for :func:`_verdicts`."""
    return out | {"resolution": out["threshold"] * w * np.asarray(dts, float)}


def _bias_like(mean: Float[np.ndarray, "d k 3"], valid: Bool[np.ndarray, "d k"]
               ) -> Bool[np.ndarray, " d"]:
    """Devices whose mean rate over their valid windows a bias can hold (at most
    :data:`MAX_BIAS`): a fitted model's residual judges them. A rate beyond it is a spin,
    which a bias term would absorb: its recording is judged as it is."""
    count = valid.sum(axis=1)
    with np.errstate(invalid="ignore"):
        held = np.where(valid[..., None], mean, 0.0).sum(axis=1) / np.maximum(count, 1)[:, None]
        return (count > 0) & (np.sqrt(np.sum(held**2, axis=1)) <= MAX_BIAS)


def _rest_rate(mean: Float[np.ndarray, "d k 3"], valid: Bool[np.ndarray, "d k"],
               moving: Bool[np.ndarray, "d k"]) -> Float[np.ndarray, " d"]:
    """The rate (norm) of the mean of each device's valid windows that did not move."""
    still = valid & ~moving
    with np.errstate(invalid="ignore"):
        held = (np.where(still[..., None], mean, 0.0).sum(axis=1)
                / np.maximum(still.sum(axis=1), 1)[:, None])
    return np.sqrt(np.sum(held**2, axis=1)).astype(mean.dtype)


def _rest_stretches(rate, moving, valid, thr, window_s: float, accel=None, accel_thr=None):
    """The stretches of one device's recording that are rest, where it moved (its windows:
    mean rate (k, 3), moving, valid, the threshold per axis; the accelerometer's window
    means and threshold where read).

    Between its moves a device held by hand or turned slowly is not at rest, and neither
    is one that spins steadily:

    * at rest, gravity holds still: a window whose specific force leaves the mean of
      its stretch (over :data:`STRETCH_CHUNK` windows) by more than :data:`TILT_FLOOR`
      (a tilt of half a degree) or the accelerometer's threshold moved;
    * a stretch shorter than :data:`MIN_STRETCH` windows between moves is no rest;
    * gravity that turned across a move (the stretches either side at rest in poses
      apart by more than :data:`TILT_FLOOR`) shows the move turned the device: a tilt;
    * a bias does not step while the device turns: it drifts by at most
      :data:`BIAS_SLEW` (and the window noise, the threshold). Stretches that agree, end
      to start, are one level. The rest is the level the device held longest, or, of the
      levels held at least :data:`REST_SHARE` as long, the one nearest to zero rate (a
      bias is small beside a spin), among the levels a bias can have (:data:`MAX_BIAS`);
      the other levels spin.

    Returns None where the check's own windows stand; else the windows moving, the
    largest rate of a spin against the rest's, the largest angle one turned and the
    largest tilt of gravity (rad)."""
    given = moving
    moving = moving.copy()
    k = moving.size
    thr = np.maximum(np.asarray(thr, float), 2.0 * EARTH_RATE)

    def stretches():
        static = valid & ~moving
        edges = np.flatnonzero(np.diff(np.r_[0, static.astype(np.int8), 0]))
        return list(zip(edges[::2], edges[1::2]))

    runs = stretches()
    tilt = 0.0
    if accel is not None:
        floor = max(TILT_FLOOR, float(np.linalg.norm(accel_thr)))
        g = max(float(np.median(np.linalg.norm(accel[valid], axis=1))), 1e-9) if valid.any() else 1.0
        # chunks of STRETCH_CHUNK windows from each stretch's start (a short last chunk
        # joins its neighbour), their means by one reduction over the stretches' windows
        chunks = []
        for start, end in runs:
            cut = list(range(start, end, STRETCH_CHUNK))
            if len(cut) > 1 and end - cut[-1] < STRETCH_CHUNK // 2:
                cut.pop()
            chunks += list(zip(cut, cut[1:] + [end]))
        if chunks:
            starts, ends = (np.asarray(x) for x in zip(*chunks))
            idx = np.concatenate([np.arange(a, b) for a, b in zip(starts, ends)])
            size = ends - starts
            mean = np.add.reduceat(accel[idx], np.r_[0, np.cumsum(size)[:-1]], axis=0) / size[:, None]
            off = np.linalg.norm(accel[idx] - np.repeat(mean, size, axis=0), axis=1)
            over = off > floor
            moving[idx[over]] = True
            if over.any():
                tilt = max(tilt, math.asin(min(float(off[over].max()) / g, 1.0)))
    runs = stretches()
    for start, end in runs:
        if end - start < MIN_STRETCH and (start > 0 or end < k):
            moving[start:end] = True
    runs = [r for r in stretches() if r[1] - r[0] >= MIN_STRETCH]
    if accel is not None:  # gravity turned across a move: the gyro's run was a turn
        for (a0, a1), (b0, b1) in zip(runs, runs[1:]):
            before = np.median(accel[max(a0, a1 - BLOCK_WINDOWS):a1], axis=0)
            after = np.median(accel[b0:min(b1, b0 + BLOCK_WINDOWS)], axis=0)
            if np.linalg.norm(after - before) > floor:
                cos = before @ after / max(np.linalg.norm(before) * np.linalg.norm(after), 1e-12)
                tilt = max(tilt, math.acos(min(max(cos, -1.0), 1.0)))
    clusters = _levels(rate, runs, thr, window_s)
    if len(clusters) < 2:
        return None if np.array_equal(moving, given) and not tilt else (moving, 0.0, 0.0, tilt)
    # a rate beyond any gyro's bias is no rest (unless every level is: an output in counts
    # with its offset, or a rate about a logged reference)
    small = [c for c in clusters if np.linalg.norm(c["level"]) <= MAX_BIAS] or clusters
    most = max(c["windows"] for c in small)
    rest = min((c for c in small if c["windows"] >= REST_SHARE * most),
               key=lambda c: float(np.linalg.norm(c["level"])))
    peak = turn = 0.0
    for c in clusters:
        if np.sqrt(np.sum(((c["level"] - rest["level"]) / thr) ** 2)) <= 1.0:
            continue  # at the rest's level (a level split only by the drift allowed)
        off = float(np.linalg.norm(c["level"] - rest["level"]))
        for a, b in c["runs"]:
            moving[a:b] = True
            peak, turn = max(peak, off), max(turn, off * (b - a) * window_s)
    return moving, peak, turn, tilt


def _levels(rate, runs, thr, window_s: float) -> list[dict]:
    """The stretches ``runs`` grouped by the rate they hold: a stretch joins the level
    whose last stretch ends at its rate (within the noise of medians of a few windows and
    :data:`BIAS_SLEW` over the gap), else starts one. Each level: its stretches, windows
    and median rate."""
    clusters: list[dict] = []
    for start, end in runs:
        span = min(BLOCK_WINDOWS, end - start)
        head = np.median(rate[start:start + span], axis=0)
        best, dist = None, 1.0
        for c in clusters:
            gap = min((start - c["end"] + span) * window_s, BLOCK_S)
            # medians of a few windows each: their difference's noise is below a window's
            tol = thr * min(1.0, 1.25 * math.sqrt(2.0 / min(span, c["span"]))) + BIAS_SLEW * gap
            z = float(np.sqrt(np.sum(((head - c["tail"]) / tol) ** 2)))
            if z <= dist:
                best, dist = c, z
        if best is None:
            best = {"runs": [], "windows": 0}
            clusters.append(best)
        best["runs"].append((start, end))
        best["windows"] += end - start
        best["end"], best["span"] = end, span
        best["tail"] = np.median(rate[end - span:end], axis=0)
    for c in clusters:
        c["level"] = np.median(np.concatenate([rate[a:b] for a, b in c["runs"]]), axis=0)
    return clusters


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
    lays = {key: _layout(len(idx), int(max(spans[idx].max(initial=0), 1)), *key, use_accel)
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


#: Groups of at most this many samples (devices × samples) are checked at a bucketed
#: shape (devices to :func:`~diffgyro.data.device_bucket`, windows to a power of two of
#: baseline blocks), so that batches of nearby sizes share one program.
PAD_SAMPLES = 1 << 21


__all__ = ["motion_check", "Motion", "rest_kept", "describe", "reason", "check_ahead",
           "window_sizes", "AT_REST", "IN_MOTION", "UNVERIFIED", "VERDICT_NAMES", "ACCEL_FLOOR",
           "EARTH_RATE", "K_SIGMA", "MAX_RESOLUTION", "MIN_PEAK_RATIO", "MIN_TILT", "MIN_WINDOWS"]
