"""diagnose(model, batch): where a model fails, and which physical effect is missing.

For every device the base model is fitted (:func:`diffgyro.fit.fit`), and then,
for every registered effect whose signals the data has and the model lacks
(built-in or registered by the user), the model *with that term added* is
scored on held-out data. The comparison is built to stay honest when the
residual is correlated in time, where a plain F-test on 10⁵ samples calls
everything significant:

* **Held-out error on whole time blocks.** The samples are cut into the fit's
  interleaved time blocks and dealt to ``n_folds`` folds
  (:func:`diffgyro.fit._fold_ids`, so the base numbers are the fit's own);
  every fold is predicted by the model fitted on the others. Base and
  candidate use the same folds, so their per-fold mean squared errors are
  *paired*.
* **A noise floor that does not depend on any model** (:func:`noise_floor`):
  the robust scale of successive differences of ``gyro − rate`` (slow drift
  and the steps of a rate table drop out), checked against the short-τ
  Allan deviation of the residual.
* **Significant means large and material.** A candidate is significant only
  when (1) its per-fold gain in held-out MSE is large against the fold-to-fold
  spread (a paired t over the folds ≥ ``t_min``), (2) the base model's
  held-out MSE is materially above the floor (``excess_min``), (3) the term
  closes a real share of that gap (``closure_min``) and (4) the gain is a
  material fraction of the noise variance (``gain_min``). Conditions (2)–(4)
  are what keep time-correlated noise (flicker, a small random walk) from
  being "explained" by any slowly varying term.
* **Time constants are chosen on training folds only.** Terms with a
  nonlinear parameter (``thermal_lag``, ``warmup``, user terms) are scored
  on a dense grid of time constants; each fold picks its own on the training
  blocks, so the held-out number pays for the search.
* **A random walk must not win by default.** A smoother can follow any slowly
  varying residual, so ``random_walk`` is scored separately (a local-level
  Kalman smoother of the base residual with its walk variance chosen by
  maximum likelihood on the training blocks, the white variance fixed at the
  floor) and enters the ranking only when no deterministic term closes the
  gap (``rw_prefer``) *and* the residual's Allan deviation rises at long τ
  (slope ≥ ``rw_slope_min``, +½ for a random walk).
* **Look-alikes are shown, not hidden.** Effects that mimic each other
  (gradient / thermal lag / inside–outside difference; scale asymmetry /
  nonlinearity; g-sensitivity / misalignment) are reported as close
  alternatives with their held-out numbers whenever they are significant too.

The thresholds (:class:`Thresholds`) were tuned on recordings made apart from
the project's simulator (``tests/hidden_effects.py``: thermal chamber, rate
table and multi-position plans, white + flicker + random-walk noise, output
and temperature quantisation, read-out lag) and on the simulator's own
batches; ``tests/test_diagnose.py`` measures the detection and ``adequate``
rates they give.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import asdict, dataclass, field

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .data import Batch, Recording
from .effects import AbstractEffect, registry
from .effects.base import MAX_ORDER
from .jit import release_compiled_if_crowded
from .jsonio import number
from .model import ErrorModel
from .signals import Signals

# --------------------------------------------------------------------------- settings


@dataclass(frozen=True)
class Thresholds:
    """When a candidate counts as significant (see the module docstring).

    ``t_min``: paired t of the per-fold held-out MSE gains (``n_folds − 1``
    degrees of freedom); an effect confined to part of the record (a warm-up
    transient) improves one or two folds a lot and the others not at all, so
    it also passes when no fold gets worse by more than ``consistency`` × the
    mean gain. ``excess_min``: the base model's held-out MSE must
    exceed the floor's by this fraction of the floor's. ``closure_min``:
    share of that gap the candidate closes. ``gain_min``: its held-out MSE
    gain as a fraction of the floor's MSE. ``rw_slope_min``: long-τ Allan
    slope of the residual needed to name a random walk, ``rw_excess_min`` the
    excess it needs (low-level flicker and rate random walk are noise, not a
    missing effect). A significant deterministic term is preferred to the
    random walk when it closes at least ``rw_prefer`` of the gap, or leaves
    less than ``rw_ratio`` times the gap the random walk leaves; a term whose
    time constant ran to the slow end of its search (a warm-up with τ of a
    quarter of the record) fits a drift, not a physical transient, and does
    not count. ``alt_share``: a significant candidate is a close
    alternative when it closes at least this share of what the best closes.

    An effect confined to a small part of the record (a warm-up transient,
    the highest rates of a rate table) can be material where it happens yet
    small over the whole record. So a candidate is also material when, in the
    ``local_share`` of time blocks it improves most, the base model's held-out
    MSE is at least ``1 + local_excess`` times the floor's and the candidate
    closes ``local_closure`` of that local gap, with a whole-record gain of at
    least ``local_gain_min`` and at least ``local_closure_min`` of the
    whole-record gap closed (so a term that follows one flicker excursion does
    not pass); never for the random walk.

    A model whose held-out MSE is ``1 + unexplained_excess`` times the
    floor's or more is ``missing_effect`` even when no single term is
    significant (several effects missing at once, or one outside the
    vocabulary); it then names none.
    """

    t_min: float = 3.0
    consistency: float = 0.25
    excess_min: float = 0.15
    closure_min: float = 0.3
    gain_min: float = 0.03
    rw_slope_min: float = 0.25
    rw_excess_min: float = 0.2
    rw_prefer: float = 0.85
    rw_ratio: float = 2.0
    alt_share: float = 0.6
    local_share: float = 0.02
    local_excess: float = 2.0
    local_closure: float = 0.5
    local_gain_min: float = 0.005
    local_closure_min: float = 0.5
    unexplained_excess: float = 1.0


#: Effects that mimic each other on common test plans (reported together).
FAMILIES: dict[str, tuple[str, ...]] = {
    "thermal transient": ("gradient", "thermal_lag", "temp_diff", "hysteresis"),
    "rate-dependent scale factor": ("scale_asym", "scale_nonlin", "scale_poly"),
    "orientation-dependent bias": ("g_sens", "misalignment"),
}

#: Time-constant grid density for candidate terms with one nonlinear parameter.
GRID_POINTS = 24
#: Walk variance grid (q·dt / r) searched by the local-level smoother.
RW_GRID = tuple(10.0 ** np.linspace(-10.0, -1.0, 19))


def family_of(name: str) -> str | None:
    for fam, names in FAMILIES.items():
        if name in names:
            return fam
    return None


# --------------------------------------------------------------------------- noise floor


def noise_floor(
    y: Float[Array, "n 3"],
    mask: Bool[Array, " n"],
    rate: Float[Array, "n 3"] | None = None,
) -> Float[Array, " 3"]:
    """White-noise σ per axis of ``y = gyro − rate``, without any model.

    From successive differences: slow drift (temperature, random walk) hardly
    changes from one sample to the next, so ``Δy/√2`` sees the white noise.
    Pairs where the reference rate jumps (a rate table spinning up, where a
    scale-factor error would leak in) are left out. A first robust scale
    (MAD) sets a ±4σ window; the floor is the root mean square of the
    differences inside it (corrected for the truncation), which, unlike a
    median, stays continuous when the output is quantised to a few LSB. When
    the LSB exceeds ~2σ most differences are exactly zero and the MAD
    collapses; the RMS of all but the largest 0.5 % of differences is used.
    The same on lag-2 differences guards against output samples that are
    correlated (a sensor's internal low-pass filter): the larger is kept.
    """
    y = jnp.asarray(y)
    out = []
    for lag in (1, 2):
        d = y[lag:] - y[:-lag]
        ok = mask[lag:] & mask[:-lag]
        if rate is not None:
            dr = jnp.linalg.norm(rate[lag:] - rate[:-lag], axis=-1)
            s0 = _mad(d, ok)
            calm = ok & (dr <= 30.0 * jnp.max(s0))
            ok = jnp.where(jnp.sum(calm) >= 0.2 * jnp.sum(ok), calm, ok)
        s1 = _mad(d, ok)
        med = _masked_median(d, ok)
        dev = jnp.abs(d - med)
        inside = ok[:, None] & (dev <= 4.0 * s1)
        ms = jnp.sum(jnp.where(inside, dev**2, 0.0), axis=0) / jnp.maximum(jnp.sum(inside, axis=0), 1)
        ms = ms / _TRUNC4
        # an output quantised to more than ~2σ makes most differences exactly 0 and the MAD
        # collapse; then the RMS of all but the largest 0.5 % of the differences is the floor
        lim = jnp.nanquantile(jnp.where(ok[:, None], dev, jnp.nan), 0.995, axis=0)
        keep = ok[:, None] & (dev <= lim)
        ms_trim = jnp.sum(jnp.where(keep, dev**2, 0.0), axis=0) / jnp.maximum(jnp.sum(keep, axis=0), 1)
        ms = jnp.where(s1**2 < 0.25 * ms_trim, ms_trim, ms)
        ms_all = jnp.sum(jnp.where(ok[:, None], dev**2, 0.0), axis=0) / jnp.maximum(jnp.sum(ok), 1)
        ms = jnp.where(ms > 0, ms, ms_all)  # a nearly constant output: every difference counts
        out.append(jnp.sqrt(ms / 2.0))
    return jnp.maximum(out[0], out[1])


#: E[Z² | |Z| ≤ 4] for a standard normal Z (truncation correction of the floor).
_TRUNC4 = 1.0 - 8.0 * math.exp(-8.0) / math.sqrt(2.0 * math.pi) / math.erf(4.0 / math.sqrt(2.0))


def _masked_median(d, ok):
    return jnp.nanmedian(jnp.where(ok[:, None], d, jnp.nan), axis=0)


def _mad(d, ok):
    med = _masked_median(d, ok)
    return 1.4826 * jnp.nanmedian(jnp.where(ok[:, None], jnp.abs(d - med), jnp.nan), axis=0)


# --------------------------------------------------------------------------- temperature read-out


def temperature_quantum(temp: np.ndarray) -> float:
    """Read-out step of a quantised temperature (°C), 0 when it is not quantised.

    Quantised read-outs change by whole steps: the nonzero successive
    differences are (within 5 %) integer multiples of their median.
    """
    temp = np.asarray(temp, float)
    d = np.abs(np.diff(temp[np.isfinite(temp)]))
    nz = d[d > 1e-9]
    if nz.size < 10:
        return 0.0
    q = float(np.median(nz))
    r = nz / q
    return q if np.mean(np.abs(r - np.round(r)) < 0.05) >= 0.9 else 0.0


def suggest_dtemp_window(batch: Batch, default: float = 60.0) -> float:
    """dT/dt window (s) for a batch: wide enough that read-out noise and steps do not flip
    the heating/cooling latch or swamp the gradient column.

    The centred slope over ``W`` seconds of a read-out with noise σ_T (or a
    quantised one, σ_T ≈ step/√12) has σ ≈ σ_T·√(12/(f_s·W³)); ``W`` is
    chosen so that this is a fifth of the latch's threshold (0.05 °C/min),
    never below ``default``, then rounded up to 60, 90, 120, 180, 240, 360,
    480 or 600 s (few distinct values: each compiles once).
    """
    from .signals import HEATING_THRESHOLD

    if batch.temp is None:
        return default
    need = default
    for i in range(batch.n_devices):
        n = int(batch.n_valid[i])
        temp = np.asarray(batch.temp[i, :n], float)
        if n < 10:
            continue
        q = temperature_quantum(temp)
        d = np.diff(temp)
        sigma = 1.4826 * np.median(np.abs(d - np.median(d))) / math.sqrt(2.0)
        sigma = max(sigma, q / math.sqrt(12.0))
        fs = 1.0 / max(float(np.median(np.diff(batch.t[i, :n]))), 1e-9)
        if sigma > 0:
            w = (5.0 * sigma * math.sqrt(12.0 / fs) / HEATING_THRESHOLD) ** (2.0 / 3.0)
            need = max(need, w)
    for w in (60.0, 90.0, 120.0, 180.0, 240.0, 360.0, 480.0, 600.0):
        if w >= need:
            return max(w, default)
    return 600.0


# --------------------------------------------------------------------------- candidates


@dataclass(frozen=True)
class CandidateSpec:
    """One candidate: the model with ``term`` added (or ``old`` raised to ``term``)."""

    effect: str
    term: AbstractEffect
    model: ErrorModel
    old: AbstractEffect | None = None  # the term it replaces (order raised)

    @property
    def spec(self) -> str:
        return self.model.spec

    @property
    def stochastic(self) -> bool:
        return self.term.stochastic


def _new_terms(cls, present: AbstractEffect | None) -> list[AbstractEffect]:
    """The terms to try for one effect: an absent one at its default order, or at orders 0
    and 1 when it has no default (a constant and a temperature-dependent one); a present
    one with its order raised by one."""
    if present is None:
        if cls.order_arg:
            if cls.default_order is not None:
                return [cls(order=cls.default_order)]
            return [cls(order=0), cls(order=1)]
        return [cls()]
    if cls.order_arg and present.order < MAX_ORDER:
        return [cls(order=present.order + 1)]
    return []


def candidate_specs(model: ErrorModel, available: frozenset[str],
                    names: list[str] | None = None) -> list[CandidateSpec]:
    """Every registered effect the data supports and ``model`` lacks (or can raise).

    An effect already in the model with an order (``bias_poly(2)``) is offered
    one order higher; an absent one at its default order, or at orders 0 and 1
    when it has none (a scale factor that drifts with temperature is
    ``scale_poly(1)``; ``scale_poly(0)`` alone can be worse than nothing
    there). ``names`` limits the search to those effect names (or full terms
    such as ``bias_poly(3)``). Order-k columns must be the first columns of
    order k+1 (true of the built-in polynomial terms) for a raised candidate
    to be scored.
    """
    from .effects import parse_term

    present = {t.name: t for t in model.terms}
    wanted: dict[str, list[AbstractEffect] | None] = {}
    if names is None:
        wanted = {n: None for n in registry()}
    else:
        for text in names:
            text = text.strip()
            if text in registry():  # a bare name: the default candidates of that effect
                wanted[text] = None
                continue
            term = parse_term(text)
            wanted.setdefault(term.name, [])
            if wanted[term.name] is not None:
                wanted[term.name].append(term)
    out = []
    for name, explicit in wanted.items():
        cls = registry()[name]
        old = present.get(name)
        for term in (explicit if explicit is not None else _new_terms(cls, old)):
            if old is not None and (term == old or not cls.order_arg or term.order <= old.order):
                continue
            if not term.requires() <= available | {"t", "gyro"}:
                continue
            if old is None:
                new_model = model + term
            else:
                new_model = ErrorModel(tuple(term if t is old else t for t in model.terms))
            out.append(CandidateSpec(effect=name, term=term, model=new_model, old=old))
    return out


# --------------------------------------------------------------------------- the engine (one device)


#: Candidates whose time constant is searched from the dT/dt window up: a lag shorter than
#: the window that estimates dT/dt is the ``gradient`` term at the data's resolution.
LAG_FROM_DTEMP_WINDOW = ("thermal_lag",)


def _extra_columns(c: CandidateSpec, base: ErrorModel, sig: Signals, theta_b, min_lag: float = 0.0):
    """Columns a candidate adds to the base design, one set per grid point: (g, n, 3, k),
    and the grid (g, q) of its nonlinear parameters."""
    term = c.term
    if c.old is not None:
        k_old = c.old.n_params
        q_slice = [qs for t, _, qs in base.slices() if t == c.old]
        th = theta_b[q_slice[0]] if q_slice else jnp.zeros((0,), sig.gyro.dtype)
        cols = term.columns(sig, th)[..., k_old:]
        return cols[None], th[None]
    if term.n_nonlinear == 0:
        return term.columns(sig, jnp.zeros((0,), sig.gyro.dtype))[None], jnp.zeros((1, 0))
    grid = term.nonlinear_grid(sig)
    if grid.shape[1] == 1:
        lo, hi = jnp.min(grid[:, 0]), jnp.max(grid[:, 0])
        if term.name in LAG_FROM_DTEMP_WINDOW and min_lag > 0:
            lo = jnp.maximum(lo, math.log(min_lag))
            hi = jnp.maximum(hi, lo + math.log(4.0))
        grid = jnp.linspace(lo, hi, GRID_POINTS)[:, None]
    cols = jax.vmap(lambda th: term.columns(sig, th))(grid)
    return cols, grid


def _solve_scaled(g, c, d):
    """Solve ``g b = c`` per leading index after scaling columns by ``d`` (tiny ridge)."""
    gs = g / (d[..., :, None] * d[..., None, :])
    eye = jnp.eye(g.shape[-1], dtype=g.dtype)
    gs = gs + 1e-11 * eye
    cs = c / d
    bad = ~jnp.all(jnp.isfinite(gs), axis=(-2, -1))
    gs = jnp.where(bad[..., None, None], eye, gs)
    b = jnp.linalg.solve(gs, cs[..., None])[..., 0] / d
    return jnp.where(bad[..., None], jnp.nan, b)


def _fold_sums(oh, a, b):
    """Per-fold Σ a_i b_j over samples: oh (n, f), a (n, 3, p), b (n, 3, q) -> (f, 3, p, q)."""
    return jnp.einsum("nf,nip,niq->fipq", oh, a, b)


def _local_level(e, obs, t, r, q_rel, p0, keep: bool = True):
    """Local-level (random-walk + white) filter on residuals ``e`` (n, s), one series per column.

    ``r`` (s,) white variance, ``q_rel`` (s,) or (grid, s) walk variance per sample interval
    as a fraction of r (a grid runs every value at once without copying the data).
    Returns filtered mean, variance, predicted variance (n, s) and the log-likelihood of
    the observed samples (s,) or (grid, s).
    """
    dt0 = jnp.maximum(jnp.nanmedian(jnp.diff(t)), 1e-12)
    q = q_rel * r / dt0

    def step(carry, inp):
        a, p, t_prev, ll = carry
        ek, ok, tk = inp
        pp = p + q * jnp.maximum(tk - t_prev, 0.0)
        f = pp + r
        k = pp / f
        innov = ek - a
        a = jnp.where(ok, a + k * innov, a)
        p = jnp.where(ok, pp * r / f, pp)
        ll = ll + jnp.where(ok, -0.5 * (jnp.log(f) + innov**2 / f), 0.0)
        return (a, p, tk, ll), ((a, p, pp) if keep else None)

    shape = jnp.broadcast_shapes(jnp.shape(q), (e.shape[1],))  # (s,) or (grid, s)
    init = (jnp.zeros(shape, e.dtype), jnp.full(shape, p0, e.dtype), t[0], jnp.zeros(shape, e.dtype))
    (_, _, _, ll), outs = jax.lax.scan(step, init, (e, obs, t))
    if not keep:
        return None, None, None, ll
    mf, pf, pp = outs
    return mf, pf, pp, ll


def _rts(mf, pf, pp):
    """Rauch–Tung–Striebel smoother for the local level (n, s)."""

    def back(carry, inp):
        ms_next = carry
        m_k, p_k, pp_next = inp
        g = p_k / jnp.maximum(pp_next, 1e-300)
        ms = m_k + g * (ms_next - m_k)
        return ms, ms

    _, ms = jax.lax.scan(back, mf[-1], (mf[:-1], pf[:-1], pp[1:]), reverse=True)
    return jnp.concatenate([ms, mf[-1:]], axis=0)


def _device_engine(base: ErrorModel, cands: tuple[CandidateSpec, ...], n_blocks: int, n_folds: int,
                   min_lag: float, sig: Signals, beta_b, theta_b, floor_axes):
    """Held-out scores of the base model, every deterministic candidate and the random walk."""
    from .fit import _fold_ids

    dtype = sig.gyro.dtype
    y = sig.gyro - sig.rate
    w = sig.mask.astype(dtype)
    xb = base.design(sig, theta_b) if base.n_params else jnp.zeros((y.shape[0], 3, 0), dtype)
    e = (y - jnp.einsum("nip,ip->ni", xb, beta_b)) * w[:, None]  # base residual (full fit)
    e = jnp.where(jnp.isfinite(e), e, 0.0)
    fold = _fold_ids(sig.mask, n_blocks, n_folds)
    oh = (fold[:, None] == jnp.arange(n_folds)[None, :]).astype(dtype)  # (n, f)
    cnt = jnp.sum(oh, axis=0)
    # time block of every valid sample (padding -> an extra, ignored segment)
    k_valid = jnp.cumsum(sig.mask) - 1
    block = jnp.where(sig.mask, (k_valid * n_blocks) // jnp.maximum(jnp.sum(sig.mask), 1), n_blocks)
    fsafe = jnp.clip(fold, 0, n_folds - 1)

    def per_block(r2):  # (n,) -> (n_blocks,)
        return jax.ops.segment_sum(r2 * w, block, num_segments=n_blocks + 1)[:n_blocks]

    blk_cnt = per_block(jnp.ones_like(w))
    ee = jnp.einsum("nf,ni->fi", oh, e * e)  # (f, 3)

    def train(s):
        return jnp.sum(s, axis=0, keepdims=True) - s

    p = xb.shape[-1]
    xx = _fold_sums(oh, xb, xb)  # (f, 3, p, p)
    xe = jnp.einsum("nf,nip,ni->fip", oh, xb, e)
    dx = jnp.sqrt(jnp.maximum(jnp.diagonal(jnp.sum(xx, 0), axis1=-2, axis2=-1), 1e-300))  # (3, p)

    def held_sse(b, g_h, c_h, q_h):
        return q_h - 2.0 * jnp.sum(b * c_h, -1) + jnp.einsum("...p,...pq,...q->...", b, g_h, b)

    b_base = _solve_scaled(train(xx), train(xe), dx) if p else jnp.zeros((n_folds, 3, 0), dtype)
    base_sse = held_sse(b_base, xx, xe, ee) if p else ee  # (f, 3)
    r_base = e - jnp.einsum("nip,nip->ni", xb, b_base[fsafe])  # held-out residual of every sample
    base_blk = per_block(jnp.sum(r_base**2, -1))

    eetr = train(ee)  # (f, 3)
    xw = oh.T[:, :, None, None] * xb[None]  # (f, n, 3, p)
    ew = oh.T[:, :, None] * e[None]  # (f, n, 3)

    def score(z):
        """Per-fold training and held-out SSE of base + z for every column set (g, n, 3, k)."""
        z = jnp.where(jnp.isfinite(z), z, 0.0) * w[None, :, None, None]
        # fold weights go on the small operands, so no (g, n, folds) temporary is formed
        zx = jnp.einsum("fnip,gnik->gfikp", xw, z)
        ze = jnp.einsum("fni,gnik->gfik", ew, z)
        zz = jnp.stack([jnp.einsum("gnik,gnil->gikl", z * oh[None, :, f, None, None], z)
                        for f in range(n_folds)], axis=1)
        g_n = z.shape[0]
        xxg = jnp.broadcast_to(xx, (g_n,) + xx.shape)
        top = jnp.concatenate([xxg, jnp.swapaxes(zx, -1, -2)], axis=-1)
        bot = jnp.concatenate([zx, zz], axis=-1)
        gm = jnp.concatenate([top, bot], axis=-2)  # (g, f, 3, P, P)
        cv = jnp.concatenate([jnp.broadcast_to(xe, (g_n,) + xe.shape), ze], axis=-1)
        gtot = jnp.sum(gm, axis=1)  # (g, 3, P, P)
        ctot = jnp.sum(cv, axis=1)
        d = jnp.sqrt(jnp.maximum(jnp.diagonal(gtot, axis1=-2, axis2=-1), 1e-300))  # (g, 3, P)
        gtr = jnp.sum(gm, axis=1, keepdims=True) - gm
        ctr = jnp.sum(cv, axis=1, keepdims=True) - cv
        b = _solve_scaled(gtr, ctr, d[:, None])  # (g, f, 3, P)
        sse_tr = jnp.sum(eetr[None] - jnp.sum(b * ctr, -1), -1)  # (g, f)
        sse_h = held_sse(b, gm, cv, ee[None])  # (g, f, 3)
        b_all = _solve_scaled(gtot, ctot, d)  # (g, 3, P)
        sse_all = jnp.sum(ee, 0)[None] - jnp.sum(b_all * ctot, -1)  # (g, 3)
        clean = lambda a: jnp.where(jnp.isfinite(a), a, jnp.inf)  # noqa: E731
        return z, b, clean(sse_tr), sse_h, sse_all, clean(jnp.sum(sse_all, -1))

    folds = jnp.arange(n_folds)

    def scored_groups(column_sets):
        """Score every (g, n, 3, k) column set; sets with the same k share one compiled pass."""
        by_k: dict[int, list[int]] = {}
        for j, z in enumerate(column_sets):
            by_k.setdefault(int(z.shape[-1]), []).append(j)
        out = [None] * len(column_sets)
        for idx in by_k.values():
            sizes = [int(column_sets[j].shape[0]) for j in idx]
            res = score(jnp.concatenate([column_sets[j] for j in idx], axis=0))
            start = 0
            for j, g in zip(idx, sizes):
                out[j] = tuple(a[start:start + g] for a in res)
                start += g
        return out

    columns = [_extra_columns(c, base, sig, theta_b, min_lag) for c in cands]  # (z, grid)
    first = scored_groups([z for z, _ in columns])
    state = []
    for (_, grid), (z, b, tr, sse_h, sse_all, tot_all) in zip(columns, first):
        pick = jnp.argmin(tr, axis=0)  # (f,) grid point chosen on each fold's training blocks
        best = jnp.argmin(tot_all)
        state.append(dict(
            grid=grid, pick=pick, best=best, tr_pick=tr[pick, folds], tot_best=tot_all[best],
            held=sse_h[pick, folds], b_pick=b[pick, folds], z_fold=z[pick], full=sse_all[best],
            theta=grid[best] if grid.shape[1] else jnp.full((1,), jnp.nan, dtype), tr=tr,
            tot_all=tot_all))

    # refine one time constant between grid points (a parabola through the neighbours),
    # again chosen on each fold's training blocks only
    refine = [j for j, (_, grid) in enumerate(columns) if grid.shape[0] >= 3 and grid.shape[1] == 1]

    def vertex(costs, i, grid):
        i = jnp.clip(i, 1, grid.shape[0] - 2)
        c0, c1, c2 = costs[i - 1], costs[i], costs[i + 1]
        den = c0 - 2.0 * c1 + c2
        off = jnp.where((den > 0) & jnp.isfinite(den), 0.5 * (c0 - c2) / jnp.where(den > 0, den, 1.0), 0.0)
        return grid[i, 0] + jnp.clip(off, -1.0, 1.0) * (grid[1, 0] - grid[0, 0])

    thetas2, sets2 = [], []
    for j in refine:
        st, term = state[j], cands[j].term
        th2 = jnp.concatenate([jax.vmap(vertex, in_axes=(1, 0, None))(st["tr"], st["pick"], st["grid"]),
                               vertex(st["tot_all"], st["best"], st["grid"])[None]])  # (f+1,)
        thetas2.append(th2)
        sets2.append(jax.vmap(lambda th, term=term: term.columns(sig, th[None]))(th2))
    for j, th2, (z2, b2, tr2, sse_h2, sse_all2, tot_all2) in zip(refine, thetas2, scored_groups(sets2)):
        st = state[j]
        better = tr2[folds, folds] < st["tr_pick"]  # keep the refinement only where it helps
        st["held"] = jnp.where(better[:, None], sse_h2[folds, folds], st["held"])
        st["b_pick"] = jnp.where(better[:, None, None], b2[folds, folds], st["b_pick"])
        st["z_fold"] = jnp.where(better[:, None, None, None], z2[:n_folds], st["z_fold"])
        full_better = tot_all2[n_folds] < st["tot_best"]
        st["full"] = jnp.where(full_better, sse_all2[n_folds], st["full"])
        st["theta"] = jnp.where(full_better, th2[n_folds:], st["theta"])

    cand_sse, cand_full, cand_theta, cand_blk, edges = [], [], [], [], []
    for st in state:
        grid = st["grid"]
        if grid.shape[0] >= 2 and grid.shape[1] == 1:
            edges.append(st["theta"][0] >= grid[-1, 0] - 0.5 * (grid[1, 0] - grid[0, 0]))
        else:
            edges.append(jnp.asarray(False))
        cand_sse.append(st["held"])
        bn = st["b_pick"][fsafe]  # (n, 3, P)
        zn = st["z_fold"][fsafe, jnp.arange(e.shape[0])]  # (n, 3, k)
        r_c = e - jnp.einsum("nip,nip->ni", xb, bn[..., :p]) - jnp.einsum("nik,nik->ni", zn, bn[..., p:])
        cand_blk.append(per_block(jnp.sum(jnp.where(jnp.isfinite(r_c), r_c, 0.0) ** 2, -1)))
        cand_full.append(st["full"])
        cand_theta.append(st["theta"])

    # random walk: local level on the base residual of each fold's training fit
    r = jnp.maximum(floor_axes**2, 1e-300)
    e_f = e[None] - jnp.einsum("nip,fip->fni", xb, b_base) * w[None, :, None] if p else \
        jnp.broadcast_to(e, (n_folds,) + e.shape)
    e_all = jnp.concatenate([e_f, e[None]], axis=0)  # (f+1, n, 3)
    obs = jnp.concatenate([(fold[None, :] != jnp.arange(n_folds)[:, None]) & sig.mask[None],
                           sig.mask[None]], axis=0)  # (f+1, n)
    s_f = n_folds + 1
    qg = jnp.asarray(RW_GRID, dtype)
    n_q = qg.shape[0]
    e2 = e_all.transpose(1, 0, 2).reshape(e.shape[0], -1)  # (n, (f+1)·3)
    o2 = jnp.broadcast_to(obs.T[:, :, None], (e.shape[0], s_f, 3)).reshape(e.shape[0], -1)
    r2 = jnp.broadcast_to(r, (s_f, 3)).reshape(-1)
    p0 = 10.0 * jnp.maximum(jnp.sum(e * e) / jnp.maximum(3 * jnp.sum(w), 1.0), jnp.max(r))
    _, _, _, ll = _local_level(e2, o2, sig.t, r2, jnp.broadcast_to(qg[:, None], (n_q, r2.shape[0])),
                               p0, keep=False)
    qi = jnp.argmax(ll.reshape(n_q, s_f, 3), axis=0)  # (f+1, 3)
    q_best = qg[qi].reshape(-1)
    mf, pf, pp, _ = _local_level(e2, o2, sig.t, r2, q_best, p0)
    ms = _rts(mf, pf, pp)
    held = (oh.T[:, :, None] > 0)  # (f, n, 1)
    ms3 = ms.reshape(e.shape[0], s_f, 3).transpose(1, 0, 2)
    mf3 = mf.reshape(e.shape[0], s_f, 3).transpose(1, 0, 2)
    rw_interp = jnp.sum(jnp.where(held, (e_f - ms3[:n_folds]) ** 2, 0.0), axis=1)  # (f, 3)
    r_rw = jnp.sum(jnp.where(held, (e_f - ms3[:n_folds]) ** 2, 0.0), axis=(0, 2))  # (n,)
    rw_fore = jnp.sum(jnp.where(held, (e_f - mf3[:n_folds]) ** 2, 0.0), axis=1)
    rw_full = jnp.sum(w[:, None] * (e - ms3[n_folds]) ** 2, axis=0)  # (3,)
    dt0 = jnp.maximum(jnp.nanmedian(jnp.diff(sig.t)), 1e-12)
    rw_q = qg[qi[n_folds]] * r / dt0  # (3,) (rad/s)²/s

    return dict(
        cnt=cnt, base_sse=base_sse, base_full=jnp.sum(e * e, 0),
        # (one NaN placeholder when there is no candidate: lax.map dislikes empty outputs)
        cand_sse=jnp.stack(cand_sse) if cands else jnp.full((1, n_folds, 3), jnp.nan, dtype),
        cand_full=jnp.stack(cand_full) if cands else jnp.full((1, 3), jnp.nan, dtype),
        cand_theta=_stack_theta(cand_theta, dtype),
        rw_interp=rw_interp, rw_fore=rw_fore, rw_full=rw_full, rw_q=rw_q,
        blk_cnt=blk_cnt, base_blk=base_blk, rw_blk=per_block(r_rw),
        cand_blk=jnp.stack(cand_blk) if cands else jnp.full((1, n_blocks), jnp.nan, dtype),
        cand_edge=jnp.stack(edges) if cands else jnp.zeros((1,), bool),
        rw_walk=ms3[n_folds], residual=e,
    )


def _stack_theta(thetas, dtype):
    if not thetas:
        return jnp.full((1, 1), jnp.nan, dtype)
    q = max(int(t.shape[0]) for t in thetas)
    return jnp.stack([jnp.pad(t, (0, q - t.shape[0]), constant_values=jnp.nan) for t in thetas])


@eqx.filter_jit
def _engine_batch(base, cands, n_blocks, n_folds, min_lag, sig, beta, theta, floor_axes):
    def one(args):
        s, b, th, fl = args
        return _device_engine(base, cands, n_blocks, n_folds, min_lag, s, b, th, fl)

    return jax.lax.map(one, (sig, beta, theta, floor_axes), batch_size=1)


@eqx.filter_jit
def _floors(sig: Signals):
    def one(s):
        return noise_floor(s.gyro - s.rate, s.mask, s.rate if s.has_rate else None)

    return jax.lax.map(one, sig)


def device_bucket(n: int) -> int:
    """Padded device count of the compiled diagnosis: 1, 2, 4, ... 64, then multiples of 64."""
    n = max(int(n), 1)
    return 1 << (n - 1).bit_length() if n <= 64 else -(-n // 64) * 64


def _pad_devices(tree, n: int, m: int):
    """Repeat the last device of every leading-axis array up to ``m`` devices."""
    if m == n:
        return tree
    idx = np.minimum(np.arange(m), n - 1)
    return jax.tree.map(lambda a: a[idx] if getattr(a, "ndim", 0) and a.shape[0] == n else a, tree)


@eqx.filter_jit
def _signals_jit(t, gyro, mask, rate, temp, temp_ext, accel, norm, dt, dtemp_window):
    from .signals import make_signals

    def one(t, gyro, mask, rate, temp, temp_ext, accel, norm, dt):
        return make_signals(t, gyro, mask, rate=rate, temp=temp, temp_ext=temp_ext, accel=accel,
                            norm=norm, dtemp_window=dtemp_window, dt=dt)

    return jax.vmap(one)(t, gyro, mask, rate, temp, temp_ext, accel, norm, dt)


def _signals(batch: Batch, res, n: int, m: int) -> Signals:
    """The fit's derived signals (its TempNorm and dT/dt window), padded to ``m`` devices,
    through one compiled function (``FitResult.signals`` runs op by op)."""
    from .fit import sampling_intervals
    from .signals import TempNorm

    idx = np.minimum(np.arange(m), n - 1)

    def arr(x):
        return None if x is None else jnp.asarray(np.asarray(x, np.float64)[idx])

    norm = None
    if res.model.requires() & {"temp"}:
        norm = TempNorm(centre=jnp.broadcast_to(jnp.asarray(res.norm.centre, jnp.float64), (n,))[idx],
                        scale=jnp.broadcast_to(jnp.asarray(res.norm.scale, jnp.float64), (n,))[idx])
    return _signals_jit(arr(batch.t), arr(batch.gyro), jnp.asarray(np.asarray(batch.mask)[idx]),
                        arr(batch.rate), arr(batch.temp), arr(batch.temp_ext), arr(batch.accel), norm,
                        jnp.asarray(sampling_intervals(batch)[idx]), float(res.options.dtemp_window))


@eqx.filter_jit
def _ranges(cands, sig):
    """(devices, candidates): > 0 where a device's data cannot support the candidate term."""
    return jax.vmap(lambda s: jnp.stack([c.term.range_problem(s) for c in cands]))(sig)


class AllanCurves(eqx.Module):
    """Overlapping Allan deviation of the residuals: ``tau``, ``adev`` (devices, 3, k)."""

    tau: np.ndarray
    adev: np.ndarray


# --------------------------------------------------------------------------- results


@dataclass
class Candidate:
    """One candidate of one device: held-out RMS of the model with the term added, and the test."""

    effect: str
    spec: str
    heldout_rms: float
    significant: bool
    gain: float          # held-out MSE gain / floor MSE
    closure: float       # share of (base held-out MSE − floor MSE) closed
    t: float             # paired t over the folds
    folds_improved: int
    rms: float           # in-sample RMS with the term
    tau: float | None = None  # chosen time constant (s), for nonlinear terms
    family: str | None = None
    stochastic: bool = False
    note: str = ""
    term: str = ""       # the term added or raised, as written in a spec (``scale_poly(1)``)

    def record(self) -> dict:
        out = {"effect": self.effect, "spec": self.spec, "heldout_rms": number(self.heldout_rms),
               "significant": bool(self.significant), "gain": number(self.gain),
               "closure": number(self.closure), "t": number(self.t),
               "folds_improved": self.folds_improved, "rms": number(self.rms)}
        if self.term:
            out["term"] = self.term
        if self.tau is not None:
            out["tau"] = number(self.tau)
        if self.family:
            out["family"] = self.family
        if self.note:
            out["note"] = self.note
        return out


@dataclass
class DeviceDiagnosis:
    device: str
    status: str
    rms: float
    heldout_rms: float
    noise_floor: float
    noise_axes: list[float]
    floor_allan: float
    verdict: str
    candidates: list[Candidate]
    best: Candidate | None
    alternatives: list[Candidate]
    random_walk: Candidate | None
    allan_slope: float
    evidence: dict = field(default_factory=dict)
    explanation: str = ""
    skipped: dict = field(default_factory=dict)

    @property
    def excess(self) -> float:
        return (self.heldout_rms**2 - self.noise_floor**2) / max(self.noise_floor**2, 1e-300)

    def record(self) -> dict:
        return {
            "device": self.device, "rms": number(self.rms), "heldout_rms": number(self.heldout_rms),
            "noise_floor": number(self.noise_floor), "verdict": self.verdict,
            "candidates": [c.record() for c in self.candidates],
            "status": self.status,
            "best": self.best.spec if self.best else None,
            "best_effect": self.best.effect if self.best else None,
            "best_term": self.best.term if self.best else None,
            "alternatives": [{"effect": c.effect, "spec": c.spec, "heldout_rms": number(c.heldout_rms)}
                             for c in self.alternatives],
            "noise_floor_axes": [number(v) for v in self.noise_axes],
            "noise_floor_allan": number(self.floor_allan),
            "excess": number(self.excess),
            "allan_slope": number(self.allan_slope),
            "random_walk": self.random_walk.record() if self.random_walk else None,
            "evidence": self.evidence,
            "skipped": self.skipped,
            "explanation": self.explanation,
        }


@dataclass
class Diagnosis:
    """Diagnosis of every device of a batch against ``model``."""

    model: ErrorModel
    devices: list[DeviceDiagnosis]
    fit: object  # FitResult of the base model
    residuals: np.ndarray  # (d, n, 3), padding zeroed
    allan: object  # AllanCurves of the residuals (tau, adev), leading axes (d, 3)
    thresholds: Thresholds
    options: dict = field(default_factory=dict)
    #: Per-fold numbers behind every decision (re-decide with other thresholds: :func:`redecide`).
    raw: dict = field(default_factory=dict, repr=False)

    @property
    def spec(self) -> str:
        return self.model.spec

    def device(self, key: int | str) -> DeviceDiagnosis:
        if isinstance(key, int):
            return self.devices[key]
        for d in self.devices:
            if d.device == key:
                return d
        raise KeyError(key)

    def to_json(self) -> dict:
        """The DESIGN.md §4 ``diagnose --json`` object (extra keys per device)."""
        return _plain({"model": self.spec, "devices": [d.record() for d in self.devices],
                       "thresholds": asdict(self.thresholds),
                       "dtemp_window": self.options.get("dtemp_window")})

    def records(self) -> list[dict]:
        """One JSON-ready record per device (the ``devices`` list of :meth:`to_json`)."""
        return self.to_json()["devices"]

    def verdicts(self) -> dict[str, int]:
        out = {"adequate": 0, "missing_effect": 0}
        for d in self.devices:
            out[d.verdict] += 1
        return out


def _plain(x):
    """JSON-safe copy: numpy scalars to Python, non-finite floats to None."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return number(x)
    return x


# --------------------------------------------------------------------------- evidence in words


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float(np.dot(a, a)) * float(np.dot(b, b)))
    return float(np.dot(a, b) / den) if den > 0 else 0.0


def evidence(residual: np.ndarray, rec: Recording, sig_dev: dict) -> dict:
    """What the residual follows: correlations a person can check in the figures.

    ``residual`` (n, 3) of the base model; ``sig_dev`` the device's derived
    signals as numpy (dtemp, heating). Per signal: the largest |r| over the
    axes, its axis, and where helpful the residual's mean in two regimes.
    """
    e = residual
    n = e.shape[0]
    out: dict = {}

    def add(name, s, per_axis=False, label=None):
        s = np.asarray(s, float)
        if s.ndim == 1 and (not np.all(np.isfinite(s)) or np.std(s) == 0):
            return
        rs = [_corr(e[:, i], s[:, i] if per_axis else s) for i in range(3)]
        i = int(np.argmax(np.abs(rs)))
        out[name] = {"r": round(rs[i], 3), "axis": "xyz"[i], "label": label or name}

    t = rec.t - rec.t[0]
    add("time", t, label="time since start")
    add("early", np.exp(-t / max(t[-1] / 20.0, 1.0)), label="the first minutes after power-on")
    if rec.temp is not None:
        add("temp", rec.temp, label="temperature")
        dtemp = sig_dev.get("dtemp")
        if dtemp is not None:
            add("dtemp", dtemp, label="dT/dt")
        heat = sig_dev.get("heating")
        if heat is not None and np.any(heat > 0) and np.any(heat < 0):
            add("heating", heat, label="heating vs cooling")
            up, down = heat > 0, heat < 0
            i = int(np.argmax(np.abs(e[up].mean(0) - e[down].mean(0))))
            out["heating"]["mean_heating"] = float(e[up, i].mean())
            out["heating"]["mean_cooling"] = float(e[down, i].mean())
        if rec.temp_ext is not None:
            add("temp_diff", rec.temp - rec.temp_ext, label="temp − temp_ext")
    if rec.rate is not None and np.max(np.abs(rec.rate)) > 1e-3:
        add("rate", rec.rate, per_axis=True, label="input rate")
        add("abs_rate", np.abs(rec.rate), per_axis=True, label="|input rate|")
        add("rate3", rec.rate**3, per_axis=True, label="rate³")
        cross = [(abs(_corr(e[:, i], rec.rate[:, j])), _corr(e[:, i], rec.rate[:, j]), i, j)
                 for i in range(3) for j in range(3) if i != j and np.std(rec.rate[:, j]) > 0]
        if cross:
            _, r, i, j = max(cross)
            out["cross_rate"] = {"r": round(r, 3), "axis": "xyz"[i],
                                 "label": f"the {'xyz'[j]} input rate"}
        hi = np.abs(rec.rate) > np.median(np.abs(rec.rate[np.abs(rec.rate) > 1e-3])) if np.any(
            np.abs(rec.rate) > 1e-3) else None
        if hi is not None:
            out["high_rate_rms"] = float(np.sqrt(np.mean(e[hi] ** 2))) if hi.any() else None
            out["low_rate_rms"] = float(np.sqrt(np.mean(e[~hi] ** 2))) if (~hi).any() else None
    if rec.accel is not None:
        f = rec.accel
        if np.ptp(f, axis=0).max() > 1.0:
            best = (0.0, 0)
            for i in range(3):
                a = np.column_stack([f - f.mean(0), np.ones(n)])
                coef, *_ = np.linalg.lstsq(a, e[:, i], rcond=None)
                pred = a @ coef
                r2 = 1 - np.sum((e[:, i] - pred) ** 2) / max(np.sum((e[:, i] - e[:, i].mean()) ** 2), 1e-300)
                if r2 > best[0]:
                    best = (r2, i)
            out["accel"] = {"r": round(math.sqrt(max(best[0], 0.0)), 3), "axis": "xyz"[best[1]],
                            "label": "specific force"}
    return out


#: The signal that names each built-in effect in an explanation.
EFFECT_SIGNAL = {
    "gradient": ("dtemp", "scales with dT/dt"),
    "thermal_lag": ("dtemp", "lags the temperature (follows dT/dt with a delay)"),
    "temp_diff": ("temp_diff", "follows the inside–outside temperature difference"),
    "hysteresis": ("heating", "separates heating from cooling and keeps the offset through soaks"),
    "bias_poly": ("temp", "curves with temperature beyond the current polynomial"),
    "warmup": ("early", "decays in the first minutes after power-on"),
    "scale_poly": ("rate", "grows in proportion to the input rate"),
    "scale_asym": ("abs_rate", "differs between positive and negative input rates"),
    "scale_nonlin": ("rate3", "grows faster than the input rate (∝ rate³)"),
    "misalignment": ("cross_rate", "follows the other axes' rates"),
    "g_sens": ("accel", "follows the specific force (changes with orientation)"),
    "random_walk": ("time", "wanders in time with no physical signal explaining it"),
}


def _fmt(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.2g}"


def explain(d: DeviceDiagnosis) -> str:
    """A short explanation in words naming the evidence."""
    floor = f"noise floor {_fmt(d.noise_floor)} rad/s"
    if d.verdict == "adequate":
        text = (f"{d.device}: adequate — held-out RMS {_fmt(d.heldout_rms)} rad/s against a "
                f"{floor} ({100 * (d.heldout_rms / max(d.noise_floor, 1e-300) - 1):+.0f} %)")
        near = [c for c in d.candidates if c.closure > 0.1][:1]
        if near:
            c = near[0]
            text += (f"; best candidate `{c.effect}` would give {_fmt(c.heldout_rms)} "
                     f"(closes {100 * max(c.closure, 0):.0f} % of a small gap: not material)")
        return text + "."
    b = d.best
    if b is None:
        near = [c for c in d.candidates if c.closure > 0][:3]
        text = (f"{d.device}: missing effect — held-out RMS {_fmt(d.heldout_rms)} rad/s is "
                f"{d.heldout_rms / max(d.noise_floor, 1e-300):.1f}× the {floor}, and no single term "
                f"closes enough of the gap")
        if near:
            text += " (best: " + ", ".join(f"`{c.spec}` {_fmt(c.heldout_rms)}, closes "
                                           f"{100 * c.closure:.0f} %" for c in near) + ")"
        return text + ": several effects may be missing at once, or one outside the vocabulary."
    sig_name, phrase = EFFECT_SIGNAL.get(b.effect, (None, f"follows the `{b.effect}` term"))
    ev = d.evidence.get(sig_name) if sig_name else None
    what = f"residual {phrase}"
    if ev is not None and sig_name != "time":
        what += f" (r = {ev['r']:+.2f} on axis {ev['axis']} with {ev['label']})"
        if sig_name == "heating" and "mean_heating" in ev:
            what += (f"; mean {_fmt(ev['mean_heating'])} rad/s heating vs "
                     f"{_fmt(ev['mean_cooling'])} cooling")
    if b.effect == "random_walk":
        what += f"; Allan slope of the residual at long τ {d.allan_slope:+.2f} (+½ for a random walk)"
    if b.effect in ("scale_asym", "scale_nonlin", "scale_poly") and d.evidence.get("high_rate_rms"):
        what += (f"; residual RMS {_fmt(d.evidence['high_rate_rms'])} at high rates vs "
                 f"{_fmt(d.evidence.get('low_rate_rms'))} at low")
    tau = f" (τ ≈ {b.tau:.0f} s)" if b.tau else ""
    text = (f"{d.device}: {what}: add `{b.term or b.effect}`{tau}; held-out RMS "
            f"{_fmt(d.heldout_rms)} → {_fmt(b.heldout_rms)} rad/s, {floor}.")
    if d.alternatives:
        alts = ", ".join(f"`{c.term or c.effect}` {_fmt(c.heldout_rms)}" for c in d.alternatives)
        fam = family_of(b.effect)
        same = fam is not None and all(family_of(c.effect) == fam for c in d.alternatives)
        text += f" Close alternatives{f' ({fam} family)' if same else ''}: {alts}."
    if b.effect != "random_walk" and d.random_walk is not None and d.random_walk.closure > 0.5:
        text += (f" A random-walk smoother would also follow this residual (held-out "
                 f"{_fmt(d.random_walk.heldout_rms)}), but `{b.effect}` explains it with a "
                 f"physical signal and calibrates future data.")
    if d.floor_allan and abs(d.floor_allan / max(d.noise_floor, 1e-300) - 1) > 0.2:
        text += (f" Note: the short-τ Allan deviation of the residual ({_fmt(d.floor_allan)}) "
                 f"disagrees with the floor (spikes, steps or correlated samples).")
    return text


# --------------------------------------------------------------------------- decision


def _decide(name: str, status: str, base_fold: np.ndarray, cnt: np.ndarray, base_full: np.ndarray,
            names: list[str], specs: list[str], cand_fold: np.ndarray, cand_full: np.ndarray,
            ok: np.ndarray, taus, rw_spec: str | None, rw_fold: np.ndarray, rw_full: np.ndarray,
            floor_axes: np.ndarray, floor_allan: float, slope: float, n_valid: int,
            th: Thresholds, ev: dict, blocks: dict | None = None,
            edge: np.ndarray | None = None, base_spec: str | None = None) -> DeviceDiagnosis:
    """Scores, significance, ranking and verdict of one device from its per-fold numbers."""
    n_held = max(float(np.sum(cnt)), 1.0)
    floor = float(np.sqrt(np.mean(floor_axes**2)))
    f2 = max(floor**2, 1e-300)
    mse_b = base_fold.sum(-1) / np.maximum(3 * cnt, 1.0)  # (f,)
    hb2 = float(base_fold.sum() / (3 * n_held))
    gap = hb2 - f2
    excess = gap / f2
    rms_b = math.sqrt(max(float(np.sum(base_full)) / (3 * max(n_valid, 1)), 0.0))

    def local(j):
        """Material where it happens: in the blocks the candidate improves most."""
        if blocks is None or j is None:
            return False
        bc, bb, cb = blocks["cnt"], blocks["base"], blocks["cand"][j]
        if not (np.all(np.isfinite(cb)) and bc.sum() > 0):
            return False
        k = max(2, int(math.ceil(th.local_share * len(bc))))
        top = np.argsort(bb - cb)[-k:]
        nb = max(3.0 * float(bc[top].sum()), 1.0)
        mb, mc = float(bb[top].sum()) / nb, float(cb[top].sum()) / nb
        return (mb - f2) / f2 >= th.local_excess and (mb - mc) / max(mb - f2, 1e-300) >= th.local_closure

    def score(effect, spec, fold_sse, full_sse, tau=None, stochastic=False, usable=True, j=None):
        mse_c = fold_sse.sum(-1) / np.maximum(3 * cnt, 1.0)
        hc2 = float(fold_sse.sum() / (3 * n_held))
        diff = mse_b - mse_c
        sd = float(np.std(diff, ddof=1)) if diff.size > 1 else 0.0
        mean = float(np.mean(diff))
        t = mean / (sd / math.sqrt(diff.size)) if sd > 0 else (math.inf if mean > 0 else 0.0)
        gain = (hb2 - hc2) / f2
        closure = (hb2 - hc2) / gap if gap > 0.01 * f2 else 0.0
        steady = mean > 0 and (t >= th.t_min or float(np.min(diff)) >= -th.consistency * mean)
        material = excess >= th.excess_min and closure >= th.closure_min and gain >= th.gain_min
        if (not material and not stochastic and gain >= th.local_gain_min
                and closure >= th.local_closure_min):
            material = local(j)
        sig = bool(usable and math.isfinite(hc2) and steady and material)
        return Candidate(effect=effect, spec=spec, heldout_rms=math.sqrt(max(hc2, 0.0)),
                         significant=sig, gain=gain, closure=closure, t=t,
                         folds_improved=int(np.sum(diff > 0)),
                         rms=math.sqrt(max(float(full_sse.sum()) / (3 * max(n_valid, 1)), 0.0)),
                         tau=tau, family=family_of(effect), stochastic=stochastic,
                         term=_added_term(base_spec, spec) if base_spec else effect)

    det: list[Candidate] = []
    skipped: dict = {}
    for j, (effect, spec) in enumerate(zip(names, specs)):
        if not ok[j]:
            skipped[effect] = "the data cannot support it (range: e.g. no rate, no temperature span)"
            continue
        if not np.all(np.isfinite(cand_fold[j])):
            skipped[effect] = "the fit failed"
            continue
        det.append(score(effect, spec, cand_fold[j], cand_full[j], tau=taus[j], j=j))
        if edge is not None and bool(edge[j]):
            det[-1].note = ("time constant at the slow end of the search: a slow drift rather "
                            "than a transient")
    rw_c = None
    if rw_spec:
        rw_c = score("random_walk", rw_spec, rw_fold, rw_full, stochastic=True)
        rw_c.note = ("local-level smoother of the residual; walk variance by maximum likelihood on "
                     "the training blocks")
    det_sig = [c for c in det if c.significant]
    # a term whose time constant ran to the slow end of its search fits a drift, not physics
    physical = [c for c in det_sig if not c.note.startswith("time constant at the slow end")]
    best_phys = min(physical, key=lambda c: c.heldout_rms) if physical else None
    best_det = min(det_sig, key=lambda c: c.heldout_rms) if det_sig else None
    in_contention = rw_c is not None and (
        best_phys is None or (best_phys.closure < th.rw_prefer
                              and 1.0 - best_phys.closure > th.rw_ratio * (1.0 - rw_c.closure)))
    if rw_c is not None:
        rw_c.significant = bool(rw_c.significant and in_contention and excess >= th.rw_excess_min
                                and math.isfinite(slope) and slope >= th.rw_slope_min)
    shown = det + ([rw_c] if in_contention else [])
    shown.sort(key=lambda c: (c.heldout_rms if math.isfinite(c.heldout_rms) else math.inf))
    sig_all = [c for c in shown if c.significant]
    if rw_c is not None and rw_c.significant:
        best = rw_c
    else:
        best = best_det
    # far above the floor with no single term closing it: still not adequate
    verdict = "missing_effect" if sig_all or excess >= th.unexplained_excess else "adequate"
    alts = []
    if best is not None:
        alts = [c for c in sig_all if c is not best and c.closure >= th.alt_share * best.closure]
    d = DeviceDiagnosis(
        device=name, status=status, rms=rms_b, heldout_rms=math.sqrt(max(hb2, 0.0)), noise_floor=floor,
        noise_axes=[float(v) for v in floor_axes], floor_allan=floor_allan, verdict=verdict,
        candidates=shown, best=best, alternatives=alts, random_walk=rw_c, allan_slope=slope,
        evidence=ev, skipped=skipped)
    d.explanation = explain(d)
    return d


def _unfitted(name: str, status: str, floor_axes: np.ndarray) -> DeviceDiagnosis:
    """A device whose base model could not be fitted: nothing to diagnose against."""
    floor = float(np.sqrt(np.mean(floor_axes**2)))
    d = DeviceDiagnosis(
        device=name, status=status, rms=float("nan"), heldout_rms=float("nan"), noise_floor=floor,
        noise_axes=[float(v) for v in floor_axes], floor_allan=float("nan"), verdict="adequate",
        candidates=[], best=None, alternatives=[], random_walk=None, allan_slope=float("nan"))
    d.explanation = (f"{name}: the base model could not be fitted ({status}); the data do not "
                     f"support it, so no effect is named: simplify the model (see `diffgyro fit`).")
    return d


def _allan_slope(adev: np.ndarray, tau: np.ndarray, total: float) -> float:
    """Log-log slope of the residual's (axis-pooled) Allan deviation at long τ (T/100 .. T/8)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a2 = np.nanmean(adev**2, axis=0)
    t = tau[0]
    sel = np.isfinite(a2) & (a2 > 0) & (t >= total / 100.0) & (t <= total / 8.0)
    if sel.sum() < 3:
        return float("nan")
    return float(np.polyfit(np.log(t[sel]), 0.5 * np.log(a2[sel]), 1)[0])


def _edge_from_theta(r: dict):
    """Older saved rows: a time constant at a quarter of the record or more counts as the edge."""
    th = r.get("cand_theta")
    if th is None:
        return None
    total = float(r["n_valid"]) * 0.5
    return np.array([bool(np.isfinite(t[0]) and np.exp(t[0]) >= 0.2 * total) for t in th])


def redecide(row: dict, thresholds: Thresholds, rw_key: str = "rw_interp") -> dict:
    """Re-run the decision of one device from its saved per-fold numbers (threshold tuning).

    ``row`` holds ``raw`` (one device's slice of :attr:`Diagnosis.raw`),
    ``cand_names``, ``cand_specs`` and ``diag`` (its record). Returns the record
    the device would get with ``thresholds``.
    """
    r = row["raw"]
    names, specs = row["cand_names"], row["cand_specs"]
    d = _decide(row["diag"]["device"], row["diag"]["status"], r["base_sse"], r["cnt"], r["base_full"],
                names, specs, r["cand_sse"], r["cand_full"], r["ok"], [None] * len(names),
                row["diag"]["random_walk"]["spec"] if row["diag"].get("random_walk") else None,
                r[rw_key], r["rw_full"], r["floors"], float(r["floor_allan"]), float(r["slope"]),
                int(r["n_valid"]), thresholds, row["diag"].get("evidence", {}),
                blocks={"cnt": r["blk_cnt"], "base": r["base_blk"], "cand": r["cand_blk"]}
                if "blk_cnt" in r else None, edge=r.get("cand_edge", _edge_from_theta(r)))
    return d.record()


# --------------------------------------------------------------------------- public API


def diagnose(
    model: ErrorModel | str,
    batch: Batch | Recording | list[Recording],
    candidates: list[str] | None = None,
    *,
    thresholds: Thresholds | None = None,
    base_fit=None,
    **fit_options,
) -> Diagnosis:
    """Diagnose every device of ``batch`` against ``model``.

    ``candidates`` limits the effects tried (names or terms, default: every
    registered effect the data supports). ``base_fit`` reuses a
    :class:`~diffgyro.fit.FitResult` of ``model`` on this batch. Other
    keywords are fit options (``n_folds``, ``n_blocks``, ``dtemp_window``...).
    Returns a :class:`Diagnosis`; ``.to_json()`` is the ``diagnose --json``
    object.
    """
    release_compiled_if_crowded(interval=1.0)  # before this call compiles its programs
    from . import allan as allan_mod
    from .fit import _as_batch
    from .fit import fit as fit_fn

    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    if any(t.stochastic for t in model.terms):
        from .errors import SpecError

        raise SpecError(f"diagnose takes a deterministic model, not {model.spec!r}",
                        hint="drop random_walk from --model: it is tried as a candidate")
    batch = _as_batch(batch)
    th = thresholds or Thresholds()
    if "dtemp_window" not in fit_options and base_fit is None:
        fit_options["dtemp_window"] = suggest_dtemp_window(batch)
    res = base_fit if base_fit is not None else fit_fn(model, batch, **fit_options)
    opts = res.options
    n_dev = batch.n_devices
    m_dev = device_bucket(n_dev)
    sig = _signals(batch, res, n_dev, m_dev)  # padded to a few device counts: few compiles
    available = frozenset(batch.signals)
    every = [c for c in candidate_specs(model, available, candidates) if not c.stochastic]
    want_rw = any(c.stochastic for c in candidate_specs(model, available, candidates))
    # drop candidates no device can support (e.g. scale terms on a static run) before compiling
    all_ranges = np.asarray(_ranges(tuple(every), sig))[:n_dev] if every else np.zeros((n_dev, 0))
    usable = [j for j in range(len(every)) if np.any(all_ranges[:, j] <= 0)]
    cands = [every[j] for j in usable]
    unsupported = [c.effect for j, c in enumerate(every) if j not in usable]
    cands_t = tuple(cands)
    floors_p = _floors(sig)  # (m, 3)
    floors = np.asarray(floors_p)[:n_dev]
    beta = _pad_devices(jnp.asarray(res.params.beta)[:n_dev], n_dev, m_dev)
    theta = _pad_devices(jnp.asarray(res.params.theta)[:n_dev], n_dev, m_dev)
    out = _engine_batch(model, cands_t, opts.n_blocks, opts.n_folds, float(opts.dtemp_window), sig,
                        beta, theta, floors_p)
    out = {k: np.asarray(v)[:n_dev] for k, v in out.items()}
    if not cands_t:
        for k in ("cand_sse", "cand_full", "cand_theta", "cand_blk", "cand_edge"):
            out[k] = out[k][:, :0]
    ranges = all_ranges[:, usable]

    resid = out["residual"]
    dts = np.array([allan_mod.sample_interval(batch.t[i], batch.n_valid[i]) for i in range(n_dev)])
    pick = np.minimum(np.arange(m_dev), n_dev - 1)
    m = allan_mod.default_m(int(np.max(batch.n_valid)), per_decade=8)
    adev_p, _ = allan_mod.oadev(jnp.asarray(np.moveaxis(resid, -1, 1)[pick]), jnp.asarray(dts[pick, None]),
                                jnp.asarray(m), jnp.asarray(np.repeat(np.asarray(batch.n_valid)[pick, None],
                                                                      3, axis=1)))
    adev = np.asarray(adev_p)[:n_dev]
    tau = dts[:, None, None] * np.asarray(m)[None, None, :] * np.ones((1, 3, 1))
    al = AllanCurves(tau=tau, adev=adev)

    devices = []
    slopes, floor_allans = [], []
    for i in range(batch.n_devices):
        nv = int(batch.n_valid[i])
        total = float(batch.t[i, nv - 1] - batch.t[i, 0])
        slope = _allan_slope(adev[i], tau[i], total)
        first = np.isfinite(adev[i][:, 0])
        floor_allan = float(np.sqrt(np.mean(adev[i][first, 0] ** 2))) if first.any() else float("nan")
        slopes.append(slope)
        floor_allans.append(floor_allan)
        taus = []
        for j, c in enumerate(cands):
            th_j = out["cand_theta"][i, j]
            if c.old is None and c.term.n_nonlinear == 1 and np.isfinite(th_j).all():
                taus.append(float(np.asarray(c.term.nonlinear_values(jnp.asarray(th_j)))[0]))
            else:
                taus.append(None)
        rw_spec = (model + "random_walk").spec if want_rw else None
        rec = batch.recording(i)
        sd = {"dtemp": None if sig.dtemp is None else np.asarray(sig.dtemp[i, :nv]),
              "heating": None if sig.heating is None else np.asarray(sig.heating[i, :nv])}
        ev = evidence(resid[i, :nv], rec, sd)
        ok = ranges[i] <= 0 if ranges.size else np.zeros(0, bool)
        if not (np.all(np.isfinite(np.asarray(res.params.beta[i])))
                and np.all(np.isfinite(np.asarray(res.params.theta[i])))):
            devices.append(_unfitted(batch.devices[i], res.status_detail(i), floors[i]))
            continue
        devices.append(_decide(
            batch.devices[i], res.status_name(i), out["base_sse"][i], out["cnt"][i],
            out["base_full"][i], [c.effect for c in cands], [c.spec for c in cands],
            out["cand_sse"][i], out["cand_full"][i], ok, taus, rw_spec, out["rw_interp"][i],
            out["rw_full"][i], floors[i], floor_allan, slope, nv, th, ev,
            blocks={"cnt": out["blk_cnt"][i], "base": out["base_blk"][i], "cand": out["cand_blk"][i]},
            edge=out["cand_edge"][i], base_spec=model.spec))
        for name in unsupported:
            devices[-1].skipped[name] = "the data cannot support it (range: e.g. no rate, no temperature span)"
    return Diagnosis(model=model, devices=devices, fit=res, residuals=resid, allan=al, thresholds=th,
                     options={"n_blocks": opts.n_blocks, "n_folds": opts.n_folds,
                              "dtemp_window": opts.dtemp_window},
                     raw={**{k: v for k, v in out.items() if k != "residual"}, "floors": floors,
                          "ok": ranges <= 0, "slope": np.asarray(slopes),
                          "floor_allan": np.asarray(floor_allans), "candidates": cands,
                          "n_valid": np.asarray(batch.n_valid)})


# --------------------------------------------------------------------------- the ladder (--auto)


@dataclass
class LadderStep:
    """One rung: the model, the effect added to reach it, and per-device numbers."""

    spec: str
    added: str | None
    heldout_rms: list[float]
    noise_floor: list[float]
    rms: list[float]
    verdicts: list[str]

    def record(self, devices) -> dict:
        return {"spec": self.spec, "added": self.added,
                "devices": [{"device": dev, "heldout_rms": number(h), "rms": number(r),
                             "noise_floor": number(f), "verdict": v}
                            for dev, h, r, f, v in zip(devices, self.heldout_rms, self.rms,
                                                       self.noise_floor, self.verdicts)]}


@dataclass
class Ladder:
    """Held-out RMS as terms are added, from the base model to an adequate one."""

    devices: list[str]
    steps: list[LadderStep]
    first: Diagnosis   # diagnosis of the base model
    final: Diagnosis   # diagnosis of the last deterministic model

    @property
    def spec(self) -> str:
        return self.steps[-1].spec

    def records(self) -> list[dict]:
        return [s.record(self.devices) for s in self.steps]

    def table_rows(self) -> list[tuple[str, str, float, float, int]]:
        """(added, spec, median held-out, median floor, adequate count) per rung."""
        return [(s.added or "(base)", s.spec, float(np.median(s.heldout_rms)),
                 float(np.median(s.noise_floor)), sum(v == "adequate" for v in s.verdicts))
                for s in self.steps]

    def html_table(self) -> str:
        import html as _html

        rows = "".join(
            f"<tr><td class=l>{_html.escape(a)}</td><td class=l><code>{_html.escape(sp)}</code></td>"
            f"<td>{h:.3g}</td><td>{f:.3g}</td><td>{k}/{len(self.devices)}</td></tr>"
            for a, sp, h, f, k in self.table_rows())
        return ("<table><tr><th class=l>added</th><th class=l>model</th><th>median held-out RMS</th>"
                f"<th>median noise floor</th><th>adequate</th></tr>{rows}</table>")


def _step(diag: Diagnosis, added: str | None) -> LadderStep:
    return LadderStep(spec=diag.spec, added=added,
                      heldout_rms=[d.heldout_rms for d in diag.devices],
                      noise_floor=[d.noise_floor for d in diag.devices],
                      rms=[d.rms for d in diag.devices], verdicts=[d.verdict for d in diag.devices])


def choose_effect(diag: Diagnosis) -> tuple[str, str] | None:
    """(effect, spec) to add for a batch: the effect named best by most devices missing one
    (ties: the lower median held-out RMS), in the spec most of those devices chose."""
    votes: dict[str, list[tuple[float, str]]] = {}
    for d in diag.devices:
        if d.verdict == "missing_effect" and d.best is not None:
            votes.setdefault(d.best.effect, []).append(
                (d.best.heldout_rms / max(d.noise_floor, 1e-300), d.best.spec))
    if not votes:
        return None
    effect = min(votes, key=lambda k: (-len(votes[k]), float(np.median([v for v, _ in votes[k]]))))
    specs = [sp for _, sp in votes[effect]]
    return effect, max(dict.fromkeys(specs), key=specs.count)


def _added_term(old: str, new: str) -> str:
    """The term text that ``new`` has and ``old`` lacks (``scale_poly(1)``, ``bias_poly(3)``)."""
    extra = [t for t in new.split("+") if t not in old.split("+")]
    return "+".join(extra) or new


def diagnose_auto(
    model: ErrorModel | str,
    batch: Batch | Recording | list[Recording],
    candidates: list[str] | None = None,
    *,
    max_steps: int = 6,
    thresholds: Thresholds | None = None,
    progress=None,
    **fit_options,
) -> Ladder:
    """Repeat "add the best significant candidate" until every device is adequate.

    One model for the whole batch: each rung adds the effect that most
    devices missing an effect name as their best. A random walk ends the
    ladder (its rung reports the smoother's held-out numbers). ``progress``
    is called with a line of text before each diagnosis.
    """
    from .fit import _as_batch

    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    batch = _as_batch(batch)
    th = thresholds or Thresholds()
    if "dtemp_window" not in fit_options:
        fit_options["dtemp_window"] = suggest_dtemp_window(batch)
    say = progress or (lambda _text: None)
    say(f"diagnosing {model.spec}")
    diag = diagnose(model, batch, candidates, thresholds=th, **fit_options)
    first = diag
    steps = [_step(diag, None)]
    for _ in range(max_steps):
        choice = choose_effect(diag)
        if choice is None:
            break
        effect, spec = choice
        if effect == "random_walk":
            rws = [d.random_walk for d in diag.devices]
            h = [c.heldout_rms if c is not None else d.heldout_rms for c, d in zip(rws, diag.devices)]
            f = [d.noise_floor for d in diag.devices]
            verdicts = ["adequate" if (hh**2 - ff**2) / max(ff**2, 1e-300) < th.excess_min
                        else "missing_effect" for hh, ff in zip(h, f)]
            steps.append(LadderStep(spec=(diag.model + "random_walk").spec, added="random_walk",
                                    heldout_rms=h, noise_floor=f,
                                    rms=[c.rms if c is not None else d.rms for c, d in zip(rws, diag.devices)],
                                    verdicts=verdicts))
            break
        added = _added_term(diag.spec, spec)
        say(f"adding {added}: diagnosing {spec}")
        diag = diagnose(spec, batch, candidates, thresholds=th, **fit_options)
        steps.append(_step(diag, added))
    return Ladder(devices=[d.device for d in first.devices], steps=steps, first=first, final=diag)


__all__ = ["FAMILIES", "Candidate", "CandidateSpec", "Diagnosis", "DeviceDiagnosis", "Ladder",
           "LadderStep", "Thresholds", "candidate_specs", "choose_effect", "diagnose",
           "diagnose_auto", "evidence", "explain", "family_of", "noise_floor", "redecide",
           "suggest_dtemp_window", "temperature_quantum"]

# jaxtyping names used in annotations only
_ = (Array, Int)
