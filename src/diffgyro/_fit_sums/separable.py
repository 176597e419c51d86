"""Variable projection on the sums: a model with time constants.

The linear coefficients are solved from the sums for every trial of the time
constants; Newton (:mod:`.newton`) moves the time constants alone. Products that do
not move with them are summed once (total and per fold); a trial forms only the
moving columns (with their first and second derivatives, each term's
``columns_jet``) and sums the moving products and their derivatives (product rule) in
one pass. The start is the best point of the model's grid of time constants.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._folds import fold_ids
from ..model import ErrorModel
from .layout import Layout, covariance_pairs, sample_products, varying_products
from .newton import newton
from .normal_equations import cho_solve, cholesky, residual_ss, unpack_split
from .projection import product_jet, projected_cost
from .sums import chunked_sum, fold_sums
from .types import FoldSums, SplitSums


class MovingSums:
    """Sums of the products that move with the time constants, at a trial θ.

    Built once per device (traced once): the moving products' factors, the moving
    terms and the covariance's pairs; :meth:`__call__` forms the moving columns (with
    derivatives) and sums every requested product in one variadic reduction.
    """

    def __init__(self, model: ErrorModel, layout: Layout, sig, ys, x_any, c: int):
        self.model, self.layout, self.sig, self.ys, self.x_any, self.c = (
            model, layout, sig, ys, x_any, c)
        self.nq = model.n_nonlinear
        self.var_idx = varying_products(layout)[0]
        # columns of the terms with time constants: only they are formed per trial
        self.moving_terms = [(tm, sl, qs) for tm, sl, qs in model.slices() if tm.n_nonlinear]
        self.cov_pairs = covariance_pairs(model, layout)[0]

    def factors(self, j):
        """A moving product j as (axis, column, other column or None for a rate)."""
        layout = self.layout
        n_xx = len(layout.xx)
        if j <= n_xx:
            a_, b_, i_ = layout.xx[j - 1]
            return i_, a_, b_
        k_ = j - 1 - n_xx
        return k_ // layout.p, k_ % layout.p, None

    def column_jets(self, th, derivatives):
        """{column: (x (n, 3), dx (q, n, 3), ddx (q, q, n, 3))} of the moving terms'
        columns, derivatives None without ``derivatives``."""
        nq, dtype, out = self.nq, self.ys.dtype, {}
        for tm, sl, qs in self.moving_terms:
            if derivatives:
                x, d, dd = tm.columns_jet(self.sig, th[qs])
            else:
                x, d, dd = tm.columns(self.sig, th[qs]), None, None
            for k_ in range(sl.stop - sl.start):
                dk = ddk = None
                if derivatives:  # this term's θ sit at qs of the model's θ
                    dk = jnp.zeros((nq,) + x.shape[:-1], dtype).at[qs].set(d[..., k_])
                    ddk = jnp.zeros((nq, nq) + x.shape[:-1], dtype).at[qs, qs].set(dd[..., k_])
                out[sl.start + k_] = (x[..., k_], dk, ddk)
        return out

    def factor(self, jets, i_, a_):
        """One column of axis i_ and its derivatives (None: a fixed column)."""
        ax = 0 if self.layout.shared[a_] else i_
        if a_ in jets:
            x, d, dd = jets[a_]
            return x[:, ax], None if d is None else d[:, :, ax], \
                None if dd is None else dd[:, :, :, ax]
        return self.x_any[:, ax, a_], None, None

    def __call__(self, th, masks, derivatives=True, plain=(), covariance=False):
        """Moving sums (m,) per mask, and with ``derivatives`` their first (q, m)
        and second (q, q, m) derivatives in θ (product rule), then the sums alone
        under the ``plain`` masks, then with ``covariance`` the sums of
        :func:`.layout.covariance_pairs` under the first mask: one variadic reduction."""
        nq, var_idx, layout = self.nq, self.var_idx, self.layout
        jets = self.column_jets(th, derivatives)

        @functools.cache
        def column(ax, a_):  # sliced once per column and axis
            return self.factor(jets, ax, a_)

        def fac(i_, a_):
            return column(0 if layout.shared[a_] else i_, a_)

        streams = []
        for j in var_idx:
            i_, a_, b_ = self.factors(j)
            u, du, ddu = fac(i_, a_)
            v, dv, ddv = (self.ys[:, i_], None, None) if b_ is None else fac(i_, b_)
            streams.append(product_jet(u, du, ddu, v, dv, ddv, nq if derivatives else 0))
        ops = [jnp.where(m, u, 0.0) for m in masks for st in streams for u in st]
        ops += [jnp.where(m, st[0], 0.0) for m in plain for st in streams]
        if covariance:  # a column (k None) or a slope ∂x/∂θ_k, of (column, axis)
            def one(a_, i_, k_):
                x_, d_, _ = fac(i_, a_)
                return x_ if k_ is None else d_[k_]

            ops += [jnp.where(masks[0], one(*f) * one(*g_), 0.0) for f, g_ in self.cov_pairs]
        return self._split(chunked_sum(ops, self.c), len(masks), len(plain), derivatives,
                           covariance)

    def _split(self, sums, n_masks: int, n_plain_masks: int, derivatives, covariance):
        """The one reduction's sums apart: per mask (with derivatives), plain, covariance."""
        nq, m = self.nq, len(self.var_idx)
        w = 1 + nq + nq * nq if derivatives else 1
        lead = n_masks * m * w
        n_plain = n_plain_masks * m
        out_plain = sums[lead:lead + n_plain].reshape(n_plain_masks, m)
        out_cov = sums[lead + n_plain:]
        sums = sums[:lead].reshape(n_masks, m, w)
        if not derivatives:
            out = sums[..., 0]
        else:
            out = (sums[..., 0], jnp.moveaxis(sums[..., 1:1 + nq], -1, 1),
                   jnp.moveaxis(sums[..., 1 + nq:].reshape(n_masks, -1, nq, nq), 1, -1))
        if covariance:
            return out, out_plain, out_cov
        return (out, out_plain) if n_plain_masks else out


def fixed_sums(model: ErrorModel, layout: Layout, opts, c: int, sig, mask, nv, ys, pos):
    """The columns that do not move (moving ones zero: never read from it) and the
    total and per-fold sums of the products that do not move."""
    dtype = ys.dtype
    fix_idx = varying_products(layout)[1]
    x_any = jnp.concatenate([jnp.zeros(ys.shape + (tm.n_params,), dtype) if tm.n_nonlinear
                             else tm.columns(sig, jnp.zeros((0,), dtype))
                             for tm, _, _ in model.slices()], axis=-1)
    fix_sel = np.asarray(fix_idx, np.int32)

    def products(src, m):
        ops = sample_products(layout, src[0], src[1], m)
        return [ops[j] for j in fix_sel]

    fix_tot, fix_fold = fold_sums(products, (x_any, ys), mask, nv, opts.n_blocks,
                                  opts.n_folds, c, pos)
    return x_any, fix_tot, fix_fold


def grid_start(model: ErrorModel, layout: Layout, moving: MovingSums, sig, mask, fix_tot):
    """The grid's time constants and projected costs, and the index of the best."""
    dtype = moving.ys.dtype

    def cost_of(fixed, v_):
        a_, c_, q_, _ = unpack_split(layout, fixed, v_)
        return jnp.sum(residual_ss(a_, c_, q_, cho_solve(*cholesky(a_), c_)))

    grid = model.nonlinear_grid(sig).astype(dtype)
    costs = jax.vmap(lambda th: cost_of(fix_tot, moving(th, [mask], False)[0]))(grid)
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    return grid, costs, jnp.argmin(costs)


def separable_sums(model: ErrorModel, layout: Layout, opts, c: int, sig, mask, nv, y, y0,
                   theta0, pos):
    """Sums of a model with time constants at the full fit's optimum (the folds' at
    their refits' optima), the fixed and moving ones apart, with the covariance's."""
    ys = y - y0
    x_any, fix_tot, fix_fold = fixed_sums(model, layout, opts, c, sig, mask, nv, ys, pos)
    moving = MovingSums(model, layout, sig, ys, x_any, c)
    grid, costs, best = grid_start(model, layout, moving, sig, mask, fix_tot)
    start = grid[best] if theta0 is None else theta0
    th_all, cost_all, (v_train, v_held, cov), steps_all, conv_all = refits(
        layout, opts, moving, mask, fix_tot, fix_fold, start)
    theta, steps = th_all[0], steps_all[0]
    # a local optimum worse than the best grid point is not the answer
    converged = conv_all[0] & (cost_all[0] <= costs[best] * (1.0 + 1e-9) + 1e-300)
    # fixed and moving sums apart: the finish unpacks them (:func:`.normal_equations.unpack_sums`)
    return FoldSums(SplitSums(fix_tot, v_train[0]), SplitSums(fix_fold, v_held[1:]),
                    SplitSums(fix_tot[None] - fix_fold, v_train[1:]), theta, steps, converged,
                    covariance=cov[0])


def refits(layout: Layout, opts, moving: MovingSums, mask, fix_tot, fix_fold, start):
    """Newton on the full fit (problem 0) and every fold's refit (problem 1 + k, without
    fold k and scored on fold k's own sums, from the full optimum): one loop solves
    them in turn, so its body is traced and compiled once."""
    n_folds, dtype = opts.n_folds, moving.ys.dtype
    fold_id = fold_ids(mask, opts.n_blocks, n_folds)  # -1 where not valid

    def projected(fixed, v_, dv, ddv):  # the fixed products do not move
        return projected_cost(unpack_split(layout, fixed, v_), unpack_split(layout, None, dv),
                              unpack_split(layout, None, ddv))

    def evaluate(j, th):
        # problem j trains without fold j − 1 (problem 0: on all) and scores on it; the
        # masks and the fixed sums by arithmetic on j (indexing by j is a gather under
        # vmap, a kernel of its own)
        held = mask & (fold_id == j - 1)
        without = jnp.sum(jnp.where((jnp.arange(n_folds) == j - 1)[:, None], fix_fold, 0.0),
                          axis=0)
        # with the covariance's sums at the trial point (problem 0's at θ̂ are the
        # ones kept): they need the columns' slopes, which only this pass forms
        ((v_train,), (dv,), (ddv,)), (v_held,), cov = moving(th, [mask & ~held], plain=[held],
                                                              covariance=True)
        return (*projected(fix_tot - without, v_train, dv, ddv), (v_train, v_held, cov))

    caps = (opts.max_steps,) + (max(8, opts.max_steps // 4),) * n_folds
    sums_shape = jax.ShapeDtypeStruct((len(moving.var_idx),), dtype)
    return newton(evaluate, start, caps, opts.rtol,
                  (sums_shape, sums_shape, jax.ShapeDtypeStruct((len(moving.cov_pairs),), dtype)))
