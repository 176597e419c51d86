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

Time constants (variable projection): the linear coefficients are solved from
the sums for every trial, Newton moves the log time constants alone. Products
that do not move with them are summed once (total and per fold); a trial forms
only the moving columns with their two derivatives (one recursion for
thermal_lag, forward mode otherwise) and sums the moving products and their
derivatives in one reduction, which gives the projected cost's value, gradient
and Hessian from one pass. The held-out folds refit from the full optimum; the
full fit and the folds are problems of one Newton loop, solved in turn, so the
evaluation is compiled once.

Devices are processed in groups of a fixed size on the host (and spread over
every local accelerator), so only the group size — not the number of devices —
is part of the compiled shape. Models with time constants take smaller groups:
their batched Newton loops step in lockstep with the group's slowest device.
The group program may reassociate its sums (:data:`REASSOCIATE`), is compiled for
compile time unless it is a fused linear model's (:data:`FAST_COMPILE`), and returns
its results packed in one array per group; the model-free noise floor is computed on
the host's threads meanwhile (:mod:`diffgyro.noise`). Unless the model is fused linear,
the group program stops at the sums and the finish (:func:`_finish`: solves,
covariance, rank check, status; small dense algebra) is a program of its own,
compiled without optimisation on a thread while the group program compiles: the
model-discovery loop compiles a program per spec, and each kernel costs compile time.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.interpreters import partial_eval as pe
from jaxtyping import Bool

from .core import TRACE_COUNTS, fit_status, fold_ids, min_samples, sampling_intervals
from .data import AUX_PREFIX, Batch, aux_key
from .jit import collector_paused, filter_jit, parallel_devices
from .linalg import rank_check, scale_gram
from .model import ErrorModel
from .noise import start as host_noise
from .signals import Signals, TempNorm, make_signals, masked_range, temp_norm_from
from .status import collinear_terms

#: Longest sample chunk of the variadic reduction (shortened to the shortest fold block).
CHUNK = 32
#: About this many samples (devices × samples) go into one compiled call.
GROUP_SAMPLES = 1 << 17
#: Models whose columns are all shared by the three axes and pointwise (temperature
#: polynomials, gradient, temp_diff) sum in one fused pass with no group-sized
#: temporaries: their groups are this many times larger (fewer calls). Others
#: materialise per-axis columns and run fastest with the group in cache: on a
#: 2-core CPU with 32 MB L3, S2's regression at 10 000 samples runs about twice as fast
#: in groups of 8 devices as of 16, and bias_poly(3) fastest in groups of 64.
FUSED_GROUP_FACTOR = 8
#: Models with time constants run batched Newton loops in lockstep: a group takes as
#: many passes as its slowest device needs for the full fit and the folds' refits.
#: Their groups hold this many times fewer samples (at least 2 devices): at 10 000
#: samples per device that is 2 devices, which fits bias_poly(1)+thermal_lag fastest
#: (smaller groups wait less for their slowest device; a single device per call pays
#: the call overhead); at 2000 samples the group size hardly matters.
NONLINEAR_GROUP_DIVISOR = 4
#: Most devices in one compiled call. XLA's CPU runtime (jax 0.10) can hang on very
#: large groups (1024 devices × 640 samples on one CPU device; two groups of 256 side
#: by side on two CPU devices), all threads idle; groups of 128 run at every length from
#: 200 to 10 000 samples. Short recordings would otherwise ask for such groups.
MAX_GROUP_DEVICES = 128
#: XLA options of the group program: its sums may be reassociated, which lets LLVM
#: vectorise the variadic reduction (XLA keeps every sum in source order otherwise, one
#: scalar accumulator per product). NaN, ±inf, division and library functions keep
#: their IEEE meaning. Sums agree with the ordered ones to rounding (about 5e-13
#: relative on the benchmark's bias_poly(3)) and run faster (bias_poly(3) by 7 %,
#: thermal_lag by about 15 %).
REASSOCIATE = dict(xla_cpu_enable_fast_math=True, xla_cpu_fast_math_honor_nans=True,
                   xla_cpu_fast_math_honor_infs=True, xla_cpu_fast_math_honor_division=True,
                   xla_cpu_fast_math_honor_functions=True)
#: XLA options of every group program but a fused linear model's: XLA's older loop
#: emitters instead of its MLIR fusion emitters. Such a program has many kernels (a
#: Newton loop, the lag recursions, per-axis columns, small factorisations) and XLA
#: spends most of its compile time emitting and optimising them one by one. The older
#: emitters compile such a program in about 60 % of the time and run it 9-14 % slower,
#: the right trade for the model-discovery loop, which compiles a program per spec and
#: fits each once. Fused linear models (every column shared by the axes: bias_poly and
#: the like) keep the fusion emitters: their one pass over the samples runs at memory
#: speed.
FAST_COMPILE = dict(xla_cpu_use_fusion_emitters=False)
#: XLA options of a tiny program run once (LLVM without optimisation passes).
ONCE = dict(xla_backend_optimization_level=0, xla_cpu_use_fusion_emitters=False)
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
    pointwise: bool = eqx.field(static=True)  # columns read only their own sample's signals
    const_col: int | None = eqx.field(static=True)
    moving: tuple = eqx.field(static=True, default=())  # per column: moves with the time constants

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
    """Signals of n samples with every field random (no derived-signal computation).

    numpy arrays: JAX operations on them one by one would each compile (tens of ms)."""
    rng = np.random.default_rng(seed)
    r = rng.normal
    has = {k: k in present for k in INPUTS}
    temp = rng.uniform(10, 40, n) if has["temp"] else None
    return Signals(
        t=np.cumsum(rng.uniform(0.5, 1.5, n)), gyro=r(size=(n, 3)), mask=np.ones(n, bool),
        rate=r(size=(n, 3)), temp=temp, temp_s=r(size=n) if has["temp"] else None,
        dtemp=r(size=n) if has["temp"] else None,
        heating=np.sign(r(size=n)) if has["temp"] else None,
        temp_ext=rng.uniform(0, 30, n) if has["temp_ext"] else None,
        accel=r(size=(n, 3)) if has["accel"] else None,
        norm=TempNorm(centre=np.asarray(25.0), scale=np.asarray(15.0)) if has["temp"] else None,
        has_rate=has["rate"], aux={k[len(AUX_PREFIX):]: r(size=n) for k in _aux_inputs(present)})


def _aux_inputs(present: frozenset[str]) -> list[str]:
    """The extra-column inputs (``aux:NAME``) among ``present``, in order."""
    return sorted(k for k in present if k.startswith(AUX_PREFIX))


@filter_jit(compiler_options=ONCE)
def _probe_designs(model: ErrorModel, thetas, sig: Signals, sig_p: Signals) -> list:
    """The design at every trial θ on the probe's signals and on their reordering (one
    design traced, vmapped over the four: a quarter of the trace and of the kernels)."""
    k = len(thetas)
    both = jax.tree.map(lambda a, b: jnp.stack([a] * k + [b] * k), sig, sig_p)
    x = jax.vmap(model.design)(both, jnp.stack(list(thetas) * 2))
    return [x[i + j * k] for i in range(k) for j in range(2)]


@functools.lru_cache(maxsize=256)
def layout_of(model: ErrorModel, present: frozenset[str]) -> tuple[Layout, frozenset[str]]:
    """The model's product layout and the inputs its columns and range checks read.

    Evaluated once per model on random signals: which columns are equal on all
    axes, which column products coincide (at two sets of time constants), which
    columns move with the time constants, and
    whether every column is a function of its own sample's signals (linear
    models that are not take the direct path). Which inputs are read — and whether the sampling
    interval (dT/dt) matters — comes from dead-code elimination of the trace.
    """
    n, q = 24, model.n_nonlinear
    sig = _random_signals(present, n, 12345)
    perm = np.random.default_rng(1).permutation(n)
    sig_p = jax.tree.map(lambda a: a[perm] if (a.ndim >= 1 and a.shape[0] == n) else a, sig)
    # two sets of time constants (log s): a coincidence at one is not at the other
    thetas = [np.full((q,), v, sig.gyro.dtype) for v in ((2.3, 4.1) if q else (0.0,))]
    # 24 samples, run once per model: compiled for compile time, not speed, on a thread
    # while this one finds the inputs the model reads
    ahead = _probe_designs.compile_ahead(model, thetas, sig, sig_p)
    need = _inputs_read(model, present, n, q)
    ahead.join()
    xs = [np.asarray(v) for v in _probe_designs(model, thetas, sig, sig_p)]
    p = xs[0].shape[-1]
    # pointwise: the columns of a reordered recording are the reordered columns
    pointwise = all(np.allclose(b, a[perm], rtol=1e-12, atol=0.0) for a, b in zip(xs[::2], xs[1::2]))
    # distinct products: the count (1) first, then column products in order
    reps, vals = [None], [np.ones(n * len(thetas))]
    xall = np.concatenate(xs[::2], axis=0)
    a_map = np.zeros((3, p, p), np.int64)
    for i in range(3):
        for a in range(p):
            for b in range(a, p):
                v = xall[:, i, a] * xall[:, i, b]
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
        if term.constant_bias:
            const_col = sl.start
    shared = tuple(bool(np.array_equal(xall[:, 0, a], xall[:, 1, a]) and
                        np.array_equal(xall[:, 0, a], xall[:, 2, a])) for a in range(p))
    moving = tuple(bool(np.any(xs[0][..., a] != xs[-2][..., a])) for a in range(p))
    layout = Layout(p=p, xx=tuple(reps[1:]), a_map=tuple(a_map.ravel().tolist()), shared=shared,
                    const_col=const_col, pointwise=bool(pointwise), moving=moving)
    return layout, need


def _inputs_read(model: ErrorModel, present: frozenset[str], n: int, q: int) -> frozenset[str]:
    """The inputs the model's columns and range checks read (and "dt" when the sampling
    interval matters, through dT/dt), by dead-code elimination of their trace."""
    dtype = jnp.float64 if jax.config.read("jax_enable_x64") else jnp.float32
    shapes = {"t": (n,), "rate": (n, 3), "temp": (n,), "temp_ext": (n,), "accel": (n, 3)}
    shapes.update({k: (n,) for k in _aux_inputs(present)})
    names = [k for k in INPUTS if k in present or k == "t"] + _aux_inputs(present)

    def f(dt, *arrays):
        kw = dict(zip(names, arrays))
        aux = {k[len(AUX_PREFIX):]: kw.pop(k) for k in _aux_inputs(present)}
        s = make_signals(kw.pop("t"), jnp.zeros((n, 3), dtype), jnp.ones(n, bool), **kw, dt=dt,
                         aux=aux)
        out = [model.design(s, jnp.zeros((q,), dtype))]
        if model.deterministic:
            out.append(model.range_problems(s))
        return out

    closed = jax.make_jaxpr(f)(jax.ShapeDtypeStruct((), dtype),
                               *[jax.ShapeDtypeStruct(shapes[k], dtype) for k in names])
    _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    return frozenset(name for name, u in zip(["dt", *names], used) if u)


def _products(layout: Layout, x, ys, mask):
    """Per-sample products of design ``x`` (..., 3, p) and rates ``ys`` (..., 3) in the order
    of :meth:`Layout.index`; masked samples give 0.

    The mask is applied once to each column and rate (products of masked
    factors are masked), and a column equal on all axes is formed once.
    """
    @functools.cache
    def masked(ax, a):  # traced once per column and axis
        return jnp.where(mask, x[..., ax, a], 0.0)

    def col(i, a):
        return masked(0 if layout.shared[a] else i, a)

    yw = [jnp.where(mask, ys[..., i], 0.0) for i in range(3)]
    ops = [mask.astype(ys.dtype)]
    ops += [col(i, a) * col(i, b) for a, b, i in layout.xx]
    ops += [yw[i] * col(i, a) for i in range(3) for a in range(layout.p)]
    ops += [yw[i] * yw[i] for i in range(3)]
    return ops


def _signal_products(layout: Layout, model: ErrorModel, theta, y0):
    """Products of a recording's signals through the model's design (a pointwise model)."""
    def products(sig, mask):
        x = model.design(sig, theta)
        return _products(layout, x, sig.gyro - sig.rate - y0, mask)

    return products


def _design_products(layout: Layout):
    """Products of a precomputed design and rates, given as the pair (x, ys)."""
    def products(xy, mask):
        return _products(layout, xy[0], xy[1], mask)

    return products


@jax.custom_jvp
def _vsum_stacked(ops):
    zero = (jnp.zeros((), ops[0].dtype),) * len(ops)
    out = lax.reduce(tuple(ops), zero, lambda u, v: tuple(a + b for a, b in zip(u, v)),
                     (ops[0].ndim - 1,))
    return jnp.stack(out, axis=-1)


@_vsum_stacked.defjvp
def _vsum_jvp(primals, tangents):
    (ops,), (dops,) = primals, tangents
    return _vsum_stacked(ops), _vsum_stacked(dops)


def _vsum(ops):
    """Sums of many arrays along their last axis in a single loop (an XLA variadic reduce),
    stacked on a new last axis."""
    return _vsum_stacked(list(ops))


def _block_positions(mask, nv, n_blocks: int):
    """First sample index of every time block of the folds (n_blocks + 1 values).

    Block b holds the valid samples of rank ceil(b·n/B) .. ceil((b+1)·n/B) − 1,
    the blocks of :func:`diffgyro.core.fold_ids`; ranks come from a cumulative count
    (devices whose valid samples come first get the starts from the host instead).
    """
    b = jnp.arange(n_blocks + 1, dtype=jnp.int32)
    rank = (b * nv + n_blocks - 1) // n_blocks
    cm = jnp.cumsum(mask.astype(jnp.int32))
    return jnp.searchsorted(cm, rank + 1, side="left").astype(jnp.int32)


def block_starts(nv, n_blocks: int) -> np.ndarray:
    """First sample of every fold block (and the end), (devices, B + 1), when each
    device's valid samples come first: block b starts at rank ceil(b·n/B)."""
    b = np.arange(n_blocks + 1, dtype=np.int64)
    nv = np.asarray(nv, np.int64)[:, None]
    return ((b * nv + n_blocks - 1) // n_blocks).astype(np.int32)


ALIGNED = "aligned"
"""``pos`` for a group whose devices are all valid to the end of a length that the
blocks divide: block b is the samples b·w .. (b + 1)·w − 1, a reshape (no gather,
no mask)."""


def _window_sums(products, src, pos, n_blocks: int, n_folds: int):
    """Total and per-fold sums when the valid samples come first (``prefix``).

    Block b is then the samples ceil(b·n/B) .. ceil((b+1)·n/B) − 1: a window of
    ceil(length/B) samples from its start, masked past its end, covers it. One
    variadic reduction over the (B, window) gathered samples gives every block's
    sums exactly; a fold's sums are those of its blocks. The window depends only
    on the padded length, so recordings of any length in a bucket share the
    compiled function. ``pos`` (the B + 1 block starts, :func:`block_starts`) comes
    from the host: computed in the graph, XLA would recompute it for every sample.
    """
    n = jax.tree.leaves(src)[0].shape[0]
    if isinstance(pos, str):  # ALIGNED
        blocks = _vsum([o.reshape(n_blocks, n // n_blocks)
                        for o in products(src, jnp.ones((n,), bool))])
        return _fold_of_blocks(blocks, n_blocks, n_folds)
    w = -(-n // n_blocks)
    start = jnp.minimum(pos[:-1], n - w)  # a window never runs past the recording
    j = start[:, None] + jnp.arange(w, dtype=jnp.int32)[None, :]
    inside = ((j >= pos[:-1, None]) & (j < pos[1:, None])).reshape(-1)

    def windows(a):
        if a.ndim >= 1 and a.shape[0] == n:
            cut = jax.vmap(lambda s_: lax.dynamic_slice_in_dim(a, s_, w, axis=0))(start)
            return cut.reshape(n_blocks * w, *a.shape[1:])
        return a

    blocks = _vsum([o.reshape(n_blocks, w) for o in products(jax.tree.map(windows, src), inside)])
    return _fold_of_blocks(blocks, n_blocks, n_folds)


def _fold_of_blocks(blocks, n_blocks: int, n_folds: int):
    """Total and per-fold sums from the sums of every block (B, F); block b is in fold b mod K."""
    b = jnp.arange(n_blocks, dtype=jnp.int32)
    own = ((b % n_folds)[None, :] == jnp.arange(n_folds, dtype=jnp.int32)[:, None])
    return jnp.sum(blocks, axis=0), own.astype(blocks.dtype) @ blocks


def _fold_sums(products, src, mask, nv, n_blocks: int, n_folds: int, c: int, pos=None):
    """Total and per-fold sums of every product, reading the samples once.

    ``products(src, mask)`` gives the per-sample products of ``src`` (a pytree
    of arrays with the sample axis first). Chunks of ``c`` samples (no longer
    than the shortest block) are summed in one variadic reduction and credited
    to the fold of their first sample. The chunks a block boundary cuts are
    summed again up to the boundary (a second, small reduction over just those
    chunks, gathered from ``src``) and the rest is moved to the next block's fold.
    Given the block starts ``pos`` (valid samples first), the blocks are summed in
    windows instead (:func:`_window_sums`).
    """
    if pos is not None:
        return _window_sums(products, src, pos, n_blocks, n_folds)
    n = mask.shape[0]
    nc = n // c
    ops = products(src, mask)
    tot = _vsum([o.reshape(nc, c) for o in ops])  # (nc, F)
    pos = _block_positions(mask, nv, n_blocks)
    starts = jnp.arange(nc, dtype=jnp.int32) * c
    blk = jnp.searchsorted(pos, starts, side="right").astype(jnp.int32) - 1
    folds = jnp.arange(n_folds, dtype=jnp.int32)
    per_fold = ((blk % n_folds)[None, :] == folds[:, None]).astype(tot.dtype) @ tot
    # chunks cut by a block's start: sum the part before it once more
    p = pos[:-1]
    ch = jnp.minimum(p // c, nc - 1)
    cut = (p % c != 0) & (p < n)
    idx = (ch[:, None] * c + jnp.arange(c, dtype=jnp.int32)[None, :]).reshape(-1)
    head_mask = (idx.reshape(-1, c) < p[:, None]).reshape(-1) & mask[idx]
    src_h = jax.tree.map(lambda a: a[idx] if (a.ndim >= 1 and a.shape[0] == n) else a, src)
    head = _vsum([o.reshape(-1, c) for o in products(src_h, head_mask)])
    late = jnp.where(cut[:, None], tot[ch] - head, 0.0)  # belongs to the next block
    b = jnp.arange(n_blocks, dtype=jnp.int32)  # block -1 (before the first valid sample) is fold -1
    move = (((b % n_folds)[None, :] == folds[:, None]).astype(late.dtype)
            - (((b - 1) % n_folds)[None, :] == folds[:, None]).astype(late.dtype))
    return jnp.sum(tot, axis=0), per_fold + move @ late


def _cholesky(a):
    """Cholesky factors of the column-scaled Gram matrices (..., p, p) and the column scales.

    A matrix that is not finite gives NaN (one degenerate device never stops the batch).
    Finite is tested on the sum of the scaled entries (|g_ij| ≤ 1 where A is positive
    semidefinite): an all-reduction of isfinite compiled to 3× the code.
    """
    g, d = scale_gram(a)
    eye = jnp.eye(a.shape[-1], dtype=a.dtype)
    ok = jnp.isfinite(jnp.sum(g, axis=(-2, -1)))[..., None, None]
    chol = jnp.linalg.cholesky(jnp.where(ok, g, eye))
    return jnp.where(ok, chol, jnp.nan), d


def _cho_inverse(chol, d):
    """Inverse of the matrix whose :func:`_cholesky` factors are ``chol`` and ``d``."""
    eye = jnp.broadcast_to(jnp.eye(chol.shape[-1], dtype=chol.dtype), chol.shape)
    return jax.scipy.linalg.cho_solve((chol, True), eye) / (d[..., :, None] * d[..., None, :])


def _cho_solve(chol, d, c):
    z = jax.scipy.linalg.cho_solve((chol, True), (c / d)[..., None])[..., 0]
    return z / d


def _unpack(layout: Layout, s):
    """A, c, Q and the count from the product vector(s) ``s`` (..., P); c and Q by static
    slices (an index array is a gather, a kernel of its own)."""
    a_idx, c_idx, q_idx = layout.index()
    lead = s.shape[:-1]
    a = s[..., a_idx]
    c = s[..., int(c_idx[0, 0]):int(c_idx[-1, -1]) + 1].reshape(lead + c_idx.shape)
    return a, c, s[..., int(q_idx[0]):int(q_idx[-1]) + 1], s[..., 0]


def _unpack_split(layout: Layout, fixed, moving):
    """:func:`_unpack` of the products whose fixed ones (:func:`varying_products`) are
    ``fixed`` and moving ones ``moving``, by one gather from the two side by side;
    ``fixed`` None: the fixed products are zero (derivatives)."""
    var_idx, fix_idx = varying_products(layout)
    src = np.zeros(layout.n_products, np.int32)
    src[var_idx] = np.arange(len(var_idx))
    if fixed is None:  # every fixed product reads the zero appended to the moving ones
        src[fix_idx] = len(var_idx)
        s = jnp.concatenate([moving, jnp.zeros(moving.shape[:-1] + (1,), moving.dtype)], axis=-1)
    else:
        src[var_idx] += len(fix_idx)
        src[fix_idx] = np.arange(len(fix_idx))
        fixed = jnp.broadcast_to(fixed, moving.shape[:-1] + fixed.shape[-1:])
        s = jnp.concatenate([fixed, moving], axis=-1)
    a_idx, c_idx, q_idx = layout.index()
    cuts = np.cumsum([a_idx.size, c_idx.size, q_idx.size])
    g = s[..., np.concatenate([src[a_idx].ravel(), src[c_idx].ravel(), src[q_idx], src[:1]])]
    lead = g.shape[:-1]
    return (g[..., :cuts[0]].reshape(lead + a_idx.shape), g[..., cuts[0]:cuts[1]].reshape(
        lead + c_idx.shape), g[..., cuts[1]:cuts[2]], g[..., cuts[2]])


def _sse(a, c, q, beta):
    """Σ (y − xβ)² per axis from the sums A, c, Q."""
    return q - 2.0 * jnp.einsum("...ip,...ip->...i", beta, c) + jnp.einsum(
        "...ip,...ipq,...iq->...i", beta, a, beta)


def _newton(evaluate, theta0, caps: tuple[int, ...], rtol, aux_shapes):
    """Minimise smooth functions of a few parameters (log time constants), one after another.

    ``evaluate(j, θ)`` gives problem j's value, gradient, Hessian and an aux pytree
    (of ``aux_shapes``: given, so that ``evaluate`` is traced once) in one pass over
    the samples. Problem 0 starts at ``theta0``, every later one at
    problem 0's optimum (the folds' refits start from the full fit's); problem j takes
    at most ``caps[j]`` steps. The problems share one loop, so ``evaluate`` is traced
    and compiled once, and each pass evaluates one problem, as many passes as steps.

    Newton steps: negative curvature is flipped and a Levenberg term damps the step,
    which is accepted only if the value does not grow (and is at most 1 in log τ);
    near a minimum (convex, Newton step below 1e-3) the plain Newton step is taken. A
    trial is evaluated once — its gradient and Hessian come with its value, so an
    accepted step needs no second pass. Converged when the Newton step at the current
    point is below ``rtol·(1 + |θ|)``. A problem's first pass evaluates its start.
    Returns per problem (theta, value, aux, steps, converged), stacked.
    """
    def proposal(th, g, h, lam):
        if th.shape[0] == 1:  # one time constant: the eigen-decomposition is the number
            e, vec = h[0], jnp.ones((1, 1), h.dtype)
        else:
            e, vec = jnp.linalg.eigh(0.5 * (h + h.T))
        convex = jnp.all(e > 0)
        e = jnp.abs(e)
        big = jnp.max(e) + 1e-300
        gv = vec.T @ g
        newton = -(vec @ (gv / jnp.maximum(e, 1e-300 * big)))
        scale_th = 1.0 + jnp.linalg.norm(th)
        size_n = jnp.linalg.norm(newton)
        # close to a minimum Newton converges quadratically and f's rounding noise (a
        # difference of sums) would veto its last steps: take them without the f test
        near = convex & (size_n <= 1e-3 * scale_th)
        step = -(vec @ (gv / (e + lam * big)))
        step = jnp.where(near, newton, step)
        size = jnp.linalg.norm(step)
        step = step * jnp.minimum(1.0, 1.0 / jnp.maximum(size, 1e-300))
        return step, near, size_n <= rtol * scale_th

    n_problems = len(caps)
    q, dtype = theta0.shape[0], theta0.dtype
    aux_leaves, aux_tree = jax.tree.flatten(aux_shapes)
    aux_sizes = [int(np.prod(a.shape, dtype=np.int64)) for a in aux_leaves]
    n_aux = sum(aux_sizes)
    # the whole state is one vector (counters as exact floats): under vmap the loop
    # keeps each device's state by one select, and XLA emits one kernel for it, not
    # one per carry. It holds j (problem), k (pass) and λ; f, θ, g, H and aux at the
    # current point; then per problem a row of θ, f, aux, steps and converged.
    point = 1 + q + q + q * q + n_aux  # f, θ, g, H, aux
    head = 3 + point
    row = q + 1 + n_aux + 2
    problems = jnp.arange(n_problems)
    caps_ = jnp.asarray(caps, dtype)

    def split_point(x):  # f, θ, g, H, aux of a point vector
        cuts = np.cumsum([1, q, q, q * q])
        f, th, g, h, aux = jnp.split(x, cuts)
        return f[0], th, g, h.reshape(q, q), aux

    def join_point(f, th, g, h, aux):
        return jnp.concatenate([f[None], th, g, h.reshape(-1), aux])

    def flat_aux(aux):
        return jnp.concatenate([a.reshape(-1).astype(dtype) for a in jax.tree.leaves(aux)])

    def body(state):
        j, k, lam = state[0], state[1], state[2]
        cur = state[3:head]
        out = state[head:].reshape(n_problems, row)
        v, th, g, h, aux = split_point(cur)
        first = k == 0
        step, near, _ = proposal(th, g, h, lam)
        step = jnp.where(first, 0.0, step)
        v_new, g_new, h_new, aux_new = evaluate(j.astype(jnp.int32), th + step)
        ok = jnp.isfinite(v_new) & ((v_new <= v) | near | first)
        cur = jnp.where(ok, join_point(v_new, th + step, g_new, h_new, flat_aux(aux_new)), cur)
        v, th, g, h, aux = split_point(cur)
        lam = jnp.where(first, lam, jnp.where(ok, lam * 0.3, lam * 10.0))
        # a start where the function is not finite ends the problem there
        done = (jnp.isfinite(v) & proposal(th, g, h, lam)[2]) | ~jnp.isfinite(v)
        k = k + 1
        end = done | (k > jnp.sum(jnp.where(problems == j, caps_, 0.0)))
        here = end & (problems == j)
        result = jnp.concatenate([th, v[None], aux, (k - 1)[None], done.astype(dtype)[None]])
        out = jnp.where(here[:, None], result[None], out)
        # the next problem starts afresh from problem 0's optimum
        restart = join_point(jnp.asarray(jnp.inf, dtype), out[0, :q], jnp.zeros_like(g),
                             jnp.eye(q, dtype=dtype), aux)
        cur = jnp.where(end, restart, cur)
        lam = jnp.where(end, 1e-3, lam)
        k = jnp.where(end, 0.0, k)
        return jnp.concatenate([jnp.stack([j + end, k, lam]), cur, out.reshape(-1)])

    def cond(state):
        return state[0] < n_problems

    # θ0 makes the state batched from the start under vmap: the loop's batching rule
    # then traces the body once, not twice
    init = jnp.concatenate([jnp.asarray([0.0, 0.0, 1e-3], dtype),
                            join_point(jnp.asarray(jnp.inf, dtype), theta0, jnp.zeros((q,), dtype),
                                       jnp.eye(q, dtype=dtype), jnp.zeros((n_aux,), dtype)),
                            jnp.zeros((n_problems * row,), dtype)])
    out = lax.while_loop(cond, body, init)[head:].reshape(n_problems, row)
    cuts = np.cumsum([0] + aux_sizes)
    aux = jax.tree.unflatten(aux_tree, [
        out[:, q + 1 + a:q + 1 + b].reshape((n_problems,) + leaf.shape).astype(leaf.dtype)
        for a, b, leaf in zip(cuts[:-1], cuts[1:], aux_leaves)])
    return (out[:, :q], out[:, q], aux, out[:, -2].astype(jnp.int32), out[:, -1] > 0.5)


def _product_jet(u, du, ddu, v, dv, ddv, q: int) -> list:
    """``u·v``, its first derivatives (q) and second derivatives (q·q, row-major) by the
    product rule; a derivative given as None is zero (a factor that does not move)."""
    def total(parts):
        parts = [t for t in parts if t is not None]
        return functools.reduce(lambda x, y: x + y, parts) if parts else jnp.zeros_like(u)

    def d1(k):
        return total([None if du is None else du[k] * v, None if dv is None else u * dv[k]])

    def d2(k, r):
        both = du is not None and dv is not None
        return total([None if ddu is None else ddu[k, r] * v,
                      None if ddv is None else u * ddv[k, r],
                      du[k] * dv[r] if both else None, du[r] * dv[k] if both else None])

    return [u * v] + [d1(k) for k in range(q)] + [d2(k, r) for k in range(q) for r in range(q)]


def _projected(sums, dsums, ddsums):
    """Value, gradient and Hessian of the projected cost ``Σ_i min_β Σ(y_i − x_iβ)²``
    from the sums (A, c, Q, count) of :func:`_unpack` and their derivatives (leading
    axes (q,) and (q, q)).

    With ``β = A⁻¹c`` stationary, ``f = Q − 2βᵀc + βᵀAβ`` has ``∂f = ∂Q − 2βᵀ∂c + βᵀ∂Aβ``
    and ``∂²f = ∂²Q − 2βᵀ∂²c + βᵀ∂²Aβ − 2 r_kᵀA⁻¹r_l`` with ``r = ∂c − ∂Aβ``: one
    factorisation of each A, no derivative of the factorisation itself.
    """
    a, c, q, _ = sums
    da, dc, dq, _ = dsums
    dda, ddc, ddq, _ = ddsums
    chol, d = _cholesky(a)
    beta = _cho_solve(chol, d, c)

    def first(a_, c_, q_):  # Σ_i ∂Q − 2βᵀ∂c + βᵀ∂Aβ over the leading axes
        return jnp.sum(q_ - 2.0 * jnp.einsum("ip,...ip->...i", beta, c_)
                       + jnp.einsum("ip,...ipr,ir->...i", beta, a_, beta), axis=-1)

    r = dc - jnp.einsum("kipr,ir->kip", da, beta)  # (q, 3, p)
    rhs = jnp.moveaxis(r, 0, -1) / d[..., None]  # (3, p, q)
    ar = jax.scipy.linalg.cho_solve((chol, True), rhs) / d[..., None]
    hess = first(dda, ddc, ddq) - 2.0 * jnp.einsum("ipk,ipl->kl", jnp.moveaxis(r, 0, -1), ar)
    value = jnp.sum(_sse(a, c, q, beta))
    return value, first(da, dc, dq), hess


def varying_products(layout: Layout) -> tuple[list, list]:
    """Indices (in :meth:`Layout.index` order) of the products that move with the time
    constants, and of those that do not.

    A column moves if it differs at two sets of time constants (``Layout.moving``);
    a product moves if one of its columns does. The others are summed once per
    device, not once per trial of the time constants.
    """
    p, moves = layout.p, layout.moving
    var = [1 + j for j, (a, b, _) in enumerate(layout.xx) if moves[a] or moves[b]]
    k = 1 + len(layout.xx)
    var += [k + i * p + a for i in range(3) for a in range(p) if moves[a]]
    fixed = [j for j in range(layout.n_products) if j not in var]
    return var, fixed


def covariance_pairs(model: ErrorModel, layout: Layout) -> tuple[list, np.ndarray, np.ndarray]:
    """The products the Gauss–Newton covariance of (β, θ) needs, each formed once.

    Factors are (column, axis, k): the column (k None) or its slope ∂x/∂θ_k, on
    axis 0 for a column equal on all axes. ``cross`` (3, p, w) and ``curvature``
    (3, w, w) index the distinct pairs: Σ x_a ∂x_m/∂θ_k and Σ ∂x_m/∂θ_k ∂x_n/∂θ_r
    for the moving columns m, n (w = columns × time constants, (m, k) order).
    """
    p, nq = layout.p, model.n_nonlinear
    slopes = [(m, k) for m in moving_columns(model) for k in range(nq)]
    pairs: dict = {}

    def index(f, g):
        key = tuple(sorted((f, g), key=repr))
        return pairs.setdefault(key, len(pairs))

    def ax(a, i):
        return 0 if layout.shared[a] else i

    cross = np.asarray([[[index((a, ax(a, i), None), (m, ax(m, i), k)) for m, k in slopes]
                         for a in range(p)] for i in range(3)], np.int32).reshape(3, p, len(slopes))
    curvature = np.asarray([[[index((m, ax(m, i), k), (n, ax(n, i), r)) for n, r in slopes]
                             for m, k in slopes] for i in range(3)],
                           np.int32).reshape(3, len(slopes), len(slopes))
    return list(pairs), cross, curvature


def _unpack_sums(layout: Layout, s):
    """:func:`_unpack` of a product vector, or of the fixed and moving sums apart (a model
    with time constants: :func:`_unpack_split`)."""
    if isinstance(s, dict):
        return _unpack_split(layout, s["fixed"], s["moving"])
    return _unpack(layout, s)


def _chunked_sum(ops, c: int):
    """Sums of the (n,) arrays ``ops`` in one loop, by chunks of ``c`` then over chunks
    (a short sum per chunk keeps the rounding of a long sum down)."""
    n = ops[0].shape[0]
    return jnp.sum(_vsum([o.reshape(n // c, c) for o in ops]), axis=0)


def _device(model: ErrorModel, layout: Layout, opts, c: int, prefix: bool, t, gyro, mask, rate,
            temp, temp_ext, accel, aux, centre, scale, dt, nv, theta0, pos=None):
    p, nq = layout.p, model.n_nonlinear
    dtype = gyro.dtype
    if isinstance(pos, str):  # ALIGNED: every sample valid; a constant mask folds away
        mask = jnp.ones(mask.shape, bool)
    norm = None
    if temp is not None:
        norm = temp_norm_from(temp, mask) if centre is None else TempNorm(centre=centre, scale=scale)
    t = jnp.zeros(mask.shape, dtype) if t is None else t
    sig = make_signals(t, gyro, mask, rate=rate, temp=temp, temp_ext=temp_ext, accel=accel,
                       norm=norm, dtemp_window=opts.dtemp_window, dt=dt, slopes=dt is not None,
                       aux=aux)
    if temp is not None:  # the same T_s with a multiply instead of a divide per sample
        inv = 1.0 / norm.scale
        sig = eqx.tree_at(lambda s_: s_.temp_s, sig, temp * inv - norm.centre * inv)
    y = sig.gyro - sig.rate
    if layout.const_col is not None:
        y0 = y[0] if prefix else y[jnp.argmax(mask)]
    else:
        y0 = jnp.zeros((3,), dtype)
    n_folds = opts.n_folds

    def sums_at(th):
        if layout.pointwise:
            return _fold_sums(_signal_products(layout, model, th, y0), sig, mask, nv,
                              opts.n_blocks, n_folds, c, pos)
        x = model.design(sig, th)  # a column that reads other samples is formed once
        return _fold_sums(_design_products(layout), (x, y - y0), mask, nv, opts.n_blocks,
                          n_folds, c, pos)

    if nq == 0:
        theta = jnp.zeros((0,), dtype)
        tot, per_fold = sums_at(theta)
        held, train = per_fold, tot[None] - per_fold
        steps, converged = jnp.asarray(1, jnp.int32), jnp.asarray(True)
    else:
        # variable projection: the linear coefficients are solved from the sums for
        # every trial of the time constants; Newton moves the time constants alone.
        # Products that do not move with them are summed once (total and per fold);
        # a trial forms only the moving columns (with their first and second
        # derivatives, each term's ``columns_jet``) and sums the moving products and
        # their derivatives (product rule) in one pass.
        var_idx, fix_idx = varying_products(layout)
        ys = y - y0
        # the fixed columns (the moving ones zero here: never read from x_any)
        x_any = jnp.concatenate([jnp.zeros(y.shape + (tm.n_params,), dtype) if tm.n_nonlinear
                                 else tm.columns(sig, jnp.zeros((0,), dtype))
                                 for tm, _, _ in model.slices()], axis=-1)
        fix_sel = np.asarray(fix_idx, np.int32)

        def fixed_products(src, m):
            ops = _products(layout, src[0], src[1], m)
            return [ops[j] for j in fix_sel]

        fix_tot, fix_fold = _fold_sums(fixed_products, (x_any, ys), mask, nv, opts.n_blocks,
                                       n_folds, c, pos)
        n_xx = len(layout.xx)

        def factors(j):  # a moving product j as (axis, column, other column or None for a rate)
            if j <= n_xx:
                a_, b_, i_ = layout.xx[j - 1]
                return i_, a_, b_
            k_ = j - 1 - n_xx
            return k_ // p, k_ % p, None

        # columns of the terms with time constants: only they are formed per trial
        moving_terms = [(tm, sl, qs) for tm, sl, qs in model.slices() if tm.n_nonlinear]

        def column_jets(th, derivatives):
            """{column: (x (n, 3), dx (q, n, 3), ddx (q, q, n, 3))} of the moving terms'
            columns, derivatives None without ``derivatives``."""
            out = {}
            for tm, sl, qs in moving_terms:
                if derivatives:
                    x, d, dd = tm.columns_jet(sig, th[qs])
                else:
                    x, d, dd = tm.columns(sig, th[qs]), None, None
                for k_ in range(sl.stop - sl.start):
                    dk = ddk = None
                    if derivatives:  # this term's θ sit at qs of the model's θ
                        dk = jnp.zeros((nq,) + x.shape[:-1], dtype).at[qs].set(d[..., k_])
                        ddk = jnp.zeros((nq, nq) + x.shape[:-1], dtype).at[qs, qs].set(
                            dd[..., k_])
                    out[sl.start + k_] = (x[..., k_], dk, ddk)
            return out

        def factor(jets, i_, a_):  # one column of axis i_ and its derivatives (None: fixed)
            ax = 0 if layout.shared[a_] else i_
            if a_ in jets:
                x, d, dd = jets[a_]
                return x[:, ax], None if d is None else d[:, :, ax], \
                    None if dd is None else dd[:, :, :, ax]
            return x_any[:, ax, a_], None, None

        cov_pairs = covariance_pairs(model, layout)[0]

        def moving(th, masks, derivatives=True, plain=(), covariance=False):
            """Moving sums (m,) per mask, and with ``derivatives`` their first (q, m)
            and second (q, q, m) derivatives in θ (product rule), then the sums alone
            under the ``plain`` masks, then with ``covariance`` the sums of
            :func:`covariance_pairs` under the first mask: one variadic reduction."""
            jets = column_jets(th, derivatives)

            @functools.cache
            def column(ax, a_):  # sliced once per column and axis
                return factor(jets, ax, a_)

            def fac(i_, a_):
                return column(0 if layout.shared[a_] else i_, a_)

            streams = []
            for j in var_idx:
                i_, a_, b_ = factors(j)
                u, du, ddu = fac(i_, a_)
                v, dv, ddv = (ys[:, i_], None, None) if b_ is None else fac(i_, b_)
                streams.append(_product_jet(u, du, ddu, v, dv, ddv, nq if derivatives else 0))
            ops = [jnp.where(m, u, 0.0) for m in masks for st in streams for u in st]
            ops += [jnp.where(m, st[0], 0.0) for m in plain for st in streams]
            if covariance:  # a column (k None) or a slope ∂x/∂θ_k, of (column, axis)
                def one(a_, i_, k_):
                    x_, d_, _ = fac(i_, a_)
                    return x_ if k_ is None else d_[k_]

                ops += [jnp.where(masks[0], one(*f) * one(*g_), 0.0) for f, g_ in cov_pairs]
            sums = _chunked_sum(ops, c)
            w = 1 + nq + nq * nq if derivatives else 1
            lead = len(masks) * len(var_idx) * w
            n_plain = len(plain) * len(var_idx)
            out_plain = sums[lead:lead + n_plain].reshape(len(plain), len(var_idx))
            out_cov = sums[lead + n_plain:]
            sums = sums[:lead].reshape(len(masks), len(var_idx), w)
            if not derivatives:
                out = sums[..., 0]
            else:
                out = (sums[..., 0], jnp.moveaxis(sums[..., 1:1 + nq], -1, 1),
                       jnp.moveaxis(sums[..., 1 + nq:].reshape(len(masks), -1, nq, nq), 1, -1))
            if covariance:
                return out, out_plain, out_cov
            return (out, out_plain) if plain else out

        def cost_of(fixed, v_):
            a_, c_, q_, _ = _unpack_split(layout, fixed, v_)
            return jnp.sum(_sse(a_, c_, q_, _cho_solve(*_cholesky(a_), c_)))

        def projected(fixed, v_, dv, ddv):  # the fixed products do not move
            return _projected(_unpack_split(layout, fixed, v_), _unpack_split(layout, None, dv),
                              _unpack_split(layout, None, ddv))

        grid = model.nonlinear_grid(sig).astype(dtype)
        costs = jax.vmap(lambda th: cost_of(fix_tot, moving(th, [mask], False)[0]))(grid)
        costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
        best = jnp.argmin(costs)
        start = grid[best] if theta0 is None else theta0

        # problem 0 is the full fit, problem 1 + k the fit without fold k (scored on
        # fold k's own sums), refitted from the full optimum: one Newton loop solves
        # them in turn, so its body is traced and compiled once
        fold_id = fold_ids(mask, opts.n_blocks, n_folds)  # -1 where not valid

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
        sums_shape = jax.ShapeDtypeStruct((len(var_idx),), dtype)
        th_all, cost_all, (v_train, v_held, cov), steps_all, conv_all = _newton(
            evaluate, start, caps, opts.rtol,
            (sums_shape, sums_shape, jax.ShapeDtypeStruct((len(cov_pairs),), dtype)))
        theta, steps = th_all[0], steps_all[0]
        # a local optimum worse than the best grid point is not the answer
        converged = conv_all[0] & (cost_all[0] <= costs[best] * (1.0 + 1e-9) + 1e-300)
        # fixed and moving sums apart: the finish unpacks them (:func:`_unpack_sums`)
        tot = dict(fixed=fix_tot, moving=v_train[0])
        held = dict(fixed=fix_fold, moving=v_held[1:])
        train = dict(fixed=fix_tot[None] - fix_fold, moving=v_train[1:])
        raw_cov = dict(covariance=cov[0])  # indexed by :func:`covariance_pairs`
    terms = model.deterministic
    raw = dict(tot=tot, held=held, train=train, theta=theta, steps=jnp.asarray(steps, jnp.int32),
               converged=jnp.asarray(converged), y0=y0,
               range_flags=model.range_problems(sig) > 0 if terms else jnp.zeros((0,), bool))
    if nq:
        raw.update(raw_cov)
    if temp is not None:
        raw["temp_range"] = jnp.stack(masked_range(temp, mask))
    if sig.norm is not None:
        raw["norm_centre"], raw["norm_scale"] = sig.norm.centre, sig.norm.scale
    return raw


def moving_columns(model: ErrorModel) -> list[int]:
    """The design columns of the terms with time constants (those that move with θ)."""
    return [a for tm, sl, _ in model.slices() if tm.n_nonlinear for a in range(sl.start, sl.stop)]


def _finish(model: ErrorModel, layout: Layout, opts, raw: dict) -> dict:
    """One device's results from its sums (:func:`_device`): the full and the folds'
    solutions, residual and held-out errors, covariance, rank check and status.

    Small dense algebra on (3, p, p) systems, no samples: a program of its own
    (:func:`_group_finish`), inlined in fused linear models' group programs.
    """
    p, nq = layout.p, model.n_nonlinear
    theta, converged = raw["theta"], raw["converged"]
    a, cc, q, n_valid = _unpack_sums(layout, raw["tot"])
    af, cf, qf, nf = _unpack_sums(layout, raw["held"])
    at, ct, _, _ = _unpack_sums(layout, raw["train"])
    dtype = a.dtype

    # with every column shared by the axes the three Gram matrices are one: factor,
    # check and invert the first axis' only and broadcast
    n_gram = 1 if all(layout.shared) else 3

    def gram_factor(m):  # Cholesky factors and column scales of m (..., 3, p, p)
        chol_, d_ = _cholesky(m[..., :n_gram, :, :])
        return jnp.broadcast_to(chol_, m.shape), jnp.broadcast_to(d_, m.shape[:-1])

    # the full fit and the folds' training fits, factored and solved together
    chol_all, d_all = gram_factor(jnp.concatenate([a[None], at]))
    beta_all = _cho_solve(chol_all, d_all, jnp.concatenate([cc[None], ct]))
    chol, dsc, beta_s, beta_f = chol_all[0], d_all[0], beta_all[0], beta_all[1:]
    ratio, direction, rank_ok = (jnp.broadcast_to(v, (3,) + v.shape[1:])
                                 for v in rank_check(a[:n_gram], opts.rank_tol))
    sse = jnp.maximum(_sse(a, cc, q, beta_s), 0.0)
    shift = jnp.zeros((3, p), dtype)
    if layout.const_col is not None:
        shift = shift.at[:, layout.const_col].set(raw["y0"])
    beta = beta_s + shift
    rms = jnp.sqrt(jnp.sum(sse) / jnp.maximum(3 * n_valid, 1.0))

    # held-out folds: train on total − fold, score on the fold's own sums
    sse_f = jnp.sum(jnp.maximum(_sse(af, cf, qf, beta_f), 0.0), axis=-1)
    heldout_rms = jnp.sqrt(jnp.sum(sse_f) / jnp.maximum(3 * jnp.sum(nf), 1.0))
    fold_mse = sse_f / jnp.maximum(3 * nf, 1.0)

    dof = jnp.maximum(n_valid - p - nq, 1.0)
    sigma2 = jnp.maximum(sse / dof, 1e-300)
    if nq == 0:  # block diagonal: σ_i² (X_iᵀX_i)⁻¹ per axis
        inv = jnp.broadcast_to(_cho_inverse(chol[:n_gram], dsc[:n_gram]), (3, p, p))
        cov = jax.scipy.linalg.block_diag(*[inv[i] * sigma2[i] for i in range(3)])
    else:  # g = ∂(Xβ)/∂θ = Σ_m β_m ∂x_m/∂θ over the moving columns m
        cols = moving_columns(model)
        b_m, n_m = beta_s[:, cols], len(cols)  # (3, M)
        _, cross_at, curvature_at = covariance_pairs(model, layout)
        cross = raw["covariance"][cross_at].reshape(3, p, n_m, nq)  # Σ x_a ∂x_m/∂θ_k
        # Σ ∂x_m/∂θ_k ∂x_n/∂θ_r
        curvature = raw["covariance"][curvature_at].reshape(3, n_m, nq, n_m, nq)
        xg = jnp.einsum("iamk,im->iak", cross, b_m)
        gg = jnp.einsum("imknr,im,in->ikr", curvature, b_m, b_m)
        cov = _covariance_separable(a, xg, gg, sigma2)

    collinear = collinear_terms(model, direction, rank_ok)
    finite = jnp.all(jnp.isfinite(beta)) & jnp.all(jnp.isfinite(theta)) & jnp.isfinite(rms)
    status = fit_status(n_valid, min_samples(p + nq), converged, finite, raw["range_flags"],
                        rank_ok)
    out = dict(beta=beta, theta=theta, cov=cov, rms=rms,
               heldout_rms=heldout_rms, fold_mse=fold_mse,
               sigma=jnp.sqrt(sigma2), steps=raw["steps"],
               status=jnp.asarray(status, jnp.int32), range_flags=raw["range_flags"],
               collinear=collinear, rank_ratio=jnp.min(ratio), n_samples=n_valid)
    for k in ("temp_range", "norm_centre", "norm_scale"):
        if k in raw:
            out[k] = raw[k]
    return out


def _covariance_separable(a, xg, gg, sigma2):
    """Gauss–Newton covariance of (β per axis, θ), each axis weighted by 1/σ_i², as
    :func:`diffgyro.fit._covariance` forms it, from the Gram matrices ``a`` (3, p, p) and
    the sums ``xg`` = Σ X ∂(Xβ)/∂θ (3, p, q) and ``gg`` = Σ (∂(Xβ)/∂θ)² (3, q, q)."""
    p = a.shape[-1]
    i_bt = xg / sigma2[:, None, None]
    i_tt = jnp.sum(gg / sigma2[:, None, None], axis=0)
    zero = jnp.zeros((p, p), a.dtype)
    info = jnp.block([[*(a[i] / sigma2[i] if j == i else zero for j in range(3)), i_bt[i]]
                      for i in range(3)] + [[*(i_bt[i].T for i in range(3)), i_tt]])
    # positive definite where the fit is identified (NaN where not: the status says why)
    return _cho_inverse(*_cholesky(info))


def _group_program(model, layout, opts, c, prefix, t, gyro, mask, rate, temp, temp_ext, accel,
                   aux, centre, scale, dt, nv, theta0, pos=None, apart=False):
    """Every device of a group through :func:`_device`: its results finished and packed
    (:func:`_pack`), or with ``apart`` its sums as they are (finished by
    :func:`_group_finish`)."""
    TRACE_COUNTS["sums"] += 1
    aligned = isinstance(pos, str)  # ALIGNED: the same for every device, not an array

    def one(*args):
        if aligned:
            return _device(model, layout, opts, c, prefix, *args, pos=pos)
        return _device(model, layout, opts, c, prefix, *args)

    args = (t, gyro, mask, rate, temp, temp_ext, accel, aux, centre, scale, dt, nv, theta0)
    raw = jax.vmap(one)(*(args if aligned else (*args, pos)))
    return raw if apart else _finished(model, layout, opts, raw)


def _finished(model, layout, opts, raw):
    """A group's results from its sums, packed (:func:`_pack`)."""
    return _pack(jax.vmap(lambda r: _finish(model, layout, opts, r))(raw), raw["y0"].dtype)


_group_fused = filter_jit(compiler_options=REASSOCIATE)(_group_program)
_group_compact = filter_jit(compiler_options={**REASSOCIATE, **FAST_COMPILE})(_group_program)
#: The finish of every model but a fused linear one: a few dozen tiny kernels, compiled
#: without optimisation (:data:`ONCE`) on a thread of its own while the group program
#: compiles: a first fit starts sooner, at the cost of a second call per group (which,
#: not the unoptimised code, makes long fits about 10 % slower).
_group_finish = filter_jit(compiler_options=ONCE)(_finished)


def _group_for(model: ErrorModel, fused: bool):
    """The compiled group program: a fused linear model's with XLA's fusion emitters (its
    sums at memory speed), any other compiled for compile time (:data:`FAST_COMPILE`)."""
    return _group_fused if fused and not model.n_nonlinear else _group_compact


def _pack(out, dtype):
    """Every result of a group as the columns of one (devices, k) array, and the results'
    shapes and dtypes as empty arrays: the host then fetches one array per group, not
    one per result (each fetch costs tens of µs). Integers and flags are exact in the
    float dtype (counts stay far below 2^24)."""
    leaves, tree = jax.tree.flatten(out)
    packed = jnp.concatenate([x.reshape(x.shape[0], -1).astype(dtype) for x in leaves], axis=1)
    return packed, jax.tree.unflatten(tree, [jnp.zeros((0, *x.shape[1:]), x.dtype)
                                             for x in leaves])


def _unpack_results(packed: np.ndarray, spec) -> dict:
    """The results :func:`_pack` packed, as numpy arrays of their own shapes and dtypes."""
    leaves, tree = jax.tree.flatten(spec)
    sizes = [int(np.prod(x.shape[1:], dtype=np.int64)) for x in leaves]
    cols = np.split(packed, np.cumsum(sizes)[:-1], axis=1)
    return jax.tree.unflatten(tree, [c.reshape(packed.shape[0], *x.shape[1:]).astype(x.dtype)
                                     for c, x in zip(cols, leaves)])


def _pow2_floor(x: int) -> int:
    return 1 << (max(int(x), 1).bit_length() - 1)


def group_size(n_devices: int, length: int, samples: int | None = None) -> int:
    """Devices per compiled call: a power of two, about ``samples`` (GROUP_SAMPLES)
    samples, ≥ 8 devices only when the batch has them (5 and 7 devices share a group
    size of 8). Independent of the device count beyond one group: no recompilation."""
    samples = GROUP_SAMPLES if samples is None else samples
    cap = _pow2_floor(max(samples // max(length, 1), 1))
    want = 1 << max(int(n_devices) - 1, 7).bit_length()  # next power of two ≥ n, at least 8
    return max(1, min(cap, want, MAX_GROUP_DEVICES))


def chunk_size(min_valid: int, n_blocks: int, length: int) -> int:
    """Chunk of the reduction: a power of two dividing the length, no longer than the
    shortest fold block (so a chunk holds at most one block boundary)."""
    c = min(CHUNK, _pow2_floor(max(min_valid // max(n_blocks, 1), 1)), length & -length)
    return max(c, 1)


def valid_counts(mask: Bool[np.ndarray, "d n"]) -> tuple[np.ndarray, np.ndarray]:
    """Valid samples of every device, and whether they come first (a prefix mask).

    One pass of fast reads: counts by popcount of the mask's bytes read as
    64-bit words; the valid samples come first when the first invalid one is
    at the count.
    """
    mask = np.asarray(mask, bool)
    d, n = mask.shape
    if (hasattr(np, "bitwise_count") and n % 8 == 0 and mask.flags.c_contiguous
            and mask.ctypes.data % 8 == 0):  # numpy ≥ 2.0
        nv = np.bitwise_count(mask.view(np.uint64)).sum(axis=1, dtype=np.int64)
    else:
        nv = np.count_nonzero(mask, axis=1).astype(np.int64)
    first_invalid = np.argmin(mask, axis=1) if n else np.zeros(d, np.int64)
    return nv, (nv == n) | (first_invalid == nv)


def solve_sums(model: ErrorModel, batch: Batch, norm: TempNorm | None, opts, theta0=None,
               dtype=np.float64, aux: dict | None = None):
    """Fit every device of ``batch`` with the sums path; numpy arrays with a device axis.

    ``theta0`` (devices × time constants, log s) replaces the grid start; ``aux`` holds
    the extra columns the model reads, centred and scaled ((devices, n) each).
    """
    aux = dict(aux or {})
    present = frozenset(batch.signals) | {aux_key(k) for k in aux}
    layout, need = layout_of(model, present)
    d, n = batch.n_devices, batch.length
    fused = layout.pointwise and all(layout.shared)
    if model.n_nonlinear:
        g = max(group_size(d, n, GROUP_SAMPLES // NONLINEAR_GROUP_DIVISOR), min(2, d))
    else:
        g = group_size(d, n, GROUP_SAMPLES * (FUSED_GROUP_FACTOR if fused else 1))
    # dT/dt (and the heating state) only for a model that reads them
    dt = sampling_intervals(batch) if "dt" in need else None
    centre = scale = None
    if norm is not None and batch.temp is not None:
        centre = np.broadcast_to(np.asarray(norm.centre, dtype), (d,))
        scale = np.broadcast_to(np.asarray(norm.scale, dtype), (d,))
    arrays = {"gyro": batch.gyro, "mask": batch.mask, "centre": centre, "scale": scale, "dt": dt,
              "theta0": None if theta0 is None else np.broadcast_to(
                  np.asarray(theta0, dtype), (d, model.n_nonlinear))}
    for k in INPUTS:
        arr = getattr(batch, k)
        # the reference rate is always read: the fit is of gyro − rate
        arrays[k] = arr if (arr is not None and (k in need or k in ("temp", "rate"))) else None
    if "t" not in need:
        arrays["t"] = None
    arrays["aux"] = {k: v for k, v in aux.items() if aux_key(k) in need}
    # groups take turns on the accelerators; on a CPU one device runs every group, the
    # host preparing the next group while XLA runs the last
    devices = parallel_devices()
    group = _group_for(model, fused)
    # a program compiled for compile time finishes in a program of its own, compiled
    # without optimisation beside it; a fused linear model's finishes inline
    apart = group is _group_compact
    finish = (model, layout, opts)
    order = ("t", "gyro", "mask", "rate", "temp", "temp_ext", "accel", "aux", "centre", "scale",
             "dt")
    nv_all, prefix_all = valid_counts(batch.mask)

    def run(j: int):
        start = j * g
        stop = min(start + g, d)
        sl = slice(start, stop) if stop - start == g else np.minimum(np.arange(start, start + g),
                                                                    stop - 1)
        nv = nv_all[sl]
        prefix = bool(np.all(prefix_all[sl]))
        c = chunk_size(int(nv.min()), opts.n_blocks, n)
        host = {k: (np.asarray(batch.mask[sl], bool) if k == "mask"
                    else np.ascontiguousarray(np.asarray(arrays[k][sl], dtype)))
                for k in order if arrays[k] is not None and k != "aux"}
        host["aux"] = {k: np.ascontiguousarray(np.asarray(v[sl], dtype))
                       for k, v in arrays["aux"].items()}
        host["nv"] = nv.astype(np.int32)
        if arrays["theta0"] is not None:
            host["theta0"] = np.ascontiguousarray(arrays["theta0"][sl])
        if prefix and nv.min() == n and n % opts.n_blocks == 0:
            pos = ALIGNED
        elif prefix:
            host["pos"] = block_starts(nv, opts.n_blocks)
            pos = None
        else:
            pos = None
        put = jax.device_put(host, devices[j % len(devices)])  # one call for the whole group
        args = (model, layout, opts, c, prefix, *[put.get(k) for k in (*order, "nv", "theta0")],
                put.get("pos", pos), apart)
        if j == 0:
            # the first group traces and compiles every program (the collector paused)
            with collector_paused():
                # the results' shapes, from the trace the call makes anyway
                shapes = group.eval_shape(*args)
                # the group program compiles while this thread traces the finish
                ahead = [group.compile_ahead(*args)]
                if apart:
                    on = jax.sharding.SingleDeviceSharding(devices[0])
                    raw = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=on),
                                       shapes)
                    shapes = _group_finish.eval_shape(*finish, raw)
                    ahead.append(_group_finish.compile_ahead(*finish, raw))
                specs.append(shapes[1])
                for thread in ahead:
                    thread.join()
        out = group(*args)
        if apart:
            out = _group_finish(*finish, out)
        return stop - start, out[0]  # the packed results (:func:`_pack`)

    # the model-free noise floor on threads of the host, beside the compiled programs
    noise = (host_noise(batch.gyro, batch.rate, batch.mask, dtype) if opts.noise_floor
             else None)
    # dispatch every group, then collect (concurrent calls from several Python threads
    # deadlocked XLA's CPU client: keep to one caller)
    specs: list = []
    outs = [run(j) for j in range(-(-d // g))]
    got = jax.device_get([o for _, o in outs])  # one transfer call for every group
    got = [_unpack_results(o, specs[0]) for o in got]
    out = {k: np.concatenate([o[k][:m] for (m, _), o in zip(outs, got)], axis=0)
           for k in got[0]}
    if noise is None:
        out["noise_floor"] = np.full(d, np.nan, dtype)
        out["noise_axes"] = np.full((d, 3), np.nan, dtype)
    else:
        out["noise_floor"], out["noise_axes"] = noise()
    return out
