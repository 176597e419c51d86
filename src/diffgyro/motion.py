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
one); the judgement on the windows likewise (:mod:`diffgyro._motion_windows`: numpy, or a
compiled loop over the devices where the pass was compiled), and where a recording moved, its stretches of rest are sought on the host
(:mod:`diffgyro._rest_stretches`). The rules' numbers are in
:mod:`diffgyro._motion_constants`. A long recording is first judged in longer windows (at most
:data:`MAX_WINDOWS`), and again in its rate's where anything moved or shook, or the long
windows cannot show a turn of :data:`MAX_RESOLUTION`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from concurrent.futures import Future

import numpy as np
from jaxtyping import Bool, Float

from ._jit import host_pool
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
from ._motion_result import (
    AT_REST,
    IN_MOTION,
    NUMBERS,
    UNVERIFIED,
    Motion,
    describe,
    reason,
    rest_kept,
    verdicts,
)
from ._motion_windows import Layout, layout
from ._rest_stretches import rest_stretches
from ._vocabulary import VERDICT_NAMES
from ._window_explain import Explanation, explain_windows, half_windows
from ._window_stats import window_stats


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
    out = np.full(mask.shape[0], mask.shape[1])
    if not mask.shape[1]:
        return out
    short = ~mask[:, -1]  # (most devices hold the batch's last sample: no search)
    if short.any():
        part = mask[short]
        last = mask.shape[1] - np.argmax(part[:, ::-1], axis=1)
        out[short] = np.where(part.any(axis=1), last, 0)
    return out


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
    read = ahead() if ahead is not None else {}
    # (the intervals and spans the first look was read in, where it was read ahead)
    dts, spans = read.get("intervals") or (_device_intervals(batch, dt), _spans(mask))
    num = {k: np.zeros(d, dtype) for k in NUMBERS}
    static = None  # (the first group's own mask where it holds every device, in order)
    window = np.zeros(d, np.int64)
    loud = np.zeros(d, bool)
    trusted = np.zeros(d, bool) if explain is None else np.asarray(explain.trusted, bool)
    if explain is not None:
        explain = functools.partial(explain_windows, batch, explain)

    def check(groups, final):
        nonlocal static
        for (w, b), idx in groups.items():
            pn, group_static, window[idx], loud[idx] = _check_group(
                gyro, accel, mask, rate, idx, w, b, dts[idx], spans[idx], use_accel,
                final=final | (w <= own[idx]), explain=explain, trusted=trusted[idx],
                read=None if final else read.get((w, b)))
            if static is None and len(idx) == d:  # (idx: sorted, so every device in order)
                static = group_static
            else:
                static = np.zeros((d, n), bool) if static is None else static
                static[idx] = group_static
            for k in NUMBERS:
                num[k][idx] = pn[k]

    rates, which = np.unique(dts, return_inverse=True)
    own = np.array([window_sizes(x)[0] for x in rates])[np.ravel(which)]
    check(_groups(dts, spans), final=False)
    # a long recording is judged first in long windows: where nothing moved in them, none
    # was shaken, and they show a turn of MAX_RESOLUTION, it was at rest. Where something
    # moved or shook, or the long windows cannot show a degree (a noisy gyro, or
    # correlated noise that averages slowly), it is judged again in the windows of its
    # rate: whether and how it moved, in the detail of its rate
    verdict = verdicts(num)
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
    static = np.zeros((d, n), bool) if static is None else static
    return Motion(**num, verdict=verdicts(num), static=static,
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
    stats, acc, todo, at, held = read or (*_read_group(gyro, accel, mask, rate, idx, lay), None,
                                          None, None)

    def judged(stats):
        return lay.check(stats, acc, w, b)

    recorded_stats = stats
    if explain is None:
        todo = np.zeros(rows, bool)
    elif todo is None:  # what the model leaves is judged, where a bias can hold the rate
        todo, held = _explained_rows(stats, d)
    if explain is not None:  # and where the fit stands
        todo = todo & np.r_[trusted, np.zeros(rows - d, bool)]
    if todo.any():
        left, noise = explain(_pad(idx, rows), w, stats[0], stats[3], stats[2], todo, q,
                              QUANTILE_WINDOWS, at=at)
        stats = (left, stats[1], stats[2], noise)
    window_s = w * np.asarray(dts, float)
    out = _numpy_out(judged(stats), d)
    moved = todo[:d] & (verdicts(_with_resolution(out, window_s)) == IN_MOTION)
    if moved.any():  # a residual that moves where the recording rests: the model's, not a turn
        raw = _numpy_out(judged(recorded_stats), d)
        keep = moved & (verdicts(_with_resolution(raw, window_s)) == AT_REST)
        for key, value in out.items():
            value = out[key] = np.array(value)  # (writable)
            value[keep] = raw[key][keep]
        todo[:d] &= ~keep
    num = {k: out[k] for k in NUMBERS if k != "resolution"}
    # the rate held at rest is the recording's (the residual's is about 0)
    recorded_rate = recorded_stats[0][:d, :, 0]
    if todo.any():
        _recorded_rest_rate(num["rest_rate"], np.flatnonzero(todo[:d]), held, out, recorded_rate)
    recorded = mask if len(idx) == len(mask) and (idx == np.arange(len(idx))).all() else mask[idx]
    samples = min(k * w, n)

    def per_sample(flags):  # window flags (d, k) to the samples (d, n)
        return _to_samples(flags, n, w, samples)

    static = per_sample(out["window_near"])
    np.greater(recorded, static, out=static)  # recorded and not near a move: one pass
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


def _recorded_rest_rate(rest_rate: Float[np.ndarray, " d"], rows, held: Float[np.ndarray, " d"],
                        out: dict, recorded: Float[np.ndarray, "d k 3"]) -> None:
    """The rest rate of devices ``rows`` judged by a model's residual (whose own is about 0):
    the recording's over the windows at rest, into ``rest_rate``. Where no window moved
    that is its rate ``held`` over the valid windows, as read; else it is formed again."""
    rest_rate[rows] = held[rows]
    moved = rows[out["window_moving"][rows].any(axis=1)]
    rest_rate[moved] = _held_rate(recorded[moved],
                                  (out["window_valid"] & ~out["window_moving"])[moved])


def _to_samples(flags: Bool[np.ndarray, "d k"], n: int, w: int, samples: int
                ) -> Bool[np.ndarray, "d n"]:
    """Window flags to the samples (``n`` per device, the first ``samples`` in windows of
    ``w``), by broadcasting in place."""
    full = np.zeros((flags.shape[0], n), bool)
    whole = samples // w
    full[:, :whole * w].reshape(-1, whole, w)[...] = flags[:, :whole, None]
    full[:, whole * w:samples] = flags[:, whole:whole + 1]
    return full


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


def _explained_rows(stats, d: int) -> tuple[Bool[np.ndarray, " r"], Float[np.ndarray, " d"]]:
    """Rows of a layout (``stats``' leading axis, ``d`` devices then padding) judged by a
    fitted model's residual: those whose mean rate a bias can hold (:func:`_bias_like`);
    and each device's rate held over its valid windows (:func:`_held_rate`)."""
    todo = np.zeros(stats[0].shape[0], bool)
    mean, valid = stats[0][:d, :, 0], stats[2][:d]
    held = _held_rate(mean, valid)
    todo[:d] = _bias_like(mean, valid, held)
    return todo, held


def _numpy_out(out: dict, d: int) -> dict:
    """A judgement's outputs on the host, its first ``d`` rows (numpy: no program per
    shape): the numbers per device writable copies, the windows' arrays read-only views
    where the backend allows (no copy of 10⁶ windows)."""
    return {k: (np.array(v) if np.ndim(v) < 2 else np.asarray(v))[:d] for k, v in out.items()}


def _with_resolution(out: dict, window_s) -> dict:
    """A judgement's numbers with the resolution (rad) the host forms for :func:`verdicts`:
    the threshold times the window's length (s)."""
    return out | {"resolution": out["threshold"] * window_s}


def _bias_like(mean: Float[np.ndarray, "d k 3"], valid: Bool[np.ndarray, "d k"],
               held: Float[np.ndarray, " d"] | None = None) -> Bool[np.ndarray, " d"]:
    """Devices whose mean rate over their valid windows (``held``, where already formed) a
    bias can hold (at most :data:`MAX_BIAS`): a fitted model's residual judges them. A rate
    beyond it is a spin, which a bias term would absorb: its recording is judged as it is."""
    held = _held_rate(mean, valid) if held is None else held
    return valid.any(axis=1) & (held <= MAX_BIAS)


def _held_rate(mean: Float[np.ndarray, "d k 3"], use: Bool[np.ndarray, "d k"]
               ) -> Float[np.ndarray, " d"]:
    """The rate (norm) of the mean of each device's window means over its windows ``use``
    (0 where none; NaN elsewhere left out): one contraction, not a sum per window."""
    picked = np.array(mean, order="C")  # (a copy of the strided means, the unused then
    picked[~use] = 0.0  # zeroed: np.where(use, mean, 0)'s numbers in one pass less)
    with np.errstate(invalid="ignore"):
        total = np.einsum("dk,dkc->dc", use.astype(mean.dtype), picked)
        held = total / np.maximum(use.sum(axis=1), 1)[:, None]
    return np.sqrt(np.sum(held**2, axis=1)).astype(mean.dtype)


def _ahead_groups(batch, dt: float | None = None
                  ) -> tuple[dict, dict, tuple[np.ndarray, np.ndarray]]:
    """The device groups of ``batch``'s check, their layouts, and the devices' sampling
    intervals and spans the groups were formed from."""
    mask = np.asarray(batch.mask)
    spans = _spans(mask)
    dts = _device_intervals(batch, dt)
    groups = _groups(dts, spans)
    _, use_accel = _reads(batch)
    lays = {key: layout(len(idx), int(max(spans[idx].max(initial=0), 1)), *key, use_accel)
            for key, idx in groups.items()}
    return groups, lays, (dts, spans)


def check_ahead(batch, dt: float | None = None, reads: frozenset[str] | None = None
                ) -> Callable[[], dict]:
    """Start what :func:`motion_check` of ``batch`` needs before a fit's model: the first
    look's window statistics read and, for a model that reads ``reads``, the half windows
    it is evaluated at (:func:`~diffgyro._window_explain.half_windows`), on a thread of its
    own (the compiled pass and numpy hold no GIL), while the caller fits. Returns a function that
    waits and gives what was read, for ``motion_check(batch, dt, ahead=...)``; its
    ``reading`` is a future done once the window statistics are read (other work may
    start after it, beside the half windows).

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch` to judge.
    - ``dt``: the sampling interval, s (default: each device's own).
    - ``reads``: the signals the fitted model will read (its ``requires()``), whose
      residual judges the recording; None where none will.
    """
    mask = np.asarray(batch.mask)
    groups, lays, intervals = _ahead_groups(batch, dt)
    _, use_accel = _reads(batch)
    out: dict = {"intervals": intervals}
    rate = None if batch.rate is None else np.asarray(batch.rate)
    accel = np.asarray(batch.accel) if use_accel else None

    read_done: Future = Future()  # (the window statistics read: the floor may start)

    def read():
        try:
            stats = {key: _read_group(np.asarray(batch.gyro), accel, mask, rate, idx, lays[key])
                     for key, idx in groups.items()}
            read_done.set_result(None)
            for key, idx in groups.items():
                todo = at = held = None
                if reads is not None:
                    todo, held = _explained_rows(stats[key][0], len(idx))
                    rows = _pad(idx, lays[key].shape[0])
                    at = half_windows(batch, rows, key[0], stats[key][0][0], todo, reads) \
                        if todo.any() else None
                out[key] = (*stats[key], todo, at, held)
        except Exception:  # noqa: BLE001 - motion_check reads what is missing, and raises there
            pass
        finally:
            if not read_done.done():
                read_done.set_result(None)

    whole = host_pool("motion-ahead", 1).submit(read)

    def wait() -> dict:
        whole.result()
        return out

    wait.reading = read_done  # type: ignore[attr-defined]
    return wait


__all__ = ["motion_check", "Motion", "rest_kept", "describe", "reason", "check_ahead",
           "window_sizes", "AT_REST", "IN_MOTION", "UNVERIFIED", "VERDICT_NAMES",
           "ACCEL_FLOOR", "EARTH_RATE", "K_SIGMA", "MAX_RESOLUTION", "MIN_PEAK_RATIO", "MIN_TILT",
           "MIN_WINDOWS"]
