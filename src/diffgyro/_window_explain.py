"""What a fitted model explains of a recording, at the motion check's windows.

A chamber's ramps and their kinks, or a fast thermal transient, change a bias faster than
the check's baseline (block medians) follows, and a recording at rest then shows windows
off the baseline. The fitted model follows them. The check judges what the model leaves
(its residual) from the window statistics it already holds: the model is evaluated at the
means of the samples over each half window (time, every signal it reads, and the gyro),
which gives the residual's window means and half-window differences. The local noise
(successive differences) stays the recording's: a model smooth over a window adds nothing
to it. The noise of a window mean is formed again from the residual's half-window
differences (a ramp inflates the recording's).

A model of the window means of its signals is the window mean of the model where it is
linear in them; otherwise they differ by its curvature times the signals' spread within a
window (for temperature over a window, far below any threshold). A model with state (a
lag, dT/dt) is evaluated at the half windows' spacing: in long windows that may leave a
transient unexplained, and such a recording is judged again in its rate's windows
(:func:`diffgyro.motion.motion_check`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from jaxtyping import Bool, Float, Int

from ._window_stats import compiled, spread_quantile, window_means, windowed_sums
from .data import Batch, aligned_empty


class Explanation(NamedTuple):
    """A fitted model, as the motion check reads it: ``residual`` maps (rows of the batch,
    a batch of those devices at their means over windows) to the model's residual there
    (rows, windows, 3); ``reads`` names the data signals it reads (``requires()``);
    ``trusted``, per device of the batch, whether its fit stands (status ``ok``): a fit
    that failed, or whose data could not support a term, explains nothing."""

    residual: Callable[[Int[np.ndarray, " r"], Batch], Float[np.ndarray, "r m 3"]]
    reads: frozenset[str]
    trusted: Bool[np.ndarray, " d"]


def windows(batch: Batch, rows: Int[np.ndarray, " r"], w: int, k: int,
            fill: Bool[np.ndarray, " r"], mean: Float[np.ndarray, "r k 3"],
            reads: frozenset[str]) -> Batch:
    """The devices ``rows`` of ``batch`` as the means of their valid samples over each of
    ``k`` windows of ``w`` samples: time, the signals in ``reads`` (a model's
    ``requires()``: ``temp``, ``accel``, ``aux:name`` ...) and the gyro (given: its
    windows' ``mean``). Only the devices ``fill`` are read; the others repeat the first
    one read (the shape stays the batch's, and a row not judged is still a well-formed
    recording). A window with no valid sample is masked and holds its neighbour's values."""
    n_dev, n = np.shape(batch.mask)
    m = min(n, k * w)
    read = np.asarray(rows)[fill]
    batch_mask = np.asarray(batch.mask)
    # (every sample of the batch valid, the usual case: no copy of the devices' masks; a
    # few devices of a large batch, a second look, read their own)
    every = ((2 * len(read) >= n_dev and bool(batch_mask[:, :m].all()))
             or bool(batch_mask[read, :m].all()))
    counts = (windowed_sums(batch_mask[read, :m], w, k) if not every else
              np.broadcast_to(windowed_sums(np.ones((1, m), bool), w, k), (len(read), k)))
    mask = np.zeros((len(rows), k), bool)
    mask[fill] = counts > 0
    spare, first = ~fill, int(np.argmax(fill))  # (rows not read repeat the first one read)
    mask[spare] = mask[first]

    def means(x):  # (d, n[, c]) -> (len(rows), k[, c]), neighbours' values where empty
        x = np.asarray(x)
        s = window_means(x, batch_mask, read, w, k)
        out = aligned_empty((len(rows),) + s.shape[1:], s.dtype)  # (the Batch keeps it)
        out[fill] = s
        out[spare] = s[0]
        return out

    def times(t):  # a window's time: its first sample's, plus half its span
        t = np.asarray(t)
        if not every or m < 2 * w:  # (with gaps, the mean of its valid samples' times)
            return means(t)
        out = aligned_empty((len(rows), k), t.dtype)
        out[...] = t[rows, :1]
        start = t[read, :m:w]
        step = np.diff(start, axis=1, append=2 * start[:, -1:] - start[:, -2:-1]) / w
        held = start.shape[1]  # (the windows past the samples hold the last one's time)
        out[fill, :held] = start + 0.5 * (w - 1) * step
        out[fill, held:] = out[fill, held - 1:held]
        out[spare] = out[first]
        return out

    kw = {f: None if getattr(batch, f) is None or f not in reads else
          means(getattr(batch, f)) for f in ("temp", "temp_ext", "accel", "mag")}
    return Batch(t=times(batch.t), gyro=np.asarray(mean, float), mask=mask, n_valid=mask.sum(axis=1),
                 devices=tuple(batch.devices[i] for i in rows) if batch.devices else (),
                 aux={a: means(v) for a, v in batch.aux.items() if f"aux:{a}" in reads}, **kw)


def half_windows(batch: Batch, rows: Int[np.ndarray, " r"], w: int,
                 stats: Float[np.ndarray, "r k 3 3"], todo: Bool[np.ndarray, " r"],
                 reads: frozenset[str]) -> Batch:
    """The devices ``rows`` of ``batch`` (in windows of ``w`` samples, their ``stats``) at
    the means of each half window (:func:`windows`), of the devices ``todo``: what a model
    reading ``reads`` is evaluated at. The gyro's half-window means are the window mean ±
    half the half-window difference. It needs no fitted model: a fit reads it beside its
    solve (:func:`diffgyro.motion.check_ahead`)."""
    r, k = stats.shape[:2]
    if compiled(r * k * w):
        from ._window_pass import compiled_halves

        return windows(batch, rows, w // 2, 2 * k, todo, compiled_halves(stats), reads)
    mean, half = stats[:, :, 0], 0.5 * stats[:, :, 2]
    gyro = aligned_empty((r, k, 2, 3), np.float64)
    np.add(mean, half, out=gyro[:, :, 0], dtype=float)
    np.subtract(mean, half, out=gyro[:, :, 1], dtype=float)
    return windows(batch, rows, w // 2, 2 * k, todo, gyro.reshape(r, 2 * k, 3), reads)


def explain_windows(batch: Batch, explanation: Explanation, rows: Int[np.ndarray, " r"], w: int,
                    stats: Float[np.ndarray, "r k 3 3"], noise: Float[np.ndarray, "r 2 3"],
                    valid: Bool[np.ndarray, "r k"], todo: Bool[np.ndarray, " r"],
                    quantiles: tuple[float, ...], limit: int, at: Batch | None = None
                    ) -> tuple[Float[np.ndarray, "r k 3 3"], Float[np.ndarray, "r 2 3"]]:
    """The window ``stats`` and rest ``noise`` of devices ``rows`` of ``batch`` (in windows
    of ``w`` samples) with those of the devices ``todo`` taken from what ``explanation``
    leaves at the means of each half window (``at``, :func:`half_windows` where not
    given; :func:`explained`)."""
    r, k = stats.shape[:2]
    if at is None:
        at = half_windows(batch, rows, w, stats, todo, explanation.reads)
    residual = np.asarray(explanation.residual(rows, at), float).reshape(r, k, 2, 3)
    return explained(stats, noise, valid, residual, todo, w, quantiles, limit)


def explained(stats: Float[np.ndarray, "r k 3 3"], noise: Float[np.ndarray, "r 2 3"],
              valid: Bool[np.ndarray, "r k"], residual: Float[np.ndarray, "r k 2 3"],
              rows: Bool[np.ndarray, " r"], w: int, quantiles: tuple[float, ...], limit: int
              ) -> tuple[Float[np.ndarray, "r k 3 3"], Float[np.ndarray, "r 2 3"]]:
    """Window ``stats`` and rest ``noise`` of the model's ``residual`` at the means of each
    window's two halves, for the devices ``rows`` (the others as given): the residual's
    window mean and half-window difference, the local noise as recorded, and a window
    mean's noise from those differences. A device whose residual is not finite keeps the
    recording's. A large batch (or any, once the compiled pass is loaded) is worked out in
    one compiled loop (:func:`diffgyro._window_pass.compiled_explained`), a small one by
    numpy here: the same numbers."""
    if compiled(stats.shape[0] * stats.shape[1] * w):
        from ._window_pass import compiled_explained

        return compiled_explained(stats, noise, valid, residual, rows, w, quantiles, limit)
    with np.errstate(invalid="ignore", over="ignore"):  # (a NaN or an infinity sums to one)
        finite = np.isfinite(residual.sum(axis=(2, 3)))
    ok = rows & np.all(finite | ~valid, axis=1)
    ok = slice(None) if ok.all() else ok  # (every row: views, not copies)
    stats, noise = stats.copy(), noise.copy()
    first, second = residual[ok, :, 0], residual[ok, :, 1]
    stats[ok, :, 0] = 0.5 * (first + second)
    stats[ok, :, 2] = first - second
    _, half_q, _, zh = quantiles
    sigma = noise[ok, 0].astype(float)
    half = spread_quantile(np.abs(stats[ok, :, 2]), valid[ok], half_q, limit)
    noise[ok, 1] = np.maximum(sigma / np.sqrt(w), half / zh / 2.0)
    return stats, noise


__all__ = ["Explanation", "explain_windows", "half_windows", "windows", "explained"]
