"""GMWM estimation of one structure: the empirical wavelet variance matched to the model's.

The Generalized Method of Wavelet Moments (Guerrier et al., JASA 2013) minimises

    (ν̂ − ν(θ))ᵀ Ω (ν̂ − ν(θ))

over the parameters θ of a composite model, ν̂ the empirical Haar wavelet
variances on dyadic scales, ν(θ) their theoretical values
(:mod:`.components`) and Ω an efficient weight: the inverse of the
covariance of the moments (:mod:`.covariance`). Here the moments are the
logarithms of the wavelet variances (below), so scales whose variances differ
by ten decades weigh by their relative precision alone.

How a fit runs (one structure, one series; vmapped outside):

1. Starting values: every pair of Gauss–Markov correlation times from a
   dyadic grid (the slopes of the curve do the rest): with the T fixed the
   model is linear in the powers N², Q², σ², K², R², which a small
   non-negative least squares gives; the best pair is kept.
2. Levenberg–Marquardt on the log-parameters (fixed iteration count, so it
   traces and vmaps): log keeps every power and time positive.

The moments matched are the logarithms of the wavelet variances, less their
known bias (:func:`log_moments`): at the longest scales ν̂ is a χ² of a few
degrees of freedom, whose typical value lies well below its mean, and matching
it linearly lets those few scales pull the fit (a random walk read as a
Gauss–Markov process bending down at the end of the record).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import digamma, polygamma
from jaxtyping import Array, Bool, Float

from ._components import (
    N_PARAMS,
    POWER_INDEX,
    TAU_INDEX,
    component_avar,
    model_wv_jac,
    row_mask,
)

#: Levenberg–Marquardt iterations per stage (from the grid's starting values, and the
#: second stage from the first's estimate, the steps have settled by then).
ITERATIONS = 20
#: Logarithms kept inside this range (no underflow of a power switched down to nothing).
_LOG_FLOOR = -150.0


@jax.jit
def scaled_chol(cov_scaled: Float[Array, "J J"], valid: Bool[Array, " J"]) -> Float[Array, "J J"]:
    """Cholesky factor of a covariance of relative wavelet variances, identity on invalid scales
    (traced once per shape: :mod:`.identify`'s note)."""
    vv = valid[:, None] & valid[None, :]
    c = jnp.where(vv, cov_scaled, jnp.eye(cov_scaled.shape[0]))
    jitter = 1e-10 * jnp.trace(c) / c.shape[0]
    return jnp.linalg.cholesky(c + jitter * jnp.eye(c.shape[0]))


@jax.jit
def log_moments(rel_cov: Float[Array, "J J"]) -> tuple[Float[Array, "J J"], Float[Array, " J"]]:
    """Covariance and bias of log ν̂ from the relative covariance of ν̂ (Σ/(ν νᵀ)).

    A wavelet variance averaged over few independent terms is skewed (χ² with e = 2/Σ̃_jj
    equivalent degrees of freedom: at the longest scales e is a few); its logarithm is
    nearly symmetric, with mean log ν + ψ(e/2) − log(e/2) and variance ψ′(e/2). The
    correlations of Σ̃ are kept. Traced once per shape (:mod:`.identify`'s note)."""

    d = jnp.maximum(jnp.diag(rel_cov), 1e-12)
    e = 2.0 / d
    g = jnp.sqrt(polygamma(1, e / 2.0) / d)
    return rel_cov * g[:, None] * g[None, :], digamma(e / 2.0) - jnp.log(e / 2.0)


def spd_solve(a: Float[Array, "... p p"], b: Float[Array, "... p"]) -> Float[Array, "... p"]:
    """Solve ``a x = b`` for symmetric positive definite ``a`` by a Cholesky factorisation
    written out over p (at most 8 here): elementwise operations over the batch, which XLA
    fuses; a batched ``jnp.linalg.solve`` of 6×6 systems took 6× as long on CPU (the
    starting values' thousands of small systems; the fit's own 8×8 steps gain nothing and
    compile longer, so they keep the LU solve). A pivot that is not positive is floored at
    1e-300 (a huge, not a NaN, step)."""
    p = a.shape[-1]
    low = [[None] * p for _ in range(p)]
    for j in range(p):
        piv = jnp.sqrt(jnp.maximum(a[..., j, j] - sum((low[j][k] ** 2 for k in range(j)), 0.0),
                                   1e-300))
        low[j][j] = piv
        for i in range(j + 1, p):
            low[i][j] = (a[..., i, j] - sum((low[i][k] * low[j][k] for k in range(j)), 0.0)) / piv
    z: list = []
    for i in range(p):
        z.append((b[..., i] - sum((low[i][k] * z[k] for k in range(i)), 0.0)) / low[i][i])
    x: list = [None] * p
    for i in reversed(range(p)):
        x[i] = (z[i] - sum((low[k][i] * x[k] for k in range(i + 1, p)), 0.0)) / low[i][i]
    return jnp.stack(x, axis=-1)


def whitener(chol: Float[Array, "J J"]) -> Float[Array, "J J"]:
    """L⁻¹ of a Cholesky factor, formed once per weight: the fit's iterations multiply by it
    (a batched triangular solve inside the iterations cost 13× the whole step on CPU)."""
    return jax.scipy.linalg.solve_triangular(chol, jnp.eye(chol.shape[0], dtype=chol.dtype),
                                             lower=True)


def residual_jac(theta, mask, target, valid, tau, dt, linv):
    """Whitened log residual L⁻¹(target − log ν(θ)), target = log ν̂ less its bias, zero on
    invalid scales (``linv``: L⁻¹, :func:`whitener`), and its Jacobian in the
    log-parameters (switched-off columns zero)."""
    nu, d = model_wv_jac(theta, mask, tau, dt)
    r = jnp.where(valid, target - jnp.log(nu), 0.0)
    d = jnp.where(valid[:, None], d / nu[:, None], 0.0)
    return linv @ r, -(linv @ d)


def _bounds(dt, n):
    lo = jnp.full((N_PARAMS,), _LOG_FLOOR)
    hi = jnp.full((N_PARAMS,), -_LOG_FLOOR)
    lo = lo.at[jnp.array(TAU_INDEX)].set(jnp.log(0.25 * dt))
    hi = hi.at[jnp.array(TAU_INDEX)].set(jnp.log(20.0 * n * dt))
    return lo, hi


def levenberg_marquardt(theta0, mask, target, valid, tau, dt, n, linv, iterations=ITERATIONS):
    """Minimise ‖residual‖² over the switched-on log-parameters (``linv``: the weight's
    :func:`whitener`); returns (θ, objective)."""
    lo, hi = _bounds(dt, n)
    fun = lambda th: residual_jac(th, mask, target, valid, tau, dt, linv)  # noqa: E731
    on = mask.astype(theta0.dtype)

    def step(carry, k):
        # evaluate the trial point (θ₀ itself first), take it if it lowers the cost, then
        # the next trial from the residual and Jacobian at θ: one evaluation an iteration,
        # one copy of the model in the program
        th, lam, cost, r, jac, trial = carry
        tr, tjac = fun(trial)
        new_cost = tr @ tr
        first = k == 0
        better = first | (jnp.isfinite(new_cost) & (new_cost < cost))
        th = jnp.where(better, trial, th)
        cost = jnp.where(better, new_cost, cost)
        r = jnp.where(better, tr, r)
        jac = jnp.where(better, tjac, jac)
        lam = jnp.where(first, lam, jnp.clip(jnp.where(better, lam / 5.0, lam * 4.0), 1e-9, 1e9))
        g = jac.T @ r
        a = jac.T @ jac
        damp = lam * (jnp.diag(a) + 1e-12) + (1.0 - on)
        delta = jnp.linalg.solve(a + jnp.diag(damp), -g[:, None])[:, 0] * on
        return (th, lam, cost, r, jac, jnp.clip(th + delta, lo, hi)), None

    carry = (theta0, jnp.asarray(1e-2, theta0.dtype), jnp.asarray(jnp.inf, theta0.dtype),
             jnp.zeros(target.shape, theta0.dtype),
             jnp.zeros(target.shape + theta0.shape, theta0.dtype), theta0)
    (th, _, cost, _, _, _), _ = jax.lax.scan(step, carry, jnp.arange(iterations + 1))
    return th, cost


def tau_grid(n_scales: int, dt) -> Float[Array, " K"]:
    """Candidate Gauss–Markov correlation times: dt·2^k, k = 0 … J+3."""
    return dt * 2.0 ** jnp.arange(n_scales + 4, dtype=jnp.float64)


def start_pairs(n_scales: int) -> tuple[jax.Array, jax.Array]:
    """Index pairs (a, b) into :func:`tau_grid` to start from, shared by every structure (one
    compiled program): (a, a) for every a (one Gauss–Markov process, or none: the times are
    then unused) and, for two, every pair of even indices with b ≥ a + 2 (times a factor 4 or
    more apart, on a two-octave grid: the Levenberg–Marquardt steps refine them)."""

    k = n_scales + 4
    a, b = np.triu_indices(k, 2)
    keep = (a % 2 == 0) & (b % 2 == 0)
    a = np.concatenate([np.arange(k), a[keep]])
    b = np.concatenate([np.arange(k), b[keep]])
    return jnp.asarray(a), jnp.asarray(b)


def _nnls_powers(c, gram, cty, target, active, sweeps=6):
    """Non-negative least squares ‖c·p − target‖ over the active columns of ``c`` (columns
    normalised; ``gram`` = cᵀc, ``cty`` = cᵀ·target), an active set shrunk by dropping
    negative coefficients. The products with the columns are formed once, outside the
    structures' vmap: a structure only masks them."""

    def solve(act):
        w = act.astype(c.dtype)
        a = gram * (w[:, None] * w[None, :]) + jnp.diag(1.0 - w) + 1e-12 * jnp.eye(c.shape[1])
        return spd_solve(a, cty * w) * w

    def sweep(act, _):
        p = solve(act)
        return act & (p > 0), p

    # the seventh solve is the final one, with the set the six sweeps left: one solve in
    # the program, not two
    _, ps = jax.lax.scan(sweep, active, None, length=sweeps + 1)
    p = jnp.maximum(ps[-1], 0.0)
    misfit = jnp.sum((c @ p - target) ** 2)
    # a switched-on component the data do not ask for starts small, not at zero
    p = jnp.where(active & (p <= 0), 1e-3 * jnp.sqrt(jnp.sum(target**2)), p)
    return p, misfit


def pair_columns(grid, pairs, tau, dt):
    """Per start pair (:func:`start_pairs`): the log-parameters with its two correlation
    times, and each component's wavelet variance at unit power (K, J, 6). The same for
    every structure and series of one sampling: formed once, outside their vmaps."""
    def one(ia, ib):
        th = jnp.zeros((N_PARAMS,)).at[3].set(jnp.log(grid[ia])).at[5].set(jnp.log(grid[ib]))
        return th, (0.5 * component_avar(th, tau, dt)).T

    return jax.vmap(one)(*pairs)


def starting_values(mask, wv_hat, valid, tau, dt, weight, grid, pairs):
    """Log-parameters from the best grid pair of correlation times and NNLS powers."""
    s = jnp.where(valid, wv_hat, 1.0)
    sw = jnp.where(valid, jnp.sqrt(weight), 0.0)
    rows_on = row_mask(mask)

    ths, cols = pair_columns(grid, pairs, tau, dt)
    cols = cols / s[None, :, None] * sw[None, :, None]  # (K, J, 6)
    norm = jnp.sqrt(jnp.sum(cols**2, 1)) + 1e-300  # (K, 6)
    c = cols / norm[:, None, :]
    gram = jnp.einsum("kji,kjl->kil", c, c)
    cty = jnp.einsum("kji,j->ki", c, sw)
    ps, misfits = jax.vmap(lambda ck, g, b: _nnls_powers(ck, g, b, sw, rows_on))(c, gram, cty)
    ps = ps / norm
    best = jnp.argmin(misfits)
    th, p = ths[best], ps[best]
    logp = jnp.log(jnp.maximum(p, 1e-300))
    th = th.at[jnp.array(POWER_INDEX)].set(logp)
    return jnp.clip(th, _LOG_FLOOR, -_LOG_FLOOR)


def diag_rel_cov(count, m):
    """First-stage relative covariance of ν̂: 4m/(3M) at each scale (white noise's equivalent
    degrees of freedom), no correlation."""
    return jnp.diag(4.0 * m / (3.0 * jnp.maximum(count, 1.0)))


def jacobian_log(theta, mask, valid, tau, dt):
    """The model's wavelet variances ν(θ) and ∂ log ν/∂θ on the valid scales, switched-off
    columns zero: ((J,), (J, 8))."""
    nu, d = model_wv_jac(theta, mask, tau, dt)
    return nu, jnp.where(valid[:, None], d / nu[:, None], 0.0)
