"""The sums path of linear fits: one blocked pass over the samples, no design matrix.

For a model linear in all its parameters everything :func:`diffgyro.fit.fit`
reports — the normal equations of every axis, those of every held-out fold,
the residual and held-out sums of squares — is a sum over samples of products
of regressor columns and rates. This path reads each device's samples once:

* one XLA *variadic* reduction over short sample chunks forms all products'
  chunk sums in a single loop (XLA on CPU does not fuse sibling reductions;
  separate ``jnp.sum`` calls read the data once per product);
* a time block of the held-out folds starts inside at most one chunk when the
  chunk is no longer than the shortest block, so each chunk also sums the
  part after that boundary; chunk and part sums land exactly in their blocks'
  folds;
* a fold's training system is the total minus its held-out sums, and its
  held-out error ``Σ(y − xβ)² = Q − 2βᵀc + βᵀAβ`` comes from the held-out
  sums alone.

Columns equal on the three axes (bias polynomial, gradient, temp_diff, ...)
share their products, so ``bias_poly(k)`` needs (k+1)(k+2)/2 column products
and 3(k+2) rate products per sample, in one pass, instead of a (n, 3, p)
design matrix read once per fold. ``Q − 2βᵀc + βᵀAβ`` cancels when the fit
is good; each axis' first valid sample is subtracted before summing when the
model has a constant bias column, which leaves the cancellation to the scale
of the rate's variation rather than of its offset.

Devices are processed in groups of a fixed size on the host (and spread over
every local JAX device), so only the group size — not the number of devices —
is part of the compiled shape.
"""

from __future__ import annotations

import functools
import os
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.interpreters import partial_eval as pe

from .data import Batch
from .model import ErrorModel
from .signals import Signals, TempNorm, make_signals, temp_norm_from

#: Longest sample chunk of the variadic reduction (shortened to the shortest fold block).
CHUNK = 32
#: About this many samples (devices × samples) go into one compiled call.
GROUP_SAMPLES = 1 << 18
#: Per-sample inputs a linear model may read, in the order the group function takes them.
INPUTS = ("t", "rate", "temp", "temp_ext", "accel")


class Layout(eqx.Module):
    """Static description of the per-sample products of one model.

    ``xx`` lists the distinct column products (a, b, axis) — products equal on
    all axes or equal as functions (T·T² = T⁰·T³) are formed once; ``a_idx``
    maps every (axis, a, b) entry of the Gram matrices to its product.
    """

    p: int = eqx.field(static=True)
    xx: tuple = eqx.field(static=True)
    a_map: tuple = eqx.field(static=True)  # (3·p·p,) product index of every Gram entry
    shared: tuple = eqx.field(static=True)  # per column: equal on the three axes
    const_col: int | None = eqx.field(static=True)

    @property
    def n_products(self) -> int:
        return 1 + len(self.xx) + 3 * self.p + 3

    def index(self):
        """Where A (3, p, p), c (3, p), Q (3,) and the count sit in the product vector."""
        p, k = self.p, 1 + len(self.xx)
        a_idx = np.asarray(self.a_map, np.int32).reshape(3, p, p)
        c_idx = (k + np.arange(3 * p)).reshape(3, p).astype(np.int32)
        q_idx = (k + 3 * p + np.arange(3)).astype(np.int32)
        return a_idx, c_idx, q_idx


def _random_signals(present: frozenset[str], n: int, seed: int) -> Signals:
    """Signals of n samples with every field random (no derived-signal computation)."""
    rng = np.random.default_rng(seed)

    def r(*shape):
        return jnp.asarray(rng.normal(size=shape))

    has = {k: k in present for k in INPUTS}
    temp = jnp.asarray(rng.uniform(10, 40, n)) if has["temp"] else None
    return Signals(
        t=jnp.asarray(np.cumsum(rng.uniform(0.5, 1.5, n))), gyro=r(n, 3), mask=jnp.ones(n, bool),
        rate=r(n, 3), temp=temp, temp_s=r(n) if has["temp"] else None,
        dtemp=r(n) if has["temp"] else None,
        heating=jnp.asarray(np.sign(rng.normal(size=n))) if has["temp"] else None,
        temp_ext=jnp.asarray(rng.uniform(0, 30, n)) if has["temp_ext"] else None,
        accel=r(n, 3) if has["accel"] else None,
        norm=TempNorm(centre=jnp.asarray(25.0), scale=jnp.asarray(15.0)) if has["temp"] else None,
        has_rate=has["rate"])


@functools.lru_cache(maxsize=256)
def layout_of(model: ErrorModel, present: frozenset[str]) -> tuple[Layout | None, frozenset[str]]:
    """The model's product layout and the inputs its columns and range checks read.

    Evaluated once per model on random signals: which columns are equal on all
    axes, which column products coincide, and whether every column is a
    function of its own sample's signals (``None`` if not: such a model takes
    the direct path). Which inputs are read — and whether the sampling
    interval (dT/dt) matters — comes from dead-code elimination of the trace.
    """
    n = 24
    sig = _random_signals(present, n, 12345)
    perm = np.random.default_rng(1).permutation(n)
    sig_p = jax.tree.map(lambda a: a[perm] if (a.ndim >= 1 and a.shape[0] == n) else a, sig)
    x, xp = jax.jit(lambda s, sp: (model.design(s, jnp.zeros((0,), s.gyro.dtype)),
                                   model.design(sp, jnp.zeros((0,), s.gyro.dtype))))(sig, sig_p)
    x, xp = np.asarray(x), np.asarray(xp)
    p = x.shape[-1]
    # pointwise: the columns of a reordered recording are the reordered columns
    pointwise = np.allclose(xp, x[perm], rtol=1e-12, atol=0.0)
    # distinct products: the count (1) first, then column products in order
    reps, vals = [None], [np.ones(n)]
    a_map = np.zeros((3, p, p), np.int64)
    for i in range(3):
        for a in range(p):
            for b in range(a, p):
                v = x[:, i, a] * x[:, i, b]
                scale = np.max(np.abs(v)) + 1e-300
                k = next((j for j, u in enumerate(vals)
                          if np.max(np.abs(u - v)) <= 1e-12 * scale), None)
                if k is None:
                    k = len(vals)
                    reps.append((a, b, i))
                    vals.append(v)
                a_map[i, a, b] = a_map[i, b, a] = k
    const_col = None
    for term, sl, _ in model.slices():
        if term.name == "bias_poly":
            const_col = sl.start
    shared = tuple(bool(np.array_equal(x[:, 0, a], x[:, 1, a]) and
                        np.array_equal(x[:, 0, a], x[:, 2, a])) for a in range(p))
    layout = Layout(p=p, xx=tuple(reps[1:]), a_map=tuple(a_map.ravel().tolist()), shared=shared,
                    const_col=const_col) if pointwise else None
    # which inputs matter (and the sampling interval, through dT/dt)
    dtype = jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32
    shapes = {"t": (n,), "rate": (n, 3), "temp": (n,), "temp_ext": (n,), "accel": (n, 3)}
    names = [k for k in INPUTS if k in present or k == "t"]

    def f(dt, *arrays):
        kw = dict(zip(names, arrays))
        s = make_signals(kw.pop("t"), jnp.zeros((n, 3), dtype), jnp.ones(n, bool), **kw, dt=dt)
        out = [model.design(s, jnp.zeros((0,), dtype))]
        if model.deterministic:
            out.append(model.range_problems(s))
        return out

    closed = jax.make_jaxpr(f)(jax.ShapeDtypeStruct((), dtype),
                               *[jax.ShapeDtypeStruct(shapes[k], dtype) for k in names])
    _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    need = {name for name, u in zip(["dt", *names], used) if u}
    return layout, frozenset(need)


def applicable(model: ErrorModel, batch: Batch) -> bool:
    """Whether the sums path can fit ``model`` on ``batch`` (linear, pointwise columns)."""
    return model.is_linear and layout_of(model, frozenset(batch.signals))[0] is not None


def _products(layout: Layout, sig: Signals, model: ErrorModel, y0, mask):
    """Per-sample products in the order of :meth:`Layout.index`; masked samples give 0.

    The mask is applied once to each column and rate (products of masked
    factors are masked), and a column equal on all axes is formed once.
    """
    dtype = sig.gyro.dtype
    x = model.design(sig, jnp.zeros((0,), dtype))
    ys = sig.gyro - sig.rate - y0

    def col(i, a):
        return jnp.where(mask, x[..., 0 if layout.shared[a] else i, a], 0.0)

    yw = [jnp.where(mask, ys[..., i], 0.0) for i in range(3)]
    ops = [mask.astype(dtype)]
    ops += [col(i, a) * col(i, b) for a, b, i in layout.xx]
    ops += [yw[i] * col(i, a) for i in range(3) for a in range(layout.p)]
    ops += [yw[i] * yw[i] for i in range(3)]
    return ops


def _vsum(ops, axis: int = -1):
    """Sums of many arrays along one axis in a single loop (an XLA variadic reduce)."""
    axis = axis % ops[0].ndim
    zero = (jnp.zeros((), ops[0].dtype),) * len(ops)
    out = lax.reduce(tuple(ops), zero, lambda u, v: tuple(a + b for a, b in zip(u, v)), (axis,))
    return jnp.stack(out, axis=-1)


def _block_positions(mask, nv, n_blocks: int, prefix: bool):
    """First sample index of every time block of the folds (n_blocks + 1 values).

    Block b holds the valid samples of rank ceil(b·n/B) .. ceil((b+1)·n/B) − 1,
    the blocks of :func:`diffgyro.fit._fold_ids`. With the valid samples first
    (``prefix``), a rank is its index; otherwise ranks come from a cumulative count.
    """
    b = jnp.arange(n_blocks + 1, dtype=jnp.int32)
    rank = (b * nv + n_blocks - 1) // n_blocks
    if prefix:
        return rank
    cm = jnp.cumsum(mask.astype(jnp.int32))
    return jnp.searchsorted(cm, rank + 1, side="left").astype(jnp.int32)


def _fold_sums(model, layout, sig, y0, mask, nv, n_blocks: int, n_folds: int, c: int,
               prefix: bool):
    """Total and per-fold sums of every product, reading the samples once.

    Chunks of ``c`` samples (no longer than the shortest block) are summed in
    one variadic reduction and credited to the fold of their first sample. The
    chunks a block boundary cuts are summed again up to the boundary (a second,
    small reduction over just those chunks) and the rest is moved to the next
    block's fold.
    """
    n = mask.shape[0]
    nc = n // c
    ops = _products(layout, sig, model, y0, mask)
    tot = _vsum([o.reshape(nc, c) for o in ops])  # (nc, F)
    pos = _block_positions(mask, nv, n_blocks, prefix)
    starts = jnp.arange(nc, dtype=jnp.int32) * c
    if prefix:
        blk = (starts * n_blocks) // jnp.maximum(nv, 1)
    else:
        blk = jnp.searchsorted(pos, starts, side="right").astype(jnp.int32) - 1
    folds = jnp.arange(n_folds, dtype=jnp.int32)
    per_fold = ((blk % n_folds)[None, :] == folds[:, None]).astype(tot.dtype) @ tot
    # chunks cut by a block's start: sum the part before it once more
    p = pos[:-1]
    ch = jnp.minimum(p // c, nc - 1)
    cut = (p % c != 0) & (p < n)
    idx = (ch[:, None] * c + jnp.arange(c, dtype=jnp.int32)[None, :]).reshape(-1)
    head_mask = (idx.reshape(-1, c) < p[:, None]).reshape(-1) & mask[idx]
    sig_h = jax.tree.map(lambda a: a[idx] if (a.ndim >= 1 and a.shape[0] == n) else a, sig)
    head = _vsum([o.reshape(-1, c) for o in _products(layout, sig_h, model, y0, head_mask)])
    late = jnp.where(cut[:, None], tot[ch] - head, 0.0)  # belongs to the next block
    b = jnp.arange(n_blocks, dtype=jnp.int32)  # block -1 (before the first valid sample) is fold -1
    move = (((b % n_folds)[None, :] == folds[:, None]).astype(late.dtype)
            - (((b - 1) % n_folds)[None, :] == folds[:, None]).astype(late.dtype))
    return jnp.sum(tot, axis=0), per_fold + move @ late


def _cholesky(a):
    """Cholesky factors of the column-scaled Gram matrices (..., p, p) and the column scales.

    A matrix that is not finite gives NaN (one degenerate device never stops the batch).
    """
    from .fit import _scaled

    g, d = _scaled(a)
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    ok = jnp.all(jnp.isfinite(g), axis=(-2, -1))[..., None, None]
    chol = jnp.linalg.cholesky(jnp.where(ok, g, eye))
    return jnp.where(ok, chol, jnp.nan), d


def _cho_solve(chol, d, c):
    z = jax.scipy.linalg.cho_solve((chol, True), (c / d)[..., None])[..., 0]
    return z / d


def _unpack(layout: Layout, s):
    a_idx, c_idx, q_idx = layout.index()
    return s[..., a_idx], s[..., c_idx], s[..., q_idx], s[..., 0]


def _sse(a, c, q, beta):
    """Σ (y − xβ)² per axis from the sums A, c, Q."""
    return q - 2.0 * jnp.einsum("...ip,...ip->...i", beta, c) + jnp.einsum(
        "...ip,...ipq,...iq->...i", beta, a, beta)


def _device(model: ErrorModel, layout: Layout, opts, c: int, prefix: bool, t, gyro, mask, rate,
            temp, temp_ext, accel, centre, scale, dt, nv):
    from . import fit as F

    p = layout.p
    dtype = gyro.dtype
    norm = None
    if temp is not None:
        norm = temp_norm_from(temp, mask) if centre is None else TempNorm(centre=centre, scale=scale)
    t = jnp.zeros(mask.shape, dtype) if t is None else t
    sig = make_signals(t, gyro, mask, rate=rate, temp=temp, temp_ext=temp_ext, accel=accel,
                       norm=norm, dtemp_window=opts.dtemp_window, dt=dt)
    if temp is not None:  # the same T_s with a multiply instead of a divide per sample
        inv = 1.0 / norm.scale
        sig = eqx.tree_at(lambda s_: s_.temp_s, sig, temp * inv - norm.centre * inv)
    y = sig.gyro - sig.rate
    if layout.const_col is not None:
        y0 = y[jnp.argmax(mask)]
    else:
        y0 = jnp.zeros((3,), dtype)
    tot, per_fold = _fold_sums(model, layout, sig, y0, mask, nv, opts.n_blocks, opts.n_folds, c,
                               prefix)
    a, cc, q, n_valid = _unpack(layout, tot)
    af, cf, qf, nf = _unpack(layout, per_fold)

    # full fit
    chol, dsc = _cholesky(a)
    beta_s = _cho_solve(chol, dsc, cc)
    ratio, direction, rank_ok = F.rank_check(a, opts.rank_tol)
    sse = jnp.maximum(_sse(a, cc, q, beta_s), 0.0)
    shift = jnp.zeros((3, p), dtype)
    if layout.const_col is not None:
        shift = shift.at[:, layout.const_col].set(y0)
    beta = beta_s + shift
    rms = jnp.sqrt(jnp.sum(sse) / jnp.maximum(3 * n_valid, 1.0))

    # held-out folds: train on total − fold, score on the fold's own sums
    beta_f = _cho_solve(*_cholesky(a[None] - af), cc[None] - cf)
    sse_f = jnp.sum(jnp.maximum(_sse(af, cf, qf, beta_f), 0.0), axis=-1)
    heldout_rms = jnp.sqrt(jnp.sum(sse_f) / jnp.maximum(3 * jnp.sum(nf), 1.0))
    fold_mse = sse_f / jnp.maximum(3 * nf, 1.0)

    # covariance of the linear coefficients: block diagonal, σ_i² (X_iᵀX_i)⁻¹ per axis
    dof = jnp.maximum(n_valid - p, 1.0)
    sigma2 = jnp.maximum(sse / dof, 1e-300)
    eye = jnp.broadcast_to(jnp.eye(p, dtype=dtype), (3, p, p))
    inv = jax.scipy.linalg.cho_solve((chol, True), eye) / (dsc[:, :, None] * dsc[:, None, :])
    cov = jax.scipy.linalg.block_diag(*[inv[i] * sigma2[i] for i in range(3)])

    if opts.noise_floor:
        noise_axes = F._noise_floor(y, mask)
    else:
        noise_axes = jnp.full((3,), jnp.nan, dtype)
    terms = model.deterministic
    range_flags = model.range_problems(sig) > 0 if terms else jnp.zeros((0,), bool)
    owner = jnp.asarray([terms.index(tm) for tm in model.column_terms()], jnp.int32)
    weak = (jnp.abs(direction) > 0.3) & (~rank_ok[:, None])
    collinear = jnp.zeros((len(terms),), bool).at[owner].max(jnp.any(weak, axis=0)) if p else \
        jnp.zeros((len(terms),), bool)
    finite = jnp.all(jnp.isfinite(beta)) & jnp.isfinite(rms)
    status = jnp.where(
        n_valid < max(2 * p, p + 4), F.INSUFFICIENT_DATA,
        jnp.where(jnp.any(range_flags), F.INSUFFICIENT_RANGE,
                  jnp.where(~jnp.all(rank_ok), F.RANK_DEFICIENT,
                            jnp.where(finite, F.OK, F.FAILED))))
    out = dict(beta=beta, theta=jnp.zeros((0,), dtype), cov=cov, rms=rms,
               heldout_rms=heldout_rms, fold_mse=fold_mse,
               noise_floor=jnp.sqrt(jnp.mean(noise_axes**2)), noise_axes=noise_axes,
               sigma=jnp.sqrt(sigma2), steps=jnp.asarray(1, jnp.int32),
               status=jnp.asarray(status, jnp.int32), range_flags=range_flags,
               collinear=collinear, rank_ratio=jnp.min(ratio), n_samples=n_valid)
    if temp is not None:
        out["temp_range"] = jnp.stack([jnp.min(jnp.where(mask, temp, jnp.inf)),
                                       jnp.max(jnp.where(mask, temp, -jnp.inf))])
    if sig.norm is not None:
        out["norm_centre"], out["norm_scale"] = sig.norm.centre, sig.norm.scale
    return out


@eqx.filter_jit
def _group(model, layout, opts, c, prefix, t, gyro, mask, rate, temp, temp_ext, accel, centre,
           scale, dt, nv):
    from . import fit as F

    F.TRACE_COUNTS["sums"] += 1

    def one(*args):
        return _device(model, layout, opts, c, prefix, *args)

    return jax.vmap(one)(t, gyro, mask, rate, temp, temp_ext, accel, centre, scale, dt, nv)


def _pow2_floor(x: int) -> int:
    return 1 << (max(int(x), 1).bit_length() - 1)


def group_size(n_devices: int, length: int) -> int:
    """Devices per compiled call: a power of two, about GROUP_SAMPLES samples, ≥ 8 devices
    only when the batch has them (5 and 7 devices share a group size of 8)."""
    cap = _pow2_floor(max(GROUP_SAMPLES // max(length, 1), 1))
    want = 1 << max(int(n_devices) - 1, 7).bit_length()  # next power of two ≥ n, at least 8
    return max(1, min(cap, want))


def chunk_size(min_valid: int, n_blocks: int, length: int) -> int:
    """Chunk of the reduction: a power of two dividing the length, no longer than the
    shortest fold block (so a chunk holds at most one block boundary)."""
    c = min(CHUNK, _pow2_floor(max(min_valid // max(n_blocks, 1), 1)), length & -length)
    return max(c, 1)


def solve_sums(model: ErrorModel, batch: Batch, norm: TempNorm | None, opts, dtype=np.float64):
    """Fit every device of ``batch`` with the sums path; numpy arrays with a device axis.

    Raises ValueError if the model's columns are not functions of each sample's
    own signals (use the direct path then).
    """
    from .fit import sampling_intervals

    present = frozenset(batch.signals)
    layout, need = layout_of(model, present)
    if layout is None:
        raise ValueError(f"model {model.spec!r} has columns that read other samples; "
                         "the sums path cannot fit it (use path='direct')")
    d, n = batch.n_devices, batch.length
    g = group_size(d, n)
    dt = sampling_intervals(batch) if "dt" in need else np.ones(d)
    centre = scale = None
    if norm is not None and batch.temp is not None:
        centre = np.broadcast_to(np.asarray(norm.centre, dtype), (d,))
        scale = np.broadcast_to(np.asarray(norm.scale, dtype), (d,))
    arrays = {"gyro": batch.gyro, "mask": batch.mask, "centre": centre, "scale": scale, "dt": dt}
    for k in INPUTS:
        arr = getattr(batch, k)
        # the reference rate is always read: the fit is of gyro − rate
        arrays[k] = arr if (arr is not None and (k in need or k in ("temp", "rate"))) else None
    if "t" not in need:
        arrays["t"] = None
    devices = jax.local_devices()
    order = ("t", "gyro", "mask", "rate", "temp", "temp_ext", "accel", "centre", "scale", "dt")
    ramp = np.arange(n)

    def run(j: int) -> dict:
        start = j * g
        stop = min(start + g, d)
        sl = slice(start, stop) if stop - start == g else np.minimum(np.arange(start, start + g),
                                                                    stop - 1)
        mask = np.asarray(batch.mask[sl], bool)
        nv = np.count_nonzero(mask, axis=1)
        prefix = bool(np.array_equal(mask, ramp[None, :] < nv[:, None]))
        c = chunk_size(int(nv.min()), opts.n_blocks, n)
        dev = devices[j % len(devices)]
        args = []
        for k in order:
            a = arrays[k]
            if a is None:
                args.append(None)
            elif k == "mask":
                args.append(jax.device_put(mask, dev))
            else:
                args.append(jax.device_put(np.ascontiguousarray(np.asarray(a[sl], dtype)), dev))
        args.append(jax.device_put(nv.astype(np.int32), dev))
        out = _group(model, layout, opts, c, prefix, *args)
        return {k: np.asarray(v)[:stop - start] for k, v in out.items()}

    n_groups = -(-d // g)
    if n_groups == 1:
        outs = [run(0)]
    else:  # XLA runs each call on the calling thread (on CPU): one caller per core
        workers = min(n_groups, max(len(devices), os.cpu_count() or 1))
        with ThreadPoolExecutor(workers) as pool:
            outs = list(pool.map(run, range(n_groups)))
    return {k: np.concatenate([o[k] for o in outs], axis=0) for k in outs[0]}
