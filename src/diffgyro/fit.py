"""fit(model, batch): calibrate every device of a batch at once.

Linear models take the closed-form path: weighted normal equations of the
per-axis design, columns scaled to unit norm, a rank check on the scaled
Gram matrix (never silent truncation) and a Cholesky solve through lineax.
Models with time constants (thermal lag, warm-up) use variable projection:
the linear coefficients are solved in closed form for given time constants
and optimistix's Levenberg–Marquardt moves the time constants alone,
started from the best point of a coarse grid. Held-out error refits every
fold of interleaved time blocks. Each device gets its own status, so one bad
device never sinks the batch.
"""

from __future__ import annotations

import dataclasses
import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from . import _aux as aux_cols
from . import _noise as noise
from ._fit_sums import solve_sums
from ._folds import fold_ids
from ._jit import TRACE_COUNTS, release_compiled_if_crowded
from ._jsonio import number
from ._linalg import normal_equations, rank_check, solve_normal, solve_normal_inner
from ._options import FitOptions
from ._signal_builder import batch_signals
from .channel import as_channel, check_channel, check_model
from .data import Batch, Recording, as_batch, pad_devices
from .effects import noise_fit
from .errors import DataError, SpecError
from .model import ErrorModel, Params
from .motion import PAD_SAMPLES, Motion, compile_check, motion_check, rest_kept
from .signals import Signals, TempNorm
from .status import (
    IN_MOTION,
    OK,
    REST_UNVERIFIED,
    STATUS_NAMES,
    collinear_terms,
    explain,
    fit_status,
    min_samples,
    residual_verdict,
)

__all__ = ["fit", "FitResult", "FitOptions", "judge_motion", "solve_device", "batch_signals",
           "device_noise_floor", "masked_median"]

# --------------------------------------------------------------------------- one device


def project_linear(model: ErrorModel, sig: Signals, y, w, theta):
    """Linear coefficients for given nonlinear parameters, and the design."""
    x = model.design(sig, theta)
    a, c = normal_equations(x, y, w)
    return solve_normal_inner(a, c), x


def varpro(model: ErrorModel, sig: Signals, y, w, theta0, opts: FitOptions, max_steps: int):
    """Levenberg–Marquardt over the time constants with the linear part projected out."""
    sw = jnp.sqrt(w)[:, None]

    def residual(theta, _):
        beta, x = project_linear(model, sig, y, w, theta)
        return (y - jnp.einsum("nip,ip->ni", x, beta)) * sw

    solver = optx.LevenbergMarquardt(rtol=opts.rtol, atol=opts.atol)
    sol = optx.least_squares(residual, solver, theta0, max_steps=max_steps, throw=False)
    return sol.value, lm_converged(sol), sol.stats["num_steps"]


#: Rejected Levenberg–Marquardt steps in a row after which the solution is a minimum to
#: rounding: each rejection shrinks the trust region fourfold (optimistix's classical
#: trust region), so no step down to 4⁻¹⁰ ≈ 1e-6 of the last accepted one lowered the cost.
STALLED_STEPS = 10


def lm_converged(sol) -> Array:
    """Whether an optimistix Levenberg–Marquardt solve converged: its tolerance met, or
    stalled at a minimum, every step of the last :data:`STALLED_STEPS` rejected. The
    tolerance compares every residual's change with its size; near the minimum that change
    is rounding, and whether it falls under the tolerance before the steps run out rests on
    the last bits of the arithmetic. A stall at a point worse than the start grid is still
    caught by :func:`solve_device`'s comparison with the grid."""
    stalled = sol.state.num_steps_since_acceptance >= STALLED_STEPS
    return (sol.result == optx.RESULTS.successful) | stalled


def _full_lm(model: ErrorModel, sig: Signals, y, w, theta0, opts: FitOptions):
    """Levenberg–Marquardt over every parameter at once (no projection).

    The reference path: for linear models it must agree with the closed form.
    """
    sw = jnp.sqrt(w)[:, None]

    def residual(params, _):
        beta, theta = params
        return (y - jnp.einsum("nip,ip->ni", model.design(sig, theta), beta)) * sw

    beta0 = jnp.zeros((3, model.n_params), y.dtype)
    solver = optx.LevenbergMarquardt(rtol=opts.rtol, atol=opts.atol)
    sol = optx.least_squares(residual, solver, (beta0, theta0), max_steps=opts.max_steps,
                             throw=False)
    beta, theta = sol.value
    return beta, theta, lm_converged(sol), sol.stats["num_steps"]


def _grid_start(model: ErrorModel, sig: Signals, y, w):
    """Best point of the coarse grid of time constants, and its cost."""
    grid = model.nonlinear_grid(sig)

    def cost(theta):
        beta, x = project_linear(model, sig, y, w, theta)
        r = y - jnp.einsum("nip,ip->ni", x, beta)
        return jnp.sum(w[:, None] * r * r)

    costs = jax.vmap(cost)(grid)
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    best = jnp.argmin(costs)
    return grid[best], costs[best]


def _sort_key(x):
    """Float bits as integers of the same order. XLA on CPU sorts integers ~5× faster
    than floats, whose comparator must also order NaN."""
    itype = jnp.int64 if x.dtype == jnp.float64 else jnp.int32
    i = jax.lax.bitcast_convert_type(x, itype)
    return jnp.where(i < 0, i ^ jnp.iinfo(itype).max, i)


def _sorted_valid(x, valid):
    """Valid (non-NaN) entries sorted to the front of the last axis, and their count."""
    valid = valid & ~jnp.isnan(x)
    key = _sort_key(x)
    key = jnp.sort(jnp.where(valid, key, jnp.iinfo(key.dtype).max), axis=-1)
    key = jnp.where(key < 0, key ^ jnp.iinfo(key.dtype).max, key)  # back to the float bits
    return jax.lax.bitcast_convert_type(key, x.dtype), jnp.sum(valid, axis=-1)


def _at(s, k):
    return jnp.take_along_axis(s, jnp.clip(k, 0, s.shape[-1] - 1)[..., None], -1)[..., 0]


def masked_median(x: Float[Array, "... n"], valid: Bool[Array, "... n"]) -> Float[Array, "..."]:
    """Median of the valid (non-NaN) entries along the last axis, NaN if none
    (``jnp.nanmedian`` of the masked values, through one integer sort)."""
    if x.shape[-1] == 0:
        return jnp.full(x.shape[:-1], jnp.nan, x.dtype)
    s, n = _sorted_valid(x, valid)
    return jnp.where(n > 0, 0.5 * (_at(s, (n - 1) // 2) + _at(s, n // 2)), jnp.nan)


def _middle_deviations(s, n, med, split, k):
    """The k-th and (k+1)-th smallest |s_i − med| of sorted s (n valid) without sorting
    again: the deviations below ``split`` and from it on are two ascending runs; a
    binary search finds how many of the k+1 smallest come from the lower run, and the
    next smallest is the lesser of the two runs' next ones."""
    def lower(i):  # i-th smallest deviation of the lower run
        return med - _at(s, split - 1 - i)

    def upper(j):
        return _at(s, split + j) - med

    lo, hi = jnp.maximum(0, k + 1 - (n - split)), jnp.minimum(k + 1, split)

    def step(_, bounds):
        lo, hi = bounds
        i = (lo + hi) // 2
        more = (i < hi) & (lower(i) < upper(k - i))  # the lower run's next is among them
        return jnp.where(more, i + 1, lo), jnp.where(more, hi, i)

    lo, _ = jax.lax.fori_loop(0, max(1, int(s.shape[-1]).bit_length() + 1), step, (lo, hi))
    j = k + 1 - lo
    kth = jnp.maximum(jnp.where(lo > 0, lower(lo - 1), -jnp.inf),
                      jnp.where(j > 0, upper(j - 1), -jnp.inf))
    after = jnp.minimum(jnp.where(lo < split, lower(lo), jnp.inf),
                        jnp.where(j < n - split, upper(j), jnp.inf))
    return kth, after


def device_noise_floor(y: Float[Array, "n 3"], mask: Bool[Array, " n"]) -> Float[Array, " 3"]:
    """White-noise σ per axis from successive differences (model-free), over pairs of
    valid samples: :func:`diffgyro._noise.sigma_from_differences` from one sort (and a
    sort of the subsample on rows longer than :data:`diffgyro._noise.SUBSAMPLE`)."""
    if y.shape[0] < 2:
        return jnp.full((3,), jnp.nan, y.dtype)
    dy = jnp.diff(y, axis=0).T  # (3, n-1)
    pair = jnp.broadcast_to(mask[1:] & mask[:-1], dy.shape)
    s, n = _sorted_valid(dy, pair)  # one sort gives every order statistic
    med = 0.5 * (_at(s, (n - 1) // 2) + _at(s, n // 2))
    split = jnp.sum((s < med[:, None]) & (jnp.arange(s.shape[-1]) < n[:, None]), axis=-1)
    # the median deviation: the middle one, or the mean of the middle two (one search)
    kth, after = _middle_deviations(s, n, med, split, (n - 1) // 2)
    scale = 1.4826 * jnp.where(n % 2 == 1, kth, 0.5 * (kth + after))
    h = (1.0 - noise.TRIM) * (n - 1)
    lo = jnp.floor(h).astype(n.dtype)
    t = h - lo
    a, b = _middle_deviations(s, n, med, split, lo)
    b = jnp.where(lo + 1 < n, b, a)
    trim = jnp.where(t >= 0.5, b - (b - a) * (1.0 - t), a + (b - a) * t)
    valid = jnp.arange(s.shape[-1]) < n[:, None]
    dev = jnp.where(valid, jnp.abs(s - med[:, None]), jnp.inf)
    sq = jnp.where(valid, dev * dev, 0.0)

    def mean_count(keep):
        count = jnp.sum(keep, -1)
        return jnp.sum(jnp.where(keep, sq, 0.0), -1) / jnp.maximum(count, 1), count

    ms, inside = mean_count(dev <= 4.0 * scale[:, None])
    ms_trim, _ = mean_count(dev <= trim[:, None])
    ms_trim = jnp.where(ms_trim > 0, ms_trim, mean_count(valid)[0])  # a nearly constant output
    ms = jnp.where(inside < noise.COLLAPSED * n, ms_trim, ms / noise.TRUNC4)
    if dy.shape[-1] > noise.SUBSAMPLE:  # rows long enough to place the window from a subsample
        ms = jnp.where(n > noise.SUBSAMPLE, _subsampled_ms(dy, pair, n, ms), ms)
    return jnp.where(n > 0, jnp.sqrt(ms / 2.0), jnp.nan)


def _subsampled_ms(dy: Float[Array, "3 m"], pair: Bool[Array, "3 m"], n: Int[Array, " 3"],
                   exact: Float[Array, " 3"]) -> Float[Array, " 3"]:
    """Twice the squared floor of rows of more than :data:`diffgyro._noise.SUBSAMPLE` valid
    differences, as :func:`diffgyro._noise._sigma_subsampled` gives it: the window placed
    from the median and MAD of the subsample, the variance of the differences inside it;
    ``exact`` where that function keeps the exact statistic."""
    k = noise.SUBSAMPLE
    valid = pair & ~jnp.isnan(dy)
    rank = (2 * jnp.arange(k)[None, :] + 1) * n[:, None] // (2 * k)  # noise.subsample_ranks
    at = jax.vmap(jnp.searchsorted)(jnp.cumsum(valid, axis=-1), rank + 1)  # the rank-th valid
    sub = jnp.take_along_axis(dy, jnp.clip(at, 0, dy.shape[-1] - 1), axis=-1)
    every = jnp.ones(sub.shape, bool)
    centre = masked_median(sub, every)
    dev = jnp.abs(sub - centre[:, None])
    half_width = 4.0 * 1.4826 * masked_median(dev, every)
    s = dy - centre[:, None]
    q = s * s
    inside = valid & (q <= (half_width * half_width)[:, None])  # noise_passes.window_sums
    count = jnp.sum(inside, axis=-1)
    mean = jnp.sum(jnp.where(inside, s, 0.0), axis=-1) / jnp.maximum(count, 1)
    ms = jnp.sum(jnp.where(inside, q, 0.0), axis=-1) / jnp.maximum(count, 1) - mean * mean
    keep = ((count < noise.EXACT_INSIDE * n) | (jnp.sum(dev == 0, axis=-1) >= noise.EXACT_TIES * k)
            | jnp.any(valid & jnp.isinf(dy), axis=-1))
    return jnp.where(keep, exact, jnp.maximum(ms, 0.0) / noise.TRUNC4)


def _covariance(model: ErrorModel, sig: Signals, params: Params, w, resid, n_eff):
    """Gauss–Newton covariance of (beta per axis, theta), each axis weighted by its σ²."""
    p, q = model.n_params, model.n_nonlinear
    x = model.design(sig, params.theta)
    dof = jnp.maximum(n_eff - p - q, 1.0)
    sigma2 = jnp.sum(w[:, None] * resid**2, axis=0) / dof
    sigma2 = jnp.maximum(sigma2, 1e-300)
    xw = x * (w[:, None] / sigma2[None, :])[:, :, None]
    i_bb = jnp.einsum("nip,niq->ipq", xw, x)
    k = 3 * p + q
    info = jnp.zeros((k, k), x.dtype)
    for i in range(3):
        info = info.at[i * p:(i + 1) * p, i * p:(i + 1) * p].set(i_bb[i])
    if q:
        gth = jax.jacfwd(lambda th: jnp.einsum("nip,ip->ni", model.design(sig, th), params.beta))(
            params.theta)  # (n, 3, q)
        i_bt = jnp.einsum("nip,niq->ipq", xw, gth)
        i_tt = jnp.einsum("niq,nir->qr", gth * (w[:, None] / sigma2[None, :])[:, :, None], gth)
        for i in range(3):
            info = info.at[i * p:(i + 1) * p, 3 * p:].set(i_bt[i])
            info = info.at[3 * p:, i * p:(i + 1) * p].set(i_bt[i].T)
        info = info.at[3 * p:, 3 * p:].set(i_tt)
    d = jnp.sqrt(jnp.diagonal(info))
    d = jnp.where(d > 0, d, 1.0)
    cov = jnp.linalg.inv(info / (d[:, None] * d[None, :])) / (d[:, None] * d[None, :])
    return cov, jnp.sqrt(sigma2)


def solve_device(model: ErrorModel, sig: Signals, opts: FitOptions,
                 theta0: Float[Array, " q"] | None = None) -> dict:
    """Fit one device: a pure JAX function (vmap it, or differentiate through it).

    Returns a dict of arrays: ``beta`` (3, p), ``theta`` (q,), ``cov``,
    ``rms``, ``heldout_rms``, ``fold_mse`` (n_folds,), ``noise_floor`` (3,),
    ``sigma`` (3,), ``steps``, ``status`` and per-term flags ``range_flags``
    and ``collinear``.
    """
    p, q = model.n_params, model.n_nonlinear
    terms = model.terms
    y = sig.gyro - sig.rate
    w = sig.mask.astype(y.dtype)
    n_valid = jnp.sum(w)

    # full fit
    if q:
        start, grid_cost = _grid_start(model, sig, y, w)
        start = start if theta0 is None else theta0
    else:
        start = jnp.zeros((0,), y.dtype)
    if opts.solver == "lm":
        beta, theta, converged, steps = _full_lm(model, sig, y, w, start, opts)
    elif q:
        theta, converged, steps = varpro(model, sig, y, w, start, opts, opts.max_steps)
    else:
        theta = start
        converged, steps = jnp.asarray(True), jnp.asarray(1)
    x = model.design(sig, theta)
    a, c = normal_equations(x, y, w)
    if opts.solver != "lm":
        beta = solve_normal(a, c)
    ratio, direction, rank_ok = rank_check(a, opts.rank_tol)
    params = Params(beta=beta, theta=theta)
    resid = (y - jnp.einsum("nip,ip->ni", x, beta)) * w[:, None]
    rms = jnp.sqrt(jnp.sum(resid**2) / jnp.maximum(3 * n_valid, 1.0))
    if q:  # a local optimum worse than the best grid point is not the answer
        converged = converged & (jnp.sum(resid**2) <= grid_cost * (1.0 + 1e-9) + 1e-300)

    # held-out error over folds of interleaved time blocks
    fold = fold_ids(sig.mask, opts.n_blocks, opts.n_folds)

    def fold_fit(f):
        wf = w * (fold != f)
        if q:
            th, _, _ = varpro(model, sig, y, wf, theta, opts, max(8, opts.max_steps // 4))
            xf = model.design(sig, th)
        else:
            xf = x
        af, cf = normal_equations(xf, y, wf)
        bf = solve_normal(af, cf)
        rf = y - jnp.einsum("nip,ip->ni", xf, bf)
        held = (fold == f).astype(y.dtype)
        return jnp.sum(held[:, None] * rf**2), jnp.sum(held)

    sse, cnt = jax.vmap(fold_fit)(jnp.arange(opts.n_folds))
    heldout_rms = jnp.sqrt(jnp.sum(sse) / jnp.maximum(3 * jnp.sum(cnt), 1.0))
    fold_mse = sse / jnp.maximum(3 * cnt, 1.0)

    noise_axes = device_noise_floor(y, sig.mask) if opts.noise_floor else jnp.full((3,), jnp.nan, y.dtype)
    cov, sigma = _covariance(model, sig, params, w, resid, n_valid)

    # status, most basic problem first
    range_flags = model.range_problems(sig) > 0 if terms else jnp.zeros((0,), bool)
    collinear = collinear_terms(model, direction, rank_ok)
    finite = jnp.all(jnp.isfinite(beta)) & jnp.all(jnp.isfinite(theta)) & jnp.isfinite(rms)
    status = fit_status(n_valid, min_samples(p + q), converged, finite, range_flags, rank_ok)
    return dict(beta=beta, theta=theta, cov=cov, rms=rms, heldout_rms=heldout_rms,
                fold_mse=fold_mse, noise_floor=jnp.sqrt(jnp.mean(noise_axes**2)),
                noise_axes=noise_axes, sigma=sigma, steps=jnp.asarray(steps, jnp.int32),
                status=jnp.asarray(status, jnp.int32), range_flags=range_flags,
                collinear=collinear, rank_ratio=jnp.min(ratio), n_samples=n_valid)


@eqx.filter_jit
def _solve_batch(model: ErrorModel, sig: Signals, opts: FitOptions, theta0):
    TRACE_COUNTS["direct"] += 1

    def one(args):
        s, th = args
        return solve_device(model, s, opts, th)

    xs = (sig, theta0)
    d = sig.gyro.shape[0]
    b = min(opts.chunk, d)
    if d % b:
        return jax.lax.map(one, xs, batch_size=opts.chunk)
    # whole chunks (fit() pads to them): reshape by hand, since lax.map's own reshape of
    # the outputs fails on zero-size ones (theta of a linear model) when no remainder is left
    grouped = jax.tree.map(lambda a: a.reshape(d // b, b, *a.shape[1:]), xs)
    out = jax.lax.map(jax.vmap(one), grouped)
    return jax.tree.map(lambda a: a.reshape(d, *a.shape[2:]), out)


# --------------------------------------------------------------------------- results


class FitResult(eqx.Module):
    """Per-device calibration results (leading device axis on every array)."""

    model: ErrorModel = eqx.field(static=True)
    devices: tuple[str, ...] = eqx.field(static=True)
    params: Params
    norm: TempNorm
    temp_range: Float[Array, "d 2"] | None
    cov: Float[Array, "d k k"]
    rms: Float[Array, " d"]
    heldout_rms: Float[Array, " d"]
    fold_mse: Float[Array, "d f"]
    noise_floor: Float[Array, " d"]
    noise_axes: Float[Array, "d 3"]
    sigma: Float[Array, "d 3"]
    steps: Int[Array, " d"]
    status: Int[Array, " d"]
    range_flags: Bool[Array, "d t"]
    collinear: Bool[Array, "d t"]
    n_samples: Float[Array, " d"]
    options: FitOptions
    #: Centre and half-range of every extra column the model reads ((d,) arrays each).
    aux_norm: dict[str, TempNorm] = eqx.field(default_factory=dict)
    #: Calibrated range of every extra column the model reads ((d, 2) each).
    aux_range: dict[str, Float[Array, "d 2"]] = eqx.field(default_factory=dict)
    #: Whether each device was at rest (:mod:`diffgyro.motion`); None when not checked.
    motion: Motion | None = None
    #: Fitted from the detected static intervals only (``static_only=True``).
    static_only: bool = eqx.field(static=True, default=False)
    #: Valid samples of each recording before the moving ones were left out.
    n_recorded: Float[Array, " d"] | None = None
    #: The sensor fitted (:mod:`diffgyro.channel`): ``gyro``, or ``accel`` with its
    #: gravity reference (m/s², the reading the offsets are relative to).
    channel: str = eqx.field(static=True, default="gyro")
    reference: Float[np.ndarray, "d 3"] | None = None

    @property
    def n_devices(self) -> int:
        return len(self.devices)

    def status_name(self, i: int) -> str:
        return STATUS_NAMES[int(self.status[i])]

    def status_detail(self, i: int) -> str:
        """Status and, when not ok, why in plain words (:func:`diffgyro.status.explain`)."""
        return explain(self.status_name(i), self.model, range_flags=self.range_flags[i],
                       collinear=self.collinear[i],
                       temp_range=None if self.temp_range is None else self.temp_range[i],
                       n_samples=self.n_samples[i], steps=self.steps[i],
                       motion=None if self.motion is None else self.motion.record(i))

    def device_params(self, i: int) -> Params:
        return jax.tree.map(lambda a: a[i], self.params)

    def stderr(self, i: int) -> Params:
        """Standard errors of device ``i``'s parameters, shaped like its Params."""
        p, q = self.model.n_params, self.model.n_nonlinear
        sd = jnp.sqrt(jnp.diagonal(self.cov[i]))
        return Params(beta=sd[:3 * p].reshape(3, p), theta=sd[3 * p:3 * p + q])

    def param_dict(self, i: int) -> dict:
        """Device ``i``'s parameters by label (``term.coefficient`` per axis; time constants in s)."""
        pr = self.device_params(i)
        out: dict = {}
        labels = self.model.param_labels()
        for ax, name in enumerate("xyz"):
            out[name] = {lab: float(v) for lab, v in zip(labels[ax], np.asarray(pr.beta[ax]))}
        taus = [t for t in self.model.terms if t.n_nonlinear]
        if taus:
            out["shared"] = {}
            for (t, _, qs) in self.model.slices():
                if t.n_nonlinear:
                    vals = np.asarray(t.nonlinear_values(pr.theta[qs]))
                    for n, v in zip(t.nonlinear_names(), vals):
                        out["shared"][f"{t.spec}.{n}"] = float(v)
        return out

    def summary(self, i: int) -> dict:
        """One device as plain JSON-ready values (the ``fit --json`` record)."""
        return {
            "device": self.devices[i],
            "status": self.status_name(i),
            "status_detail": self.status_detail(i),
            "rms": number(self.rms[i]),
            "heldout_rms": number(self.heldout_rms[i]),
            "noise_floor": number(self.noise_floor[i]),
            "steps": int(self.steps[i]),
            "n_samples": int(self.n_samples[i]),
            "params": self.param_dict(i),
            "motion": None if self.motion is None else self.motion.record(i),
            "residual_ratio": residual_verdict(self.heldout_rms[i], self.noise_floor[i])[1],
        } | ({"static_only": True, "n_recorded": int(self.n_recorded[i])} if self.static_only else {})

    def records(self) -> list[dict]:
        return [self.summary(i) for i in range(self.n_devices)]

    def signals(self, batch: Batch) -> Signals:
        """Derived signals of ``batch`` with this calibration's temperature centring."""
        names = aux_cols.aux_names(self.model.requires())
        aux_cols.check_columns(batch, names, vary=False)
        return batch_signals(batch, norm=self.norm if self.model.requires() & {"temp"} else None,
                             dtemp_window=self.options.dtemp_window,
                             aux=aux_cols.scaled(batch, self.aux_norm) if names else None)

    def residuals(self, batch: Batch) -> Float[Array, "d n 3"]:
        """Measured minus predicted rate for every sample of ``batch`` (padding zeroed)."""
        sig = self.signals(batch)
        pred = _predict_batch(self.model, self.params, sig)
        return (sig.gyro - pred) * sig.mask[..., None]


@eqx.filter_jit
def _predict_batch(model: ErrorModel, params: Params, sig: Signals) -> Float[Array, "d n 3"]:
    """Predicted rate of every device, compiled once per model and shape."""
    return jax.vmap(model.predict)(params, sig)


def fit(
    model: ErrorModel | str,
    data: Batch | Recording | list[Recording],
    *,
    norm: TempNorm | None = None,
    options: FitOptions | None = None,
    theta0: Float[Array, "d q"] | None = None,
    aux_norm: dict[str, TempNorm] | None = None,
    static_only: bool = False,
    check_motion: bool = True,
    channel: str = "gyro",
    **option_overrides,
) -> FitResult:
    """Calibrate every device of ``data`` with ``model`` (a spec string or ErrorModel).

    ``norm`` fixes the temperature centring (default: each device's own
    range), ``aux_norm`` that of extra columns by name (``aux(NAME)`` terms);
    ``theta0`` (devices × nonlinear parameters, solver space = log τ)
    replaces the grid start of the nonlinear solve. Keyword overrides set
    fields of :class:`FitOptions` (``n_folds=5``, ``max_steps=100``, ...).

    Every device's recording is checked for motion (:func:`diffgyro.motion.motion_check`,
    ``check_motion=False`` skips it): without a rate reference in the model, a device
    that moved (:meth:`diffgyro.motion.Motion.moved_all`: more than 2 % of its recording,
    turns of at least ten times the threshold)
    gets status ``in_motion`` instead of ``ok``. ``static_only`` fits the detected
    static samples only (the moving ones, and a window either side, masked out).

    ``channel="accel"`` fits the accelerometer's thermal offset relative to its gravity
    reference (:func:`diffgyro.channel.as_channel`); the motion check is still the IMU's,
    of the gyro and accelerometer as loaded. ``static_only`` is refused there: the rest
    either side of a move may hold another orientation, so another gravity reference.
    """
    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    imu = as_batch(data)
    channel = check_channel(channel)
    check_model(model, channel)
    if channel != "gyro" and static_only:
        raise DataError("static_only is not available on the accelerometer channel: each "
                        "stretch of rest may hold another orientation (another gravity "
                        "reference)", hint="record the soak in one orientation, at rest")
    batch, reference = as_channel(imu, channel)
    if channel != "gyro":
        result = fit(model, batch, norm=norm, options=options, theta0=theta0, aux_norm=aux_norm,
                     check_motion=False, **option_overrides)
        if hasattr(result, "status"):
            result = _replace(result, channel=channel, reference=reference)
            if check_motion:
                result = judge_motion(result, batch, motion_check(imu))
        return result
    if not (check_motion or static_only):
        return _fit(model, batch, norm, options, theta0, aux_norm, option_overrides)
    recorded = jax.device_put(np.asarray(batch.mask).sum(axis=1).astype(float))
    if static_only:  # the fit needs the check's static samples
        motion = motion_check(batch)  # of gyro − rate where the data hold a rate reference
        batch = eqx.tree_at(lambda b: b.mask, batch, np.asarray(motion.static) & np.asarray(batch.mask))
        result = _fit(model, batch, norm, options, theta0, aux_norm, option_overrides)
    else:  # the check's program compiles while the fit's are traced
        ahead = compile_check(imu)
        result = _fit(model, batch, norm, options, theta0, aux_norm, option_overrides)
        ahead.join()
        motion = motion_check(imu)
    if not hasattr(result, "status"):  # a user's noise-component fit: its own result
        return result
    return judge_motion(result, batch, motion, recorded, static_only)


def judge_motion(result, batch: Batch, motion: Motion | None = None, recorded=None,
                 static_only: bool = False):
    """``result`` (a :class:`FitResult` or the state-space path's fit) with the motion check
    of ``batch`` (computed here unless given) and, where the model has no rate reference,
    status ``in_motion`` for a device that moved and ``rest_unverified`` for one whose
    recording cannot show that it was at rest (:class:`diffgyro.motion.Motion`);
    ``recorded``: samples per device before ``static_only`` masked the moving ones (whose
    fit is ``rest_unverified`` where too little rest is left). Every path that fits a batch
    ends here."""
    if motion is None:
        motion = motion_check(batch)
    if recorded is None:
        recorded = jax.device_put(np.asarray(batch.mask).sum(axis=1).astype(float))
    status = result.status
    if batch.rate is None:  # a fit with a rate reference subtracts it
        if static_only:
            motion = rest_kept(motion)
            moved = np.zeros(len(motion.verdict), bool)
        else:
            moved = motion.moved_all()
        # (a random walk's smoothed bias follows a turn: only a deterministic model's
        # residual tells a thermal transient from motion)
        # (the accelerometer channel keeps the IMU's verdict: its residual is in m/s²)
        if (not static_only and isinstance(result, FitResult) and result.channel == "gyro"
                and np.any(moved & (np.asarray(status) == OK))):
            motion = _unexplained(result, batch, motion, moved)
            moved = motion.moved_all()
        status = np.asarray(status)  # on the host: no program per batch size
        unverified = motion.unverified_all()
        status = np.where(moved & (status == OK), IN_MOTION, status)
        status = np.where(unverified & (status == OK), REST_UNVERIFIED, status)
        status = jax.device_put(status.astype(np.asarray(result.status).dtype))
    return _replace(result, status=status, motion=motion, n_recorded=recorded,
                    static_only=static_only)


def _unexplained(result: FitResult, batch: Batch, motion: Motion, moved) -> Motion:
    """The motion check of what the fitted model leaves unexplained (its residual), for the
    devices whose recording moved; the others keep ``motion``. A fast thermal transient the
    model follows is not motion; a turn no model without a rate reference can follow
    stays in the residual."""
    d, n = np.shape(batch.mask)
    # a large batch: only the devices that moved (a residual and a check of the whole batch
    # cost more than the fit itself); a small one whole (its check program is compiled
    # already, where a sub-batch's would compile anew)
    idx = np.flatnonzero(moved) if d * n > PAD_SAMPLES else np.arange(d)

    def take(x):
        return x[idx] if isinstance(x, (np.ndarray, jax.Array)) and x.ndim and x.shape[0] == d else x

    sub, part = (result, batch) if len(idx) == d else (jax.tree.map(take, result), batch.select(idx))
    resid = np.asarray(sub.residuals(part))  # (only called where batch.rate is None)
    again = motion_check(eqx.tree_at(lambda b: b.gyro, part, resid))
    if len(idx) == d:
        idx = np.flatnonzero(moved)
        again = again.select(idx)
    return motion.put(idx, again)


def _replace(result, **changes):
    """``result`` (a FitResult, or the state-space path's fit) with some fields changed
    (static ones included)."""
    return dataclasses.replace(result, **changes)


def _fit(model: ErrorModel, batch: Batch, norm, options, theta0, aux_norm, option_overrides):
    """:func:`fit` without the motion check."""
    if not jax.config.read("jax_enable_x64"):
        warnings.warn("diffgyro.fit runs in float32 because JAX float64 is off; "
                      "call diffgyro.enable_x64() first", stacklevel=2)
    release_compiled_if_crowded(interval=1.0)  # before this fit compiles its programs
    names = aux_cols.aux_names(model.requires())
    aux_cols.check_columns(batch, names)  # DataError: missing, gaps, constant
    missing = model.requires() - set(batch.signals) - {"t"} - {f"aux:{k}" for k in names}
    if missing:
        col = {"temp": "temp", "temp_ext": "temp_ext", "accel": "ax, ay, az",
               "rate": "rx, ry, rz"}
        name = sorted(missing)[0]
        raise DataError(f"model {model.spec!r} needs column(s) {col.get(name, name)}, not in the data",
                        file=batch.sources[0] if batch.sources else None, column=col.get(name, name))
    if model.noise is not None:  # the state-space path (random_walk: diffgyro.kalman)
        if names:
            raise SpecError(f"{model.noise.spec} with aux terms ({model.spec!r}) is not supported",
                            hint=f"fit the aux terms without {model.noise.spec}")
        fit_noise = noise_fit(model.noise)
        return fit_noise(model, batch, norm=norm, options=options, **option_overrides)
    opts = options or FitOptions()
    if option_overrides:
        opts = opts.replace(**option_overrides)
    if opts.path not in ("auto", "direct", "sums"):
        raise ValueError(f"unknown fit path {opts.path!r}; use 'auto', 'direct' or 'sums'")
    extra = aux_cols.norms(batch, names, aux_norm), aux_cols.ranges(batch, names)
    if opts.solver != "lm" and opts.path in ("sums", "auto"):
        return _fit_sums(model, batch, norm, opts, theta0, extra)
    if opts.path == "sums":
        raise ValueError("path='sums' needs solver='closed'")
    n_dev = batch.n_devices
    batch = pad_devices(batch)  # a few device-count buckets: no compile per batch size
    pad = np.minimum(np.arange(batch.n_devices), n_dev - 1)
    scaled = aux_cols.scaled(batch, {k: TempNorm(centre=v.centre[pad], scale=v.scale[pad])
                                     for k, v in extra[0].items()})
    sig = batch_signals(batch, norm=norm, dtemp_window=opts.dtemp_window, aux=scaled)
    if theta0 is not None:
        theta0 = jnp.broadcast_to(jnp.asarray(theta0, sig.gyro.dtype), (n_dev, model.n_nonlinear))
        theta0 = theta0[np.minimum(np.arange(batch.n_devices), n_dev - 1)]
    out = _solve_batch(model, sig, opts, theta0)
    sig_norm = sig.norm
    if batch.n_devices != n_dev:  # unpadded on the host: no slicing program per shape
        out, sig_norm = jax.device_put(jax.tree.map(lambda a: np.asarray(a)[:n_dev], (out, sig_norm)))
        batch = batch.select(np.arange(n_dev))
    temp_range = None
    if batch.temp is not None:
        tmask = np.where(batch.mask, batch.temp, np.nan)
        temp_range = jnp.stack([jnp.asarray(np.nanmin(tmask, axis=1)),
                                jnp.asarray(np.nanmax(tmask, axis=1))], axis=1)
    norm_out = sig_norm if sig_norm is not None else TempNorm(
        centre=jnp.zeros(batch.n_devices), scale=jnp.ones(batch.n_devices))
    return FitResult(
        model=model, devices=batch.devices, params=Params(beta=out["beta"], theta=out["theta"]),
        norm=norm_out, temp_range=temp_range, cov=out["cov"], rms=out["rms"],
        heldout_rms=out["heldout_rms"], fold_mse=out["fold_mse"], noise_floor=out["noise_floor"],
        noise_axes=out["noise_axes"], sigma=out["sigma"], steps=out["steps"],
        status=out["status"], range_flags=out["range_flags"], collinear=out["collinear"],
        n_samples=out["n_samples"], options=opts, **_aux_fields(extra))


def _aux_fields(extra) -> dict:
    """FitResult's ``aux_norm`` and ``aux_range`` from (norms, ranges) (JAX arrays)."""
    norms, ranges = extra
    return dict(aux_norm={k: TempNorm(centre=jnp.asarray(v.centre), scale=jnp.asarray(v.scale))
                          for k, v in norms.items()},
                aux_range={k: jnp.asarray(v) for k, v in ranges.items()})


def _fit_sums(model: ErrorModel, batch: Batch, norm: TempNorm | None, opts: FitOptions,
              theta0=None, extra=({}, {})) -> FitResult:
    """The sums path (:mod:`diffgyro._fit_sums`): one blocked pass per trial of the time constants."""

    out = solve_sums(model, batch, norm, opts, theta0, aux=aux_cols.scaled(batch, extra[0]))
    d = batch.n_devices
    if "norm_centre" in out:
        norm_out = TempNorm(centre=jax.device_put(out.pop("norm_centre")),
                            scale=jax.device_put(out.pop("norm_scale")))
    else:
        norm_out = TempNorm(centre=jnp.zeros(d), scale=jnp.ones(d))
    # device_put, not jnp.asarray: that compiles a copy for every new shape (~10 ms each)
    temp_range = jax.device_put(out.pop("temp_range")) if "temp_range" in out else None
    out = jax.device_put(out)
    return FitResult(
        model=model, devices=batch.devices, params=Params(beta=out["beta"], theta=out["theta"]),
        norm=norm_out, temp_range=temp_range, cov=out["cov"], rms=out["rms"],
        heldout_rms=out["heldout_rms"], fold_mse=out["fold_mse"], noise_floor=out["noise_floor"],
        noise_axes=out["noise_axes"], sigma=out["sigma"], steps=out["steps"],
        status=out["status"], range_flags=out["range_flags"], collinear=out["collinear"],
        n_samples=out["n_samples"], options=opts, **_aux_fields(extra))
