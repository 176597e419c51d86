"""Which columns and products a model needs: the product layout, probed once per model
on random signals, and the per-sample products in its order."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.interpreters import partial_eval as pe

from .._jit import filter_jit
from .._xla_options import ONCE
from ..data import AUX_PREFIX
from ..model import ErrorModel
from ..signals import Signals, TempNorm, make_signals

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
        if model.terms:
            out.append(model.range_problems(s))
        return out

    closed = jax.make_jaxpr(f)(jax.ShapeDtypeStruct((), dtype),
                               *[jax.ShapeDtypeStruct(shapes[k], dtype) for k in names])
    _, used = pe.dce_jaxpr(closed.jaxpr, [True] * len(closed.jaxpr.outvars))
    return frozenset(name for name, u in zip(["dt", *names], used) if u)


def sample_products(layout: Layout, x, ys, mask):
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


def signal_products(layout: Layout, model: ErrorModel, theta, y0):
    """Products of a recording's signals through the model's design (a pointwise model)."""
    def products(sig, mask):
        x = model.design(sig, theta)
        return sample_products(layout, x, sig.gyro - sig.rate - y0, mask)

    return products


def design_products(layout: Layout):
    """Products of a precomputed design and rates, given as the pair (x, ys)."""
    def products(xy, mask):
        return sample_products(layout, xy[0], xy[1], mask)

    return products



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



def moving_columns(model: ErrorModel) -> list[int]:
    """The design columns of the terms with time constants (those that move with θ)."""
    return [a for tm, sl, _ in model.slices() if tm.n_nonlinear for a in range(sl.start, sl.stop)]
