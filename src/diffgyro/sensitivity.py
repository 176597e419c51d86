"""How good is a calibration, and what limits it: honest covariance and gradients through the fit.

* :func:`hac_covariance` — the Gauss–Newton covariance assumes white
  residuals; gyro residuals are not (bias instability, thermal transients),
  and the plain covariance is then too small by the ratio of long-run to
  short-run variance. This is a Newey–West style sandwich
  ``H⁻¹ S H⁻¹`` with ``S`` a kernel-weighted sum of score autocovariances,
  after AR(1) prewhitening of the scores (Andrews & Monahan 1992) and with
  the bandwidth chosen from the residuals' autocorrelation (Andrews 1991
  plug-in, fed by flat-top estimates as in Politis & White 2004).
* :func:`block_bootstrap` — circular block bootstrap of the residuals (all
  three axes share the blocks), refitting every replicate (linear models with
  one Cholesky factor for all of them; models with time constants one replicate
  and one device at a time).
* :func:`uncertainty_band` / :func:`plot_uncertainty_band` — propagated
  uncertainty of the compensated rate over an operating temperature range.
* :func:`param_sensitivity`, :func:`compensation_sensitivity` — Jacobians of
  the fitted parameters / of the compensated rate at operating points with
  respect to every input sample, by reverse mode through
  :func:`~diffgyro.fit.solve_device` (closed form through lineax, variable
  projection through optimistix's implicit adjoint).

Flat parameter order everywhere is that of ``FitResult.cov``: ``beta`` per
axis (3p), then ``theta`` (q).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from statistics import NormalDist

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._direct import project_linear, solve_device, varpro
from ._jit import release_compiled_if_crowded
from ._linalg import normal_equations
from .data import Batch
from .fit import FitOptions, FitResult
from .model import ErrorModel, Params
from .plan_design import compensation_error, flat, operating_signals, output_jacobian, unflat
from .signals import Signals, TempNorm

__all__ = ["param_sensitivity", "batch_param_sensitivity", "compensation_sensitivity",
           "uncertainty_band", "uncertainty_bands", "plot_uncertainty_band", "Band",
           "fitted_params", "hac_covariance", "block_bootstrap", "coverage", "z_value",
           "long_run_covariance", "autocovariance", "lag_window", "levinson", "ar_autocovariance"]

KERNELS = ("bartlett", "parzen", "qs")
# Andrews (1991) optimal-bandwidth constants and the characteristic exponent q.
_ANDREWS = {"bartlett": (1.1447, 1), "parzen": (2.6614, 2), "qs": (1.3221, 2)}


# --------------------------------------------------------------------------- autocorrelation


def autocovariance(x: Float[Array, " n"], n_valid) -> Float[Array, " n"]:
    """Biased sample autocovariance ``γ_k = Σ x_t x_{t+k} / n`` of a zero-padded series (FFT).

    **Arguments:**

    - ``x``: the zero-padded series (n,).
    - ``n_valid``: its real samples.
    """
    m = _fft_size(x.shape[0])
    f = jnp.fft.rfft(x, m)
    return jnp.fft.irfft(f * jnp.conj(f), m)[:x.shape[0]] / jnp.maximum(n_valid, 1.0)


def flat_top_sums(x: Float[Array, " n"], n_valid, c: float = 2.0) -> Float[Array, " 3"]:
    """Flat-top estimates of ``Σ γ_k``, ``Σ |k| γ_k`` and ``Σ k² γ_k`` (Politis & White).

    The pilot window ``M = 2 m̂``, ``m̂`` the first lag after which ``K``
    consecutive autocorrelations are below ``c·√(log10 n / n)``.
    """
    n = x.shape[0]
    x = x - jnp.sum(x) / jnp.maximum(n_valid, 1.0) * (jnp.arange(n) < n_valid)
    g = autocovariance(x, n_valid)
    rho = g / jnp.maximum(g[0], 1e-300)
    nv = jnp.maximum(n_valid, 10.0)
    thr = c * jnp.sqrt(jnp.log10(nv) / nv)
    kn = max(5, int(math.sqrt(math.log10(max(n, 10)))))
    small = (jnp.abs(rho) < thr).astype(jnp.int32).at[0].set(0)
    csum = jnp.concatenate([jnp.zeros((1,), jnp.int32), jnp.cumsum(small)])
    k = jnp.arange(n)
    ahead = csum[jnp.clip(k + 1 + kn, 0, n)] - csum[jnp.clip(k + 1, 0, n)]
    ok = (ahead >= kn) & (k + kn < n)
    m_hat = jnp.where(jnp.any(ok), jnp.argmax(ok), n // 4)
    big_m = jnp.clip(2 * m_hat, 1, n // 2).astype(x.dtype)
    u = k / big_m
    lam = jnp.where(u <= 0.5, 1.0, jnp.where(u <= 1.0, 2.0 * (1.0 - u), 0.0))
    two = jnp.where(k == 0, 1.0, 2.0)  # both signs of the lag
    s0 = jnp.sum(two * lam * g)
    s1 = jnp.sum(two * lam * k * g)
    s2 = jnp.sum(two * lam * k * k * g)
    return jnp.stack([jnp.maximum(s0, 1e-3 * g[0]), s1, s2])


def _lag1(x: Float[Array, "n ..."], cap: float) -> Float[Array, "..."]:
    num = jnp.sum(x[1:] * x[:-1], axis=0)
    den = jnp.sum(x[:-1] ** 2, axis=0)
    return jnp.clip(num / jnp.maximum(den, 1e-300), -cap, cap)


def _prewhiten(x: Float[Array, "n ..."], rho) -> Float[Array, "n ..."]:
    return jnp.concatenate([x[:1], x[1:] - rho * x[:-1]], axis=0)


def andrews_bandwidth(resid: Float[Array, "n 3"], n_valid, kernel: str = "bartlett",
                      prewhiten: bool = True, cap: float = 0.97) -> Float[Array, ""]:
    """Lag-window bandwidth from the residual autocorrelation (largest over the axes).

    ``L = c_K (α n)^{1/(2q+1)}`` with ``α = (Σ|k|^q γ_k / Σ γ_k)²`` per axis
    (Andrews 1991; for an AR(1) this is his closed form), the sums estimated
    with a flat-top window; on the AR(1)-prewhitened residuals when the
    scores are prewhitened too.
    """
    const, q = _ANDREWS[kernel]
    if prewhiten:
        resid = _prewhiten(resid, _lag1(resid, cap))
    sums = jax.vmap(lambda r: flat_top_sums(r, n_valid), in_axes=1)(resid)  # (3, 3)
    alpha = (sums[:, q] / sums[:, 0]) ** 2
    bw = const * (alpha * n_valid) ** (1.0 / (2 * q + 1))
    return jnp.clip(jnp.max(bw), 1.0, n_valid / 2)


def lag_window(kind: str, x: Float[Array, "..."]) -> Float[Array, "..."]:
    """Kernel weight at ``x = lag / bandwidth``.

    **Arguments:**

    - ``kind``: the kernel (``"bartlett"``, …).
    - ``x``: lag / bandwidth.
    """
    x = jnp.abs(x)
    if kind == "bartlett":
        return jnp.maximum(1.0 - x, 0.0)
    if kind == "parzen":
        return jnp.where(x <= 0.5, 1 - 6 * x**2 + 6 * x**3, jnp.where(x <= 1, 2 * (1 - x) ** 3, 0.0))
    if kind == "qs":
        z = 6 * jnp.pi * x / 5
        zs = jnp.where(x > 0, z, 1.0)
        val = 25 / (12 * jnp.pi**2 * jnp.where(x > 0, x, 1.0) ** 2) * (jnp.sin(zs) / zs - jnp.cos(zs))
        return jnp.where(x > 0, val, 1.0)
    raise ValueError(f"unknown kernel {kind!r}; choose from {KERNELS}")


def _fft_size(n: int) -> int:
    return 1 << (2 * n - 1).bit_length()


def _circular_lags(m: int, dtype) -> Float[Array, " m"]:
    lag = jnp.arange(m)
    return jnp.minimum(lag, m - lag).astype(dtype)


def lag_weighted_sum(u: Float[Array, "n k"], w_circ: Float[Array, " m"]) -> Float[Array, "k k"]:
    """``Σ_t Σ_s w(t−s) u_t u_sᵀ`` for a symmetric lag weight given on a circular grid of
    ``m ≥ 2n`` points (so no wrap-around), by FFT."""
    n, m = u.shape[0], w_circ.shape[0]
    wf = jnp.fft.rfft(w_circ).real
    conv = jnp.fft.irfft(wf[:, None] * jnp.fft.rfft(u, m, axis=0), m, axis=0)[:n]
    s = u.T @ conv
    return 0.5 * (s + s.T)


def long_run_covariance(u: Float[Array, "n k"], bandwidth, kernel: str = "bartlett"):
    """Kernel estimate ``Σ_t Σ_s k((t−s)/L) u_t u_sᵀ`` (Newey–West for the Bartlett kernel).

    **Arguments:**

    - ``u``: the scores (n, k).
    - ``bandwidth``: the lag window's bandwidth L, samples.
    - ``kernel``: the lag window.
    """
    m = _fft_size(u.shape[0])
    return lag_weighted_sum(u, lag_window(kernel, _circular_lags(m, u.dtype) / bandwidth))


def levinson(g: Float[Array, " p1"], n_valid) -> tuple[Float[Array, " p"], Float[Array, ""], Float[Array, ""]]:
    """Autoregressive fit from autocovariances ``g[0..pmax]`` (Levinson–Durbin), order by AIC.

    Returns the coefficients (zero beyond the chosen order), the innovation
    variance and the order.

    **Arguments:**

    - ``g``: the autocovariances ``g[0..pmax]``.
    - ``n_valid``: the samples they came from (for AIC).
    """
    pmax = g.shape[0] - 1
    a = jnp.zeros((pmax,), g.dtype)
    e = g[0]
    coefs, errs = [a], [e]
    for k in range(1, pmax + 1):
        acc = g[k] - jnp.sum(a[:k - 1] * g[1:k][::-1]) if k > 1 else g[1]
        kappa = acc / jnp.maximum(e, 1e-300)
        prev = a[:k - 1]
        a = a.at[:k - 1].set(prev - kappa * prev[::-1]).at[k - 1].set(kappa)
        e = e * jnp.maximum(1 - kappa**2, 1e-12)
        coefs.append(a)
        errs.append(e)
    errs = jnp.stack(errs)
    aic = n_valid * jnp.log(jnp.maximum(errs, 1e-300)) + 2 * jnp.arange(pmax + 1)
    order = jnp.argmin(aic)
    return jnp.stack(coefs)[order], errs[order], order


def ar_autocovariance(x: Float[Array, " n"], n_valid, m: int, pmax: int = 16,
                      return_order: bool = False):
    """Autocovariance at every circular lag of the AR(p) model (p ≤ pmax by AIC) fitted to ``x``
    (and the order p, with ``return_order``).

    **Arguments:**

    - ``x``: the zero-padded series (n,).
    - ``n_valid``: its real samples.
    - ``m``: the circular lags (the length of the result).
    - ``pmax``: the largest AR order.
    - ``return_order``: also return the order chosen.
    """
    x = x - jnp.sum(x) / jnp.maximum(n_valid, 1.0) * (jnp.arange(x.shape[0]) < n_valid)
    g = autocovariance(x, n_valid)[:pmax + 1]
    a, e, order = levinson(g, n_valid)
    omega = 2 * jnp.pi * jnp.arange(m // 2 + 1) / m
    lags = jnp.arange(1, pmax + 1)
    poly = 1 - jnp.sum(a[None, :] * jnp.exp(-1j * omega[:, None] * lags[None, :]), axis=1)
    spec = e / jnp.abs(poly) ** 2
    gam = jnp.fft.irfft(spec, m)
    return (gam, order) if return_order else gam


# --------------------------------------------------------------------------- covariances


def _residuals(model: ErrorModel, sig: Signals, params: Params):
    w = sig.mask.astype(sig.gyro.dtype)
    return (sig.gyro - model.predict(params, sig)) * w[:, None], w


def _bread(jac, w, sigma2):
    jw = jac * (w[:, None] / sigma2[None, :])[:, :, None]
    k = jac.shape[-1]
    return jw.reshape(-1, k).T @ jac.reshape(-1, k)


def device_hac(model: ErrorModel, sig: Signals, params: Params, method: str = "ar",
               kernel: str = "bartlett", bandwidth=None, prewhiten: bool = True,
               cap: float = 0.97, pmax: int = 16) -> dict:
    """Autocorrelation-consistent sandwich covariance of one device's flat parameters (pure).

    ``method="kernel"``: Newey–West style — scores prewhitened by AR(1) per
    component, lag-window sum with ``kernel`` and ``bandwidth`` (default:
    Andrews' plug-in from the residual autocorrelation), recoloured.
    ``method="ar"``: autoregressive spectral — an AR(p) model (p ≤ ``pmax``
    by AIC) of each axis's residuals gives the noise autocovariance at every
    lag, propagated exactly through the Jacobian (the parametric HAC of den
    Haan & Levin, per axis on the residuals; it assumes stationary noise).

    Returns ``cov`` (k, k), the plain Gauss–Newton ``cov_gn`` from the same
    residuals, the ``bandwidth`` used (samples; for ``"ar"`` the largest AR
    order chosen) and the prewhitening ``rho`` (k,; zero for ``"ar"``).
    """
    if method == "ar":
        return _device_ar_hac(model, sig, params, pmax)
    if method != "kernel":
        raise ValueError(f"unknown method {method!r}; choose 'ar' or 'kernel'")
    k = 3 * model.n_params + model.n_nonlinear
    resid, w = _residuals(model, sig, params)
    n = jnp.sum(w)
    sigma2 = jnp.maximum(jnp.sum(resid**2, axis=0) / jnp.maximum(n - k / 3, 1.0), 1e-300)
    jac = output_jacobian(model, sig, params) * w[:, None, None]
    h = _bread(jac, w, sigma2)
    hinv = _sym_inverse(h)
    u = jnp.einsum("nik,ni->nk", jac, resid / sigma2[None, :])
    if bandwidth is None:
        bandwidth = andrews_bandwidth(resid, n, kernel, prewhiten, cap)
    bandwidth = jnp.asarray(bandwidth, u.dtype)
    if prewhiten:
        rho = _lag1(u, cap)
        e = _prewhiten(u, rho) * w[:, None]
        s = long_run_covariance(e, bandwidth, kernel)
        d = 1.0 / (1.0 - rho)
        s = s * d[:, None] * d[None, :]
    else:
        rho = jnp.zeros((k,), u.dtype)
        s = long_run_covariance(u, bandwidth, kernel)
    s = s * n / jnp.maximum(n - k, 1.0)
    cov = hinv @ s @ hinv
    return dict(cov=0.5 * (cov + cov.T), cov_gn=hinv, bandwidth=bandwidth, rho=rho)


def _device_ar_hac(model: ErrorModel, sig: Signals, params: Params, pmax: int) -> dict:
    k = 3 * model.n_params + model.n_nonlinear
    resid, w = _residuals(model, sig, params)
    n = jnp.sum(w)
    sigma2 = jnp.maximum(jnp.sum(resid**2, axis=0) / jnp.maximum(n - k / 3, 1.0), 1e-300)
    jac = output_jacobian(model, sig, params) * w[:, None, None]
    hinv = _sym_inverse(_bread(jac, w, sigma2))
    m = _fft_size(resid.shape[0])
    p, q = model.n_params, model.n_nonlinear
    s = jnp.zeros((k, k), resid.dtype)
    orders = []
    for i in range(3):
        cols = np.r_[i * p:(i + 1) * p, 3 * p:3 * p + q]  # axis i's rows of the Jacobian are 0 elsewhere
        gam, order = ar_autocovariance(resid[:, i], n, m, pmax, return_order=True)
        orders.append(order)
        # residual variance is short by the fitted share; the dof factor restores it
        gam = gam * n / jnp.maximum(n - k / 3, 1.0)
        s = s.at[np.ix_(cols, cols)].add(lag_weighted_sum(jac[:, i, cols] / sigma2[i], gam))
    cov = hinv @ s @ hinv
    return dict(cov=0.5 * (cov + cov.T), cov_gn=hinv,
                bandwidth=jnp.max(jnp.stack(orders)).astype(resid.dtype),
                rho=jnp.zeros((k,), resid.dtype))


def _sym_inverse(a):
    d = jnp.sqrt(jnp.maximum(jnp.diagonal(a), 1e-300))
    return jnp.linalg.inv(a / (d[:, None] * d[None, :])) / (d[:, None] * d[None, :])


def hac_covariance(result: FitResult, batch: Batch, method: str = "ar", kernel: str = "bartlett",
                   bandwidth=None, prewhiten: bool = True, cap: float = 0.97, pmax: int = 16,
                   chunk: int | None = None) -> dict:
    """Autocorrelation-consistent covariance of every device of a fit (leading device axis).

    ``batch`` is the data the fit saw; ``method`` and the other options as
    in :func:`device_hac`. Returns ``cov`` (d, k, k), ``cov_gn`` (plain, same
    residuals), ``bandwidth`` (d,), ``rho`` (d, k).

    **Arguments:**

    - ``result``: the :class:`~diffgyro.fit.FitResult`.
    - ``batch``: the data the fit saw.
    - ``method``: ``"ar"`` (autoregressive spectral) or ``"kernel"`` (Newey–West style).
    - ``kernel``: the lag window of ``"kernel"`` (``"bartlett"``, …).
    - ``bandwidth``: its bandwidth, samples (default: Andrews' plug-in).
    - ``prewhiten``: prewhiten the scores by AR(1) (``"kernel"``).
    - ``cap``: the bound on |ρ| of the AR(1) prewhitening.
    - ``pmax``: the largest AR order (``"ar"``).
    - ``chunk``: devices per compiled call (default: all at once).
    """
    release_compiled_if_crowded(interval=1.0)  # before this call compiles its programs
    if kernel not in KERNELS:
        raise ValueError(f"unknown kernel {kernel!r}; choose from {KERNELS}")
    return _hac_batch(result.model, result.signals(batch), result.params, method, kernel,
                      bandwidth, prewhiten, cap, pmax, chunk)


@eqx.filter_jit
def _hac_batch(model, sig, params, method, kernel, bandwidth, prewhiten, cap, pmax, chunk):
    return jax.lax.map(lambda a: device_hac(model, a[0], a[1], method, kernel, bandwidth, prewhiten,
                                            cap, pmax), (sig, params), batch_size=chunk or None)


def block_length(resid: Float[Array, "n 3"], n_valid) -> Float[Array, ""]:
    """Circular-block-bootstrap block length from the residual autocorrelation (Politis–White)."""
    sums = jax.vmap(lambda r: flat_top_sums(r, n_valid), in_axes=1)(resid)
    g, d = sums[:, 1], 4.0 / 3.0 * sums[:, 0] ** 2
    b = (2 * g**2 / d) ** (1 / 3) * n_valid ** (1 / 3)
    return jnp.clip(jnp.ceil(jnp.max(b)), 1.0, n_valid / 4)


def device_bootstrap(model: ErrorModel, sig: Signals, params: Params, key, n_boot: int = 200,
                     block=None, opts: FitOptions | None = None) -> dict:
    """Circular block bootstrap of one device's fit: replicate flat parameters and their covariance."""
    opts = opts or FitOptions()
    resid, w = _residuals(model, sig, params)
    n_valid = jnp.sum(w)
    n = w.shape[0]
    if block is None:
        block = block_length(resid, n_valid)
    block = jnp.asarray(block, resid.dtype)
    fitted = model.predict(params, sig)
    t = jnp.arange(n)
    j = (t // block).astype(jnp.int32)
    off = t - j * block
    nv = jnp.maximum(n_valid, 1.0)

    def resample(key):
        starts = jax.random.uniform(key, (n,), resid.dtype, 0.0, nv)
        idx = jnp.floor(jnp.mod(jnp.floor(starts[j]) + off, nv)).astype(jnp.int32)
        return resid[idx] * w[:, None]

    keys = jax.random.split(key, n_boot)
    rstar = jax.vmap(resample)(keys)  # (B, n, 3)
    y_star = fitted - sig.rate + rstar  # bias/scale part plus resampled noise
    if model.n_nonlinear == 0:
        x = model.design(sig, params.theta)
        a, _ = normal_equations(x, y_star[0], w)
        g, dsc = _scaled_gram(a)
        factor = jax.scipy.linalg.cho_factor(g)
        rhs = jnp.einsum("nip,bni->bip", x * w[:, None, None], y_star) / dsc
        beta = jax.vmap(lambda c: jax.scipy.linalg.cho_solve(factor, c[..., None])[..., 0])(rhs) / dsc
        theta = jnp.broadcast_to(params.theta, (n_boot, 0))
    else:
        def refit(y):
            th, _, _ = varpro(model, sig, y, w, params.theta, opts, opts.max_steps)
            b, _ = project_linear(model, sig, y, w, th)
            return b, th

        # one replicate at a time: a batched Levenberg–Marquardt loop runs every element to
        # the slowest one's step count (equal to rounding, in a few times the run time)
        beta, theta = jax.lax.map(refit, y_star)
    reps = jnp.concatenate([beta.reshape(n_boot, -1), theta], axis=1)
    centred = reps - jnp.mean(reps, axis=0)
    cov = centred.T @ centred / (n_boot - 1)
    return dict(cov=cov, replicates=reps, block=block)


def _scaled_gram(a):
    d = jnp.sqrt(jnp.maximum(jnp.diagonal(a, axis1=-2, axis2=-1), 1e-300))
    return a / (d[..., :, None] * d[..., None, :]), d


def block_bootstrap(result: FitResult, batch: Batch, n_boot: int = 200, block=None, seed: int = 0,
                    chunk: int = 8) -> dict:
    """Circular block bootstrap covariance of every device (``cov`` (d, k, k), ``block`` (d,)).

    Residuals of the three axes are resampled with the same blocks (so
    cross-axis correlation survives) and added to the fitted error; each
    replicate is refitted — one Cholesky factor for linear models, variable
    projection from the fitted time constants otherwise.

    **Arguments:**

    - ``result``: the :class:`~diffgyro.fit.FitResult`.
    - ``batch``: the data the fit saw.
    - ``n_boot``: bootstrap replicates.
    - ``block``: the block length, samples (default: chosen per device).
    - ``seed``: the seed.
    - ``chunk``: devices refitted side by side (a linear model's; a model with time
      constants refits one device and one replicate at a time).
    """
    release_compiled_if_crowded(interval=1.0)  # before this call compiles its programs
    keys = jax.random.split(jax.random.PRNGKey(seed), result.n_devices)
    return _bootstrap_batch(result.model, result.signals(batch), result.params, keys,
                            n_boot, block, result.options, chunk)


@eqx.filter_jit
def _bootstrap_batch(model, sig, params, keys, n_boot, block, opts, chunk):
    def one(a):
        out = device_bootstrap(model, a[0], a[1], a[2], n_boot, block, opts)
        return dict(cov=out["cov"], block=out["block"])

    return jax.lax.map(one, (sig, params, keys), batch_size=None if model.n_nonlinear else chunk)


def z_value(level: float) -> float:
    """Two-sided normal quantile for a confidence ``level`` (0.95 → 1.96).

    **Arguments:**

    - ``level``: the confidence level.
    """

    return NormalDist().inv_cdf(0.5 + level / 2)


def coverage(estimates, truth, cov, level: float = 0.95) -> float:
    """Share of parameters whose ``level`` interval (from ``cov``'s diagonal) holds the truth.

    **Arguments:**

    - ``estimates``: the estimated parameters.
    - ``truth``: the true ones.
    - ``cov``: the covariances whose diagonals give the intervals.
    - ``level``: the intervals' confidence level.
    """
    est, tru = np.asarray(estimates), np.asarray(truth)
    sd = np.sqrt(np.maximum(np.diagonal(np.asarray(cov), axis1=-2, axis2=-1), 0.0))
    return float(np.mean(np.abs(est - tru) <= z_value(level) * sd))


# --------------------------------------------------------------------------- operating-range band


class Band(eqx.Module):
    """Estimated correction and its uncertainty over operating temperatures, per axis."""

    temps: Float[Array, " m"]
    rate: Float[Array, " 3"]
    correction: Float[Array, "m 3"]   # the error the calibration removes (rad/s)
    sigma: Float[Array, "m 3"]        # 1σ uncertainty of the compensated rate (rad/s)
    level: float = eqx.field(static=True, default=0.95)
    label: str = eqx.field(static=True, default="")

    @property
    def half_width(self) -> Float[Array, "m 3"]:
        return z_value(self.level) * self.sigma

    @property
    def lower(self):
        return self.correction - self.half_width

    @property
    def upper(self):
        return self.correction + self.half_width


def compensation_jacobian(model: ErrorModel, params: Params, norm: TempNorm, temps, rate=0.0,
                          dtemp: float = 0.0) -> tuple[Float[Array, "m 3 k"], Float[Array, "m 3"]]:
    """∂(compensated rate)/∂(flat params) at operating points, and the correction there.

    At every temperature the device sees ``rate`` (scalar on all axes, or a
    3-vector); its output is what the fitted model predicts, held fixed while
    the parameters move.
    """
    temps = jnp.atleast_1d(jnp.asarray(temps, params.beta.dtype))
    rate = jnp.broadcast_to(jnp.asarray(rate, temps.dtype), (3,))
    ops = operating_signals(temps, jnp.broadcast_to(rate, (temps.shape[0], 3)), norm, dtemp)
    jac = jax.jacfwd(lambda v: compensation_error(model, unflat(v, model), ops, model, params))(
        flat(params))
    corr = jax.vmap(lambda s: model.error(params, s)[0])(ops)
    return jac, corr


@eqx.filter_jit
def _band_arrays(model: ErrorModel, params: Params, norm: TempNorm, cov, temps, rate, dtemp):
    g, corr = compensation_jacobian(model, params, norm, temps, rate, dtemp)
    return corr, jnp.sqrt(jnp.maximum(jnp.einsum("mik,kl,mil->mi", g, cov, g), 0.0))


def uncertainty_band(result: FitResult, i: int, temps, rate=0.0, cov=None, level: float = 0.95,
                     dtemp: float = 0.0, label: str = "") -> Band:
    """Propagated uncertainty of device ``i``'s compensated rate over ``temps`` (°C).

    ``σ(T) = √diag(G C Gᵀ)`` with ``G`` the Jacobian of the compensated rate
    at temperature ``T`` and input ``rate`` (rad/s) with respect to the
    parameters, and ``C`` the parameter covariance: ``result.cov[i]`` (plain
    Gauss–Newton) by default, or any (k, k) matrix such as
    ``hac_covariance(...)["cov"][i]``.

    **Arguments:**

    - ``result``: the :class:`~diffgyro.fit.FitResult`.
    - ``i``: the device's index.
    - ``temps``: the temperatures, °C.
    - ``rate``: the input rate, rad/s.
    - ``cov``: the parameter covariance (k, k); default ``result.cov[i]``.
    - ``level``: the band's confidence level.
    - ``dtemp``: dT/dt, °C/s.
    - ``label``: the band's name in figures.
    """
    params = result.device_params(i)
    norm = TempNorm(centre=result.norm.centre[i], scale=result.norm.scale[i])
    cov = result.cov[i] if cov is None else jnp.asarray(cov)
    temps = jnp.atleast_1d(jnp.asarray(temps, params.beta.dtype))
    corr, sigma = _band_arrays(result.model, params, norm, cov, temps, rate, dtemp)
    return Band(temps=temps, rate=jnp.broadcast_to(jnp.asarray(rate, temps.dtype), (3,)),
                correction=corr, sigma=sigma, level=level, label=label)


def uncertainty_bands(result: FitResult, temps, rate=0.0, cov=None, level: float = 0.95,
                      dtemp: float = 0.0) -> Band:
    """:func:`uncertainty_band` of every device at once (arrays get a leading device axis).

    **Arguments:**

    - ``result``: the :class:`~diffgyro.fit.FitResult`.
    - ``temps``: the temperatures, °C.
    - ``rate``: the input rate, rad/s.
    - ``cov``: the covariances (d, k, k); default ``result.cov``.
    - ``level``: the bands' confidence level.
    - ``dtemp``: dT/dt, °C/s.
    """
    cov = result.cov if cov is None else jnp.asarray(cov)
    temps = jnp.atleast_1d(jnp.asarray(temps, result.params.beta.dtype))
    model = result.model

    @jax.jit
    def run(params, centre, scale, cov):
        return jax.vmap(lambda p, c, s, v: _band_arrays(model, p, TempNorm(centre=c, scale=s), v,
                                                         temps, rate, dtemp))(params, centre, scale, cov)

    corr, sigma = run(result.params, result.norm.centre, result.norm.scale, cov)
    return Band(temps=temps, rate=jnp.broadcast_to(jnp.asarray(rate, temps.dtype), (3,)),
                correction=corr, sigma=sigma, level=level)


UNITS = {"rad/s": 1.0, "deg/s": 180 / math.pi, "deg/h": 180 / math.pi * 3600}


def plot_uncertainty_band(bands: Band | list[Band], unit: str = "deg/h", fig=None, title: str = ""):
    """One panel per gyro axis: the estimated correction with its shaded confidence band.

    Several bands (e.g. plain and autocorrelation-consistent covariance)
    overlay; returns the matplotlib Figure.

    **Arguments:**

    - ``bands``: one :class:`Band` or several to overlay.
    - ``unit``: the unit plotted (``"deg/h"`` or ``"rad/s"``).
    - ``fig``: a matplotlib Figure to draw on (default: a new one).
    - ``title``: the figure's title.
    """

    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:  # a notebook keeps its own backend
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bands = [bands] if isinstance(bands, Band) else list(bands)
    scale = UNITS[unit]
    if fig is None:
        fig, axes = plt.subplots(1, 3, figsize=(12, 3.4), sharex=True, constrained_layout=True)
    else:
        axes = fig.subplots(1, 3, sharex=True)
    for ax_i, ax in enumerate(axes):
        for j, b in enumerate(bands):
            temps = np.asarray(b.temps)
            c = np.asarray(b.correction[:, ax_i]) * scale
            h = np.asarray(b.half_width[:, ax_i]) * scale
            color = f"C{j}"
            name = b.label or f"band {j + 1}"
            ax.fill_between(temps, c - h, c + h, color=color, alpha=0.25,
                            label=f"{name} ({100 * b.level:.0f} %)")
            if j == 0:
                ax.plot(temps, c, color="k", lw=1.2, label="correction")
        ax.set_title(f"{'xyz'[ax_i]} axis")
        ax.set_xlabel("temperature (°C)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"compensation ({unit})")
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


# --------------------------------------------------------------------------- sensitivities


def _sens_options(opts: FitOptions | None) -> FitOptions:
    # folds do not change the full fit; two keep the unused held-out refits cheap
    return opts or FitOptions(n_folds=2, n_blocks=2)


def fitted_params(model: ErrorModel, sig: Signals, opts: FitOptions | None = None,
                  theta0=None) -> Float[Array, " k"]:
    """Flat fitted parameters of one device through :func:`~diffgyro.fit.solve_device`.

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``sig``: one device's :class:`~diffgyro.signals.Signals`.
    - ``opts``: the :class:`~diffgyro.fit.FitOptions`.
    - ``theta0``: the start of the time constants (log τ).
    """
    out = solve_device(model, sig, _sens_options(opts), theta0)
    return flat(Params(beta=out["beta"], theta=out["theta"]))


def param_sensitivity(model: ErrorModel, sig: Signals, opts: FitOptions | None = None,
                      theta0=None) -> Float[Array, "k n 3"]:
    """∂(fitted flat parameters)/∂(every gyro sample) of one device (reverse mode).

    Linear models differentiate the lineax Cholesky solve; models with time
    constants differentiate the Levenberg–Marquardt solution by the implicit
    function theorem (optimistix ``ImplicitAdjoint``). Padded samples get 0.

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``sig``: one device's :class:`~diffgyro.signals.Signals`.
    - ``opts``: the :class:`~diffgyro.fit.FitOptions` (default: the defaults).
    - ``theta0``: the start of the time constants (log τ; default: the grid's best point).
    """
    def f(gyro):
        return fitted_params(model, eqx.tree_at(lambda s: s.gyro, sig, gyro), opts, theta0)

    return jax.jacrev(f)(sig.gyro)


def compensation_sensitivity(model: ErrorModel, sig: Signals, temps, rate=0.0,
                             opts: FitOptions | None = None, theta0=None,
                             dtemp: float = 0.0) -> Float[Array, "m 3 n 3"]:
    """∂(compensated rate at each operating temperature and axis)/∂(every gyro sample).

    The compensated error is the compensated minus the true rate; the truth
    does not depend on the data, so this is also the sensitivity of the
    compensation error. ``sig.norm`` fixes the temperature scaling.

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``sig``: one device's :class:`~diffgyro.signals.Signals`.
    - ``temps``: the operating temperatures (m,), °C.
    - ``rate``: the true rate there, rad/s.
    - ``opts``: the :class:`~diffgyro.fit.FitOptions`.
    - ``theta0``: the start of the time constants (log τ).
    - ``dtemp``: dT/dt there, °C/s.
    """
    theta_hat = fitted_params(model, sig, opts, theta0)
    params = unflat(theta_hat, model)
    g, _ = compensation_jacobian(model, params, sig.norm, temps, rate, dtemp)
    return jnp.einsum("mik,knj->minj", g, param_sensitivity(model, sig, opts, theta0))


def batch_param_sensitivity(result: FitResult, batch: Batch) -> Float[Array, "d k n 3"]:
    """:func:`param_sensitivity` of every device of a fit, vmapped (starts at the fitted τ).

    **Arguments:**

    - ``result``: the :class:`~diffgyro.fit.FitResult`.
    - ``batch``: the data the fit saw.
    """
    sig = result.signals(batch)
    model = result.model
    opts = dataclasses.replace(result.options, n_folds=2, n_blocks=2)
    theta = result.params.theta if model.n_nonlinear else None

    @jax.jit
    def run(sig, theta):
        return jax.vmap(lambda s, th: param_sensitivity(model, s, opts, th),
                        in_axes=(0, 0 if theta is not None else None))(sig, theta)

    return run(sig, theta)
