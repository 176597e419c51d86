"""The direct path: one device's fit on its design matrix, a pure JAX function.

Linear models take the closed form: weighted normal equations of the per-axis design,
columns scaled to unit norm, a rank check on the scaled Gram matrix (never silent
truncation) and a Cholesky solve through lineax. Models with time constants (thermal
lag, warm-up) use variable projection: the linear coefficients are solved in closed form
for given time constants (:func:`project_linear`) and optimistix's Levenberg–Marquardt
moves the time constants alone (:func:`varpro`), started from the best point of a coarse
grid. Held-out error refits every fold of interleaved time blocks. :func:`solve_device`
is what :func:`diffgyro.fit.fit` runs per device on its direct path, what the sensitivities
differentiate and what plan design predicts through; :func:`solve_batch` maps it over a
batch in one compiled program.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from ._folds import fold_ids
from ._jit import TRACE_COUNTS
from ._linalg import normal_equations, rank_check, solve_normal, solve_normal_inner
from ._noise_jax import device_noise_floor
from ._options import FitOptions
from .model import ErrorModel, Params, columns_times
from .signals import Signals
from .status import collinear_terms, fit_status, min_samples

if TYPE_CHECKING:
    import optimistix as optx

__all__ = ["solve_device", "solve_batch", "project_linear", "varpro", "lm_converged",
           "STALLED_STEPS"]

def project_linear(model: ErrorModel, sig: Signals, y: Float[Array, "n 3"], w: Float[Array, " n"],
                   theta: Float[Array, " q"]
                   ) -> tuple[Float[Array, "3 p"], Float[Array, "n 3 p"]]:
    """Linear coefficients for given nonlinear parameters, and the design."""
    x = model.design(sig, theta)
    a, c = normal_equations(x, y, w)
    return solve_normal_inner(a, c), x


def varpro(model: ErrorModel, sig: Signals, y: Float[Array, "n 3"], w: Float[Array, " n"],
           theta0: Float[Array, " q"], opts: FitOptions, max_steps: int
           ) -> tuple[Float[Array, " q"], Bool[Array, ""], Int[Array, ""]]:
    """Levenberg–Marquardt over the time constants with the linear part projected out."""
    sw = jnp.sqrt(w)[:, None]

    def residual(theta, _):
        beta, x = project_linear(model, sig, y, w, theta)
        return (y - columns_times(x, beta)) * sw

    import optimistix as optx  # loaded when a solve is traced (0.1-0.25 s of a start)

    solver = optx.LevenbergMarquardt(rtol=opts.rtol, atol=opts.atol)
    sol = optx.least_squares(residual, solver, theta0, max_steps=max_steps, throw=False)
    return sol.value, lm_converged(sol), sol.stats["num_steps"]


#: Rejected Levenberg–Marquardt steps in a row after which the solution is a minimum to
#: rounding: each rejection shrinks the trust region fourfold (optimistix's classical
#: trust region), so no step down to 4⁻¹⁰ ≈ 1e-6 of the last accepted one lowered the cost.
STALLED_STEPS = 10


def lm_converged(sol: optx.Solution) -> Bool[Array, ""]:
    """Whether an optimistix Levenberg–Marquardt solve converged: its tolerance met, or
    stalled at a minimum, every step of the last :data:`STALLED_STEPS` rejected. The
    tolerance compares every residual's change with its size; near the minimum that change
    is rounding, and whether it falls under the tolerance before the steps run out rests on
    the last bits of the arithmetic. A stall at a point worse than the start grid is still
    caught by :func:`solve_device`'s comparison with the grid."""
    import optimistix as optx

    stalled = sol.state.num_steps_since_acceptance >= STALLED_STEPS
    return (sol.result == optx.RESULTS.successful) | stalled


def _full_lm(model: ErrorModel, sig: Signals, y: Float[Array, "n 3"], w: Float[Array, " n"],
             theta0: Float[Array, " q"], opts: FitOptions
             ) -> tuple[Float[Array, "3 p"], Float[Array, " q"], Bool[Array, ""], Int[Array, ""]]:
    """Levenberg–Marquardt over every parameter at once (no projection).

    The reference path: for linear models it must agree with the closed form.
    """
    sw = jnp.sqrt(w)[:, None]

    def residual(params, _):
        beta, theta = params
        return (y - columns_times(model.design(sig, theta), beta)) * sw

    import optimistix as optx

    beta0 = jnp.zeros((3, model.n_params), y.dtype)
    solver = optx.LevenbergMarquardt(rtol=opts.rtol, atol=opts.atol)
    sol = optx.least_squares(residual, solver, (beta0, theta0), max_steps=opts.max_steps,
                             throw=False)
    beta, theta = sol.value
    return beta, theta, lm_converged(sol), sol.stats["num_steps"]


def _grid_start(model: ErrorModel, sig: Signals, y: Float[Array, "n 3"], w: Float[Array, " n"]
                ) -> tuple[Float[Array, " q"], Float[Array, ""]]:
    """Best point of the coarse grid of time constants, and its cost."""
    grid = model.nonlinear_grid(sig)

    def cost(theta):
        beta, x = project_linear(model, sig, y, w, theta)
        r = y - columns_times(x, beta)
        return jnp.sum(w[:, None] * r * r)

    costs = jax.vmap(cost)(grid)
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    best = jnp.argmin(costs)
    return grid[best], costs[best]


def _covariance(model: ErrorModel, sig: Signals, params: Params, w: Float[Array, " n"],
                resid: Float[Array, "n 3"], n_eff: Float[Array, ""]
                ) -> tuple[Float[Array, "k k"], Float[Array, " 3"]]:
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
        gth = jax.jacfwd(lambda th: columns_times(model.design(sig, th), params.beta))(
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
                 theta0: Float[Array, " q"] | None = None) -> dict[str, Array]:
    """Fit one device: a pure JAX function (vmap it, or differentiate through it).

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``sig``: one device's :class:`~diffgyro.signals.Signals` (n samples).
    - ``opts``: :class:`~diffgyro.fit.FitOptions` (solver, folds, tolerances, steps).
    - ``theta0``: the start of the time constants (solver space, log τ); None starts from
      the best point of the model's grid.

    **Returns:** a dict of arrays: ``beta`` (3, p), ``theta`` (q,), ``cov``,
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
    resid = (y - columns_times(x, beta)) * w[:, None]
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
        rf = y - columns_times(xf, bf)
        held = (fold == f).astype(y.dtype)
        return jnp.sum(held[:, None] * rf**2), jnp.sum(held)

    # the folds one after another: a vmap here, inside the vmap over devices, batches
    # the solver's loop twice, which traces and runs slower for the same numbers
    sse, cnt = jax.lax.map(fold_fit, jnp.arange(opts.n_folds))
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
def solve_batch(model: ErrorModel, sig: Signals, opts: FitOptions,
                theta0: Float[Array, "d q"] | None) -> dict[str, Array]:
    """:func:`solve_device` of every device of ``sig`` (``theta0``: (d, q) starts or None),
    in groups of ``opts.chunk`` devices: one compiled program per model and shape."""
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
