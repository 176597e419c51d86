"""Bias random walk: Kalman filter, RTS smoother, likelihood and learned noise levels.

Per gyro axis the measured rate minus the reference rate is modelled as::

    y_k = X_k·β + b_k + v_k,     v_k ~ N(0, r)            (measured where obs_k)
    b_k = b_{k−1} + w_k,         w_k ~ N(0, q·(t_k − t_{k−1})),   b_0 ~ N(0, p0)

``X·β`` is any deterministic error model (``ErrorModel.design(sig, θ)``),
``b`` the random walk. ``q`` is the random-walk intensity in (rad/s)²/s, so
√q is the rate random walk in rad/s²/√Hz (what the Allan +1/2 line reads);
``r`` the white-noise variance per sample, (rad/s)², so √(r·dt) is the angle
random walk in rad/s/√Hz. Samples with ``obs = False`` (moving with no
reference rate, gaps, padding) get no measurement update.

**β is profiled out in closed form.** The filter's gains do not depend on the
data, so running it on ``y`` and on every column of ``X`` at once gives
innovations ``e_y``, ``E_X`` and variances ``F`` with which the likelihood of
any β is ``−½ Σ [log 2πF + (e_y − E_X β)²/F]``: generalised least squares in
whitened form. ``β̂ = (Σ E_Xᵀ E_X / F)⁻¹ Σ E_Xᵀ e_y / F`` exactly, and the
profile likelihood (or, with ``reml=True``, the restricted likelihood) is a
smooth function of (log q, log r, θ) alone, which optimistix's BFGS maximises
per device (vmapped, ``throw=False``, per-device status).

With a constant bias among the deterministic terms (``bias_poly``), the walk
starts at 0 (``p0 = 0``) so the constant and the walk are not confounded;
without one the walk gets a wide prior instead.

Also here: a causal filter run (:func:`causal_bias`) for real-time compensation.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ._fit_result import AbstractFitResult
from ._folds import fold_ids
from ._jit import release_compiled_if_crowded
from ._jsonio import number
from ._noise_jax import device_noise_floor
from ._options import FitOptions
from ._signal_builder import batch_signals
from .data import Batch, Recording, as_batch, bucket_length
from .model import ErrorModel, Params
from .signals import TempNorm
from .status import FAILED, INSUFFICIENT_DATA, NOT_CONVERGED, OK, explain
from .stochastic import bias_filter, state_space

__all__ = ["fit_random_walk", "RandomWalkFit", "identified_bias", "smooth_bias", "causal_bias",
           "rw_filter", "rts_smoother", "learn_noise", "loglik", "profile", "FilterPass",
           "SmoothedBias", "NoiseFit"]

LOG_2PI = math.log(2.0 * math.pi)
#: Prior variance of the walk's start when no constant bias is modelled, (rad/s)².
WIDE_PRIOR = 1.0


# --------------------------------------------------------------------------- one axis


class FilterPass(eqx.Module):
    """Per-sample output of the augmented filter (one axis).

    ``e_y``/``e_x`` innovations of the data and of each design column,
    ``f`` innovation variance, ``a_y``/``a_x`` filtered means (after the
    update), ``p`` filtered variance, ``p_pred`` predicted variance.
    """

    e_y: Float[Array, " n"]
    e_x: Float[Array, "n p"]
    f: Float[Array, " n"]
    a_y: Float[Array, " n"]
    a_x: Float[Array, "n p"]
    p: Float[Array, " n"]
    p_pred: Float[Array, " n"]


def rw_filter(
    y: Float[Array, " n"],
    x: Float[Array, "n p"],
    obs: Bool[Array, " n"],
    t: Float[Array, " n"],
    q: Float[Array, ""],
    r: Float[Array, ""],
    p0: Float[Array, ""] = 0.0,
) -> FilterPass:
    """Kalman filter of the random walk run on ``y`` and on each column of ``x`` (lax.scan).

    (An associative-scan version compiled for minutes and ran slower on CPU.)

    **Arguments:**

    - ``y``: one axis' observations (n,).
    - ``x``: the design columns of that axis (n, p).
    - ``obs``: where the bias is observed (n,).
    - ``t``: sample times (n,), s.
    - ``q``: the walk's variance rate.
    - ``r``: the white measurement variance.
    - ``p0``: the walk's prior variance at the first sample.
    """
    dtype = y.dtype
    p_cols = x.shape[1]

    def step(carry, inp):
        a_y, a_x, p, t_prev = carry
        yk, xk, ok, tk = inp
        pp = p + q * (tk - t_prev)
        f = pp + r
        k = jnp.where(ok, pp / f, 0.0)
        ey = yk - a_y
        ex = xk - a_x
        a_y = a_y + k * ey
        a_x = a_x + k * ex
        p = jnp.where(ok, pp * r / f, pp)
        return (a_y, a_x, p, tk), (ey, ex, f, a_y, a_x, p, pp)

    init = (jnp.zeros((), dtype), jnp.zeros((p_cols,), dtype), jnp.asarray(p0, dtype), t[0])
    _, out = jax.lax.scan(step, init, (y, x, obs, t))
    return FilterPass(*out)


def profile(fp: FilterPass, obs: Bool[Array, " n"], reml: bool = False):
    """Log-likelihood with β profiled out (GLS), and β̂, from one filter pass.

    Returns (loglik, beta, gram) where gram = Σ E_Xᵀ E_X / F is Xᵀ Σ⁻¹ X.

    **Arguments:**

    - ``fp``: one filter pass (:func:`rw_filter`).
    - ``obs``: where the bias is observed (n,).
    - ``reml``: restricted maximum likelihood instead of plain ML.
    """
    w = jnp.where(obs, 1.0 / fp.f, 0.0)
    quad = jnp.sum(w * fp.e_y**2)
    logdet = jnp.sum(jnp.where(obs, jnp.log(fp.f), 0.0))
    n_obs = jnp.sum(obs)
    ll = -0.5 * (n_obs * LOG_2PI + logdet + quad)
    p_cols = fp.e_x.shape[1]
    if p_cols == 0:
        return ll, jnp.zeros((0,), fp.e_y.dtype), jnp.zeros((0, 0), fp.e_y.dtype)
    a = jnp.einsum("n,ni,nj->ij", w, fp.e_x, fp.e_x)
    c = jnp.einsum("n,ni,n->i", w, fp.e_x, fp.e_y)
    d = jnp.sqrt(jnp.maximum(jnp.diagonal(a), 1e-300))
    a_s = a / (d[:, None] * d[None, :]) + 1e-14 * jnp.eye(p_cols, dtype=a.dtype)
    chol = jnp.linalg.cholesky(a_s)
    z = jax.scipy.linalg.cho_solve((chol, True), c / d)
    beta = z / d
    ll = ll + 0.5 * jnp.dot(c, beta)
    if reml:
        logdet_a = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol))) + 2.0 * jnp.sum(jnp.log(d))
        ll = ll + 0.5 * p_cols * LOG_2PI - 0.5 * logdet_a
    return ll, beta, a


def loglik(y, x, obs, t, q, r, p0=0.0, reml: bool = False):
    """Marginal log-likelihood of one axis (β profiled out) and β̂.

    **Arguments:**

    - ``y``: one axis' observations (n,).
    - ``x``: its design columns (n, p).
    - ``obs``: where the bias is observed (n,).
    - ``t``: sample times (n,), s.
    - ``q``: the walk's variance rate.
    - ``r``: the white measurement variance.
    - ``p0``: the walk's prior variance at the first sample.
    - ``reml``: restricted maximum likelihood instead of plain ML.
    """
    fp = rw_filter(y, x, obs, t, q, r, p0)
    ll, beta, _ = profile(fp, obs, reml)
    return ll, beta


def rts_smoother(fp: FilterPass, beta: Float[Array, " p"]):
    """Rauch–Tung–Striebel smoother of the walk for the residual ``y − Xβ``.

    Returns (mean, variance) of ``b_k`` given all observations, every sample:
    ``G_k = P_k|k / P_{k+1|k}``, ``m_k = m_k|k + G_k (m_{k+1} − m_k|k)``,
    ``P_k = P_k|k + G_k² (P_{k+1} − P_{k+1|k})`` (G = 1 where nothing moves).

    **Arguments:**

    - ``fp``: the forward pass (:func:`rw_filter`).
    - ``beta``: the deterministic coefficients (p,) whose residual is smoothed.
    """
    mf = fp.a_y - fp.a_x @ beta
    pf = fp.p

    def back(carry, inp):
        ms_next, ps_next = carry
        m_k, p_k, pp_next = inp
        g = jnp.where(pp_next > 0, p_k / jnp.where(pp_next > 0, pp_next, 1.0), 1.0)
        ms = m_k + g * (ms_next - m_k)
        ps = p_k + g * g * (ps_next - pp_next)
        return (ms, ps), (ms, ps)

    init = (mf[-1], pf[-1])
    _, (ms, ps) = jax.lax.scan(back, init, (mf[:-1], pf[:-1], fp.p_pred[1:]), reverse=True)
    return jnp.concatenate([ms, mf[-1:]]), jnp.concatenate([ps, pf[-1:]])


class SmoothedBias(eqx.Module):
    """Smoothed bias of one device (or a batch, leading axes added).

    ``bias`` = deterministic part ``X·β`` + ``walk`` (rad/s); ``walk_sd`` the
    walk's posterior standard deviation given β̂; ``loglik`` per axis.
    """

    beta: Float[Array, "3 p"]
    bias: Float[Array, "n 3"]
    walk: Float[Array, "n 3"]
    walk_sd: Float[Array, "n 3"]
    loglik: Float[Array, " 3"]


def smooth_bias(
    y: Float[Array, "n 3"],
    x: Float[Array, "n 3 p"],
    obs: Bool[Array, " n"],
    t: Float[Array, " n"],
    q: Float[Array, " 3"],
    r: Float[Array, " 3"],
    p0: float | Float[Array, ""] = 0.0,
    reml: bool = False,
) -> SmoothedBias:
    """GLS β and RTS-smoothed random walk of all three axes of one device.

    ``y`` is the measured minus the reference rate, ``x`` the deterministic
    design (``model.design(sig, θ)``), ``obs`` where the bias is observed.

    **Arguments:**

    - ``y``: the measured minus the reference rate (n, 3).
    - ``x``: the deterministic design (n, 3, p), ``model.design(sig, θ)``.
    - ``obs``: where the bias is observed (n,).
    - ``t``: sample times (n,), s.
    - ``q``: the walk's variance rate per axis (3,), (rad/s)²/s.
    - ``r``: the white measurement variance per axis (3,), (rad/s)².
    - ``p0``: the walk's prior variance at the first sample.
    - ``reml``: profile β by restricted maximum likelihood (REML) instead of plain ML.
    """
    p0 = jnp.asarray(p0, y.dtype)

    def axis(yi, xi, qi, ri):
        fp = rw_filter(yi, xi, obs, t, qi, ri, p0)
        ll, beta, _ = profile(fp, obs, reml)
        ms, ps = rts_smoother(fp, beta)
        return beta, xi @ beta + ms, ms, jnp.sqrt(jnp.maximum(ps, 0.0)), ll

    beta, bias, walk, sd, ll = jax.vmap(axis, in_axes=(1, 1, 0, 0), out_axes=(0, 1, 1, 1, 0))(
        y, x, jnp.asarray(q, y.dtype), jnp.asarray(r, y.dtype))
    return SmoothedBias(beta=beta, bias=bias, walk=walk, walk_sd=sd, loglik=ll)


def causal_bias(y, obs, t, q, r, m0, p0):
    """Real-time bias estimate of one axis: the filter's prediction from samples before k.

    Starts from ``b ~ N(m0, p0)`` at ``t[0]``; returns (mean, variance) per sample
    (what a device would subtract at sample k, knowing only the past).

    **Arguments:**

    - ``y``: one axis' measured minus reference rate (n,).
    - ``obs``: where the bias is observed (n,).
    - ``t``: sample times (n,), s.
    - ``q``: the walk's variance rate, (rad/s)²/s.
    - ``r``: the white measurement variance, (rad/s)².
    - ``m0``: the prior mean of the bias at ``t[0]``.
    - ``p0``: its prior variance.
    """
    fp = rw_filter(y - m0, jnp.zeros((y.shape[0], 0), y.dtype), obs, t, q, r, p0)
    pred = jnp.concatenate([jnp.zeros((1,), y.dtype), fp.a_y[:-1]]) + m0
    return pred, fp.p_pred


def identified_bias(y: Float[Array, "n 3"], axes: dict, dt: float, p0_walk: float = WIDE_PRIOR):
    """Filtered bias (mean, variance) (n, 3) of each axis under its identified noise model.

    ``axes``: ``{"x": {"components": [...]}, ...}`` as ``noise --json`` and
    ``diagnose --json``'s ``noise`` give them (SI units). Gauss–Markov and random-walk
    states replace the one walk of :func:`rw_filter`
    (:mod:`diffgyro.stochastic._bias_filter`); a random walk alone is that filter. An
    axis with no bias process (white only) has bias 0 and variance 0. ``y``: the rate
    at rest, or the residual of a deterministic model, sampled every ``dt`` s.

    **Arguments:**

    - ``y``: the rate at rest, or the residual of a deterministic model (n, 3), rad/s.
    - ``axes``: each axis' identified noise model, ``{"x": {"components": [...]}, ...}``.
    - ``dt``: the sampling interval, s.
    - ``p0_walk``: the prior variance of a random-walk state at the first sample.
    """

    y = jnp.asarray(y, jnp.float64)
    mean, var = [], []
    for k, ax in enumerate("xyz"):
        comps = axes[ax]["components"]
        if not any(c["kind"] in ("gauss_markov", "random_walk") for c in comps):
            mean.append(jnp.zeros_like(y[:, k]))
            var.append(jnp.zeros_like(y[:, k]))
            continue
        b, pb, _, _ = bias_filter(y[:, k], *state_space(comps, dt, p0_walk=p0_walk))
        mean.append(b)
        var.append(pb)
    return jnp.stack(mean, 1), jnp.stack(var, 1)


# --------------------------------------------------------------------------- learning


def initial_noise(y: Float[Array, "n 3"], obs: Bool[Array, " n"], t: Float[Array, " n"]):
    """Starting (q, r) per axis: r from successive differences (robust), q from long lags."""
    dy = jnp.diff(y, axis=0)
    pair = obs[1:] & obs[:-1]
    d = jnp.where(pair[:, None], dy, jnp.nan)
    med = jnp.nanmedian(d, axis=0)
    sd = 1.4826 * jnp.nanmedian(jnp.abs(d - med), axis=0) / jnp.sqrt(2.0)
    r = jnp.maximum(sd**2, 1e-30)
    dt = jnp.nanmedian(jnp.where(pair, jnp.diff(t), jnp.nan))
    dt = jnp.where(jnp.isfinite(dt) & (dt > 0), dt, 1.0)
    return r, dt


class NoiseFit(eqx.Module):
    """Learned noise levels of one device: q, r per axis, θ, β, likelihood and solver status."""

    q: Float[Array, " 3"]
    r: Float[Array, " 3"]
    theta: Float[Array, " k"]
    beta: Float[Array, "3 p"]
    loglik: Float[Array, ""]
    steps: Int[Array, ""]
    converged: Bool[Array, ""]


def _design(model: ErrorModel, sig, theta, dtype):
    if model.n_params:
        return model.design(sig, theta)
    return jnp.zeros((sig.t.shape[0], 3, 0), dtype)


def _floor_penalty(lq, floor):
    """Near zero above ``floor``, quadratic below (smoothly): keeps log q finite for an unseen walk.

    Such a walk has its likelihood maximum at q → 0, where the likelihood is
    flat; the penalty turns that into an optimum at the floor that the solver
    converges to, and changes nothing above it. The floor, q = 0.01·r/(dt·n²)
    for n observations, is a walk whose spread over the whole record is a
    tenth of the noise of the record's mean: invisible in these data.
    """
    return 0.5 * jnp.sum(jax.nn.softplus(floor - lq) ** 2)


def learn_noise(
    model: ErrorModel,
    sig,
    obs: Bool[Array, " n"],
    p0: Float[Array, ""],
    keep: tuple[Int[Array, " m"], Bool[Array, " m"]] | None = None,
    *,
    reml: bool = False,
    max_steps: int = 200,
    rtol: float = 1e-6,
    atol: float = 1e-9,
    n_grid: int = 13,
) -> NoiseFit:
    """Maximum-likelihood q, r (per axis) and θ of one device (vmap over devices).

    ``keep`` = (indices, valid) restricts the likelihood to those samples:
    passing the observed ones is exact (between observations the walk only
    accumulates q·Δt) and saves the scan steps of long unobserved stretches.
    Start: r from successive differences; log q from the best of a grid
    (q·dt from 1e-9·r to 10·r) at that r; then BFGS on the negative
    log-likelihood per observation in (log q, log r, θ). β follows in closed form.

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel` (its time constants are learned
      too).
    - ``sig``: one device's :class:`~diffgyro.signals.Signals`.
    - ``obs``: where the bias is observed (n,).
    - ``p0``: the walk's prior variance at the first sample.
    - ``keep``: (indices, valid): the samples the likelihood reads, or None for all.
    - ``reml``: restricted maximum likelihood instead of plain ML.
    - ``max_steps``: BFGS steps at most.
    - ``rtol``: BFGS's relative tolerance.
    - ``atol``: BFGS's absolute tolerance.
    - ``n_grid``: points of the starting grid in log q.
    """
    dtype = sig.gyro.dtype
    obs = obs & sig.mask
    y_all = jnp.where(obs[:, None], sig.gyro - sig.rate, 0.0)
    if keep is None:
        idx, ok = jnp.arange(obs.shape[0]), jnp.ones(obs.shape, bool)
    else:
        idx, ok = keep
    y, t, o = y_all[idx], sig.t[idx], obs[idx] & ok
    n_obs = jnp.maximum(jnp.sum(o), 1).astype(dtype)
    r0, dt = initial_noise(y, o, t)
    floor = jnp.log(1e-2 * r0 / (dt * n_obs**2))
    theta0 = model.nonlinear_init(sig)

    def nll(params):
        lq, lr, theta = params[:3], params[3:6], params[6:]
        x = _design(model, sig, theta, dtype)[idx]

        def axis(yi, xi, qi, ri):
            return loglik(yi, xi, o, t, qi, ri, p0, reml)[0]

        ll = jax.vmap(axis, in_axes=(1, 1, 0, 0))(y, x, jnp.exp(lq), jnp.exp(lr))
        return -jnp.sum(ll) / n_obs + _floor_penalty(lq, floor)

    grid = jnp.linspace(jnp.log(1e-9), jnp.log(10.0), n_grid)
    vals = jax.vmap(lambda g: nll(jnp.concatenate([jnp.log(r0 / dt) + g, jnp.log(r0), theta0])))(grid)
    vals = jnp.where(jnp.isfinite(vals), vals, jnp.inf)
    x0 = jnp.concatenate([jnp.log(r0 / dt) + grid[jnp.argmin(vals)], jnp.log(r0), theta0])
    solver = optx.BFGS(rtol=rtol, atol=atol)
    sol = optx.minimise(lambda p, _: nll(p), solver, x0, max_steps=max_steps, throw=False)
    p = sol.value
    q, r, theta = jnp.exp(p[:3]), jnp.exp(p[3:6]), p[6:]
    x = _design(model, sig, theta, dtype)[idx]
    ll, beta = jax.vmap(lambda yi, xi, qi, ri: loglik(yi, xi, o, t, qi, ri, p0, reml),
                        in_axes=(1, 1, 0, 0))(y, x, q, r)
    return NoiseFit(q=q, r=r, theta=theta, beta=beta, loglik=jnp.sum(ll),
                    steps=sol.stats["num_steps"], converged=sol.result == optx.RESULTS.successful)


def observed_indices(obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per device, the indices of the observed samples padded to one bucket length, and
    their validity: the ``keep`` argument of :func:`learn_noise` for a batch (host numpy)."""

    obs = np.asarray(obs, bool)
    counts = obs.sum(axis=1)
    length = min(bucket_length(max(int(counts.max()), 1)), obs.shape[1])
    idx = np.zeros((obs.shape[0], length), np.int64)
    ok = np.zeros((obs.shape[0], length), bool)
    for d in range(obs.shape[0]):
        where = np.flatnonzero(obs[d])
        if where.size:
            idx[d, :where.size] = where
            idx[d, where.size:] = where[-1]
            ok[d, :where.size] = True
    return idx, ok


# --------------------------------------------------------------------------- the batch fit


class RandomWalkFit(AbstractFitResult):
    """Deterministic model + random walk fitted to every device of a batch: the fields of
    :class:`~diffgyro.fit.AbstractFitResult` (``rms`` over the observed samples,
    ``heldout_rms`` on held-out time blocks predicted by the smoother from the rest, with
    q, r and θ from the full fit), and the walk's own below."""

    residual_tells_motion: ClassVar[bool] = False

    model: ErrorModel = eqx.field(static=True)
    devices: tuple[str, ...] = eqx.field(static=True)
    params: Params
    norm: object
    #: Random-walk intensity per axis, (rad/s)²/s.
    q: Float[Array, "d 3"]
    #: White-noise variance per sample and axis, (rad/s)².
    r: Float[Array, "d 3"]
    #: Log-likelihood (restricted with ``reml``).
    loglik: Float[Array, " d"]
    #: The smoothed total bias (deterministic part and walk) on every sample.
    bias: Float[Array, "d n 3"]
    #: The walk part of :attr:`bias`, and its standard deviation.
    walk: Float[Array, "d n 3"]
    walk_sd: Float[Array, "d n 3"]
    #: What the smoothed bias leaves (zero where not observed).
    residual: Float[Array, "d n 3"]
    #: The samples that observed the bias.
    observed: Bool[Array, "d n"]
    rms: Float[Array, " d"]
    heldout_rms: Float[Array, " d"]
    fold_mse: Float[Array, "d f"]
    noise_floor: Float[Array, " d"]
    noise_axes: Float[Array, "d 3"]
    steps: Int[Array, " d"]
    status: Int[Array, " d"]
    n_samples: Float[Array, " d"]
    temp_range: Float[Array, "d 2"] | None
    options: object
    #: Prior variance of the walk's start, (rad/s)².
    p0: Float[Array, ""]
    reml: bool = eqx.field(static=True, default=False)
    motion: object = None
    static_only: bool = eqx.field(static=True, default=False)
    n_recorded: Float[Array, " d"] | None = None

    def smooth(self, batch, static=None) -> SmoothedBias:
        """The fitted model's bias on ``batch`` (same devices): β and θ kept, the walk smoothed
        afresh with the learned q, r where ``batch`` observes it (its reference rate, or
        ``static``, or every sample)."""
        sig = self.signals(batch)
        obs = jnp.asarray(batch.mask)
        if static is not None:
            obs = obs & jnp.asarray(static, bool)
        model, p0, reml = self.model, self.p0, self.reml

        def one(s, o, beta, theta, q, r):
            y = jnp.where(o[:, None], s.gyro - s.rate, 0.0)
            det = jnp.einsum("nip,ip->ni", _design(model, s, theta, y.dtype), beta)
            none = jnp.zeros((y.shape[0], 0), y.dtype)

            def axis(zi, qi, ri):
                fp = rw_filter(zi, none, o, s.t, qi, ri, p0)
                ll, _, _ = profile(fp, o, reml)
                ms, ps = rts_smoother(fp, jnp.zeros((0,), y.dtype))
                return ms, jnp.sqrt(jnp.maximum(ps, 0.0)), ll

            walk, sd, ll = jax.vmap(axis, in_axes=(1, 0, 0), out_axes=(1, 1, 0))(y - det, q, r)
            return SmoothedBias(beta=beta, bias=det + walk, walk=walk, walk_sd=sd, loglik=ll)

        return jax.vmap(one)(sig, obs, self.params.beta, self.params.theta, self.q, self.r)

    def residuals(self, batch, static=None) -> Float[Array, "d n 3"]:
        """Measured minus reference rate minus the smoothed bias (β, θ, q, r of this fit)."""
        sig = self.signals(batch)
        sb = self.smooth(batch, static)
        return (sig.gyro - sig.rate - sb.bias) * sig.mask[..., None]

    @property
    def aux_norm(self) -> dict:
        """Centring of extra columns by name: none (fit() refuses aux terms beside a walk)."""
        return {}

    @property
    def aux_range(self) -> dict:
        """Calibrated range of extra columns by name: none, as :attr:`aux_norm`."""
        return {}

    @property
    def rrw(self) -> Float[Array, "d 3"]:
        """Rate random walk √q, rad/s²/√Hz."""
        return jnp.sqrt(self.q)

    def status_detail(self, i: int) -> str:
        """Status and, when not ok, why in plain words (:func:`diffgyro.status.explain`)."""
        name = self.status_name(i)
        if name == "insufficient_data":
            need = max(20, 4 * (self.model.n_params + self.model.n_nonlinear + 2))
            return (f"{name}: {int(np.asarray(self.n_samples)[i])} observed samples; the state-space fit "
                    f"of {self.model.spec} needs at least {need}")
        return explain(name, self.model, n_samples=np.asarray(self.n_samples)[i],
                       steps=np.asarray(self.steps)[i],
                       motion=None if self.motion is None else self.motion.record(i))

    def _axis_noise(self, i: int, axis: int) -> dict:
        return {"random_walk.q": float(self.q[i, axis]), "random_walk.r": float(self.r[i, axis])}

    def _likelihood(self, i: int) -> dict:
        return {"loglik": number(self.loglik[i])}


def _fit_device(model, sig, obs, keep, p0, reml, max_steps, n_blocks, n_folds):

    nf = learn_noise(model, sig, obs, p0, keep, reml=reml, max_steps=max_steps)
    obs = obs & sig.mask
    y = jnp.where(obs[:, None], sig.gyro - sig.rate, 0.0)
    x = _design(model, sig, nf.theta, y.dtype)
    sb = smooth_bias(y, x, obs, sig.t, nf.q, nf.r, p0, reml)
    w = obs.astype(y.dtype)
    resid = (y - sb.bias) * w[:, None]
    n_obs = jnp.sum(w)
    rms = jnp.sqrt(jnp.sum(resid**2) / jnp.maximum(3 * n_obs, 1.0))
    fold = jnp.where(obs, fold_ids(obs, n_blocks, n_folds), -1)

    def fold_fit(f):
        of = obs & (fold != f)
        sf = smooth_bias(y, x, of, sig.t, nf.q, nf.r, p0, reml)
        held = (fold == f).astype(y.dtype)
        return jnp.sum(held[:, None] * (y - sf.bias) ** 2), jnp.sum(held)

    sse, cnt = jax.vmap(fold_fit)(jnp.arange(n_folds))
    heldout = jnp.sqrt(jnp.sum(sse) / jnp.maximum(3 * jnp.sum(cnt), 1.0))
    noise_axes = device_noise_floor(sig.gyro - sig.rate, obs)
    finite = jnp.all(jnp.isfinite(sb.bias)) & jnp.isfinite(nf.loglik) & jnp.all(jnp.isfinite(nf.q))
    p = model.n_params + model.n_nonlinear
    status = jnp.where(n_obs < max(20, 4 * (p + 2)), INSUFFICIENT_DATA,
                       jnp.where(~finite, FAILED, jnp.where(nf.converged, OK, NOT_CONVERGED)))
    return dict(beta=sb.beta, theta=nf.theta, q=nf.q, r=nf.r, loglik=jnp.sum(sb.loglik),
                bias=sb.bias, walk=sb.walk, walk_sd=sb.walk_sd, residual=resid, rms=rms,
                heldout_rms=heldout, fold_mse=sse / jnp.maximum(3 * cnt, 1.0),
                noise_axes=noise_axes, noise_floor=jnp.sqrt(jnp.mean(noise_axes**2)),
                steps=jnp.asarray(nf.steps, jnp.int32), status=jnp.asarray(status, jnp.int32),
                n_samples=n_obs)


@eqx.filter_jit
def _fit_batch(model, sig, obs, keep, p0, reml, max_steps, n_blocks, n_folds, chunk):
    def one(args):
        s, o, k = args
        return _fit_device(model, s, o, k, p0, reml, max_steps, n_blocks, n_folds)

    return jax.lax.map(one, (sig, obs, keep), batch_size=chunk)


def fit_random_walk(
    model: ErrorModel | str,
    batch: Batch | Recording | list[Recording],
    *,
    static: Bool[np.ndarray, "d n"] | None = None,
    norm: TempNorm | None = None,
    options: FitOptions | None = None,
    reml: bool = False,
    p0: float | None = None,
    **option_overrides,
) -> RandomWalkFit:
    """Fit the deterministic part of ``model`` plus a bias random walk to every device.

    **Arguments:**

    - ``model``: a spec string or :class:`~diffgyro.model.ErrorModel`
      (``"bias_poly(0)+random_walk"``): its deterministic terms are fitted beside the walk.
    - ``batch``: a :class:`~diffgyro.data.Batch`, one recording or a list of them.
    - ``static``: (devices × samples) where the device is static, e.g. from
      :mod:`diffgyro.detect`; the bias is observed there when the data hold no reference
      rate (``rx, ry, rz``). None: every sample (a static recording).
    - ``norm``: the temperature centring (default: each device's own range).
    - ``options``: :class:`~diffgyro.fit.FitOptions`; keyword ``option_overrides`` set its
      fields (``n_blocks``, ``n_folds``, ``max_steps``, ``chunk``, ``dtemp_window``).
    - ``reml``: learn q and r by the restricted likelihood instead of the profile one.
    - ``p0``: prior variance of the walk's start, (rad/s)²; default 0 beside a constant
      bias, else :data:`WIDE_PRIOR`.

    q, r per axis and any time constants are learned by maximum likelihood, β by GLS.
    """
    release_compiled_if_crowded(interval=1.0)  # before this call compiles its programs

    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    batch = as_batch(batch)
    opts = options or FitOptions()
    if option_overrides:
        opts = opts.replace(**option_overrides)
    sig = batch_signals(batch, norm=norm, dtemp_window=opts.dtemp_window)
    obs = np.asarray(batch.mask, bool)
    if static is not None:
        obs = obs & np.asarray(static, bool).reshape(obs.shape)
    if p0 is None:
        p0 = 0.0 if any(t.constant_bias for t in model.terms) else WIDE_PRIOR
    idx, ok = observed_indices(obs)
    keep = (jnp.asarray(idx), jnp.asarray(ok))
    out = _fit_batch(model, sig, jnp.asarray(obs), keep, jnp.asarray(p0, sig.gyro.dtype), reml,
                     opts.max_steps, opts.n_blocks, opts.n_folds, opts.chunk)
    norm_out = sig.norm if sig.norm is not None else TempNorm(
        centre=jnp.zeros(batch.n_devices), scale=jnp.ones(batch.n_devices))
    temp_range = None
    if batch.temp is not None:
        tmask = np.where(batch.mask, batch.temp, np.nan)
        temp_range = jnp.stack([jnp.asarray(np.nanmin(tmask, axis=1)),
                                jnp.asarray(np.nanmax(tmask, axis=1))], axis=1)
    return RandomWalkFit(
        model=model, devices=batch.devices, params=Params(beta=out["beta"], theta=out["theta"]),
        norm=norm_out, q=out["q"], r=out["r"], loglik=out["loglik"], bias=out["bias"],
        walk=out["walk"], walk_sd=out["walk_sd"], residual=out["residual"],
        observed=jnp.asarray(obs), rms=out["rms"], heldout_rms=out["heldout_rms"],
        fold_mse=out["fold_mse"], noise_floor=out["noise_floor"], noise_axes=out["noise_axes"],
        steps=out["steps"], status=out["status"], n_samples=out["n_samples"],
        temp_range=temp_range, options=opts, p0=jnp.asarray(p0, sig.gyro.dtype), reml=reml)
