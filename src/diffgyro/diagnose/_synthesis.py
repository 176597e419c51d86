"""Term synthesis: when no built-in term closes the gap, a term built from the signals.

For a device whose verdict is ``missing_effect`` and whose best built-in term (or pair)
leaves the gap open, a candidate library is built from the term grammar
(:mod:`diffgyro.effects._grammar`) on the signals the recording holds:

- every pairwise product and square of the signals that vary (temperature, external
  temperature, dT/dt, heating state, specific force, reference rates, the axis' own
  rate, extra columns), less those a built-in term already is (T², Ω·T);
- lags of the extra columns and of the external temperature, on a grid of time
  constants (the fit then learns τ), and each of them, and the temperature, times its own
  lag (a signal × its lag);
- "the thermal version" of every grammar term already in the model (its product
  times temperature);
- the linear built-in candidates the diagnosis found significant, so that a synthesised
  term is proposed only where it does better than the vocabulary.

Selection is forward and greedy on per-block sums (``ZᵀZ``, ``Zᵀy``, ``yᵀy`` of each
contiguous time block, the base design included, per axis): a set's held-out error on
a block comes from the other blocks' sums alone, so each step is a few small solves per
candidate, never a pass over the samples. A term is added when it improves the held-out
error consistently over the blocks (paired t over blocks) and materially (against the
noise floor); selection stops when the held-out error reaches the floor. Only a set that
reaches the floor (or closes ``rw_prefer`` of the gap to it, as a built-in term must to be
preferred to the random walk) is proposed, the smallest found: a residual of correlated noise (a
random walk, flicker) is not closed by any product of the logged signals, so it gets no
invented term.

Where the residual holds a Gauss–Markov process (:mod:`.noise_model`), the white floor
cannot be reached by any set: the steps are taken as above, then the noise of the
residual the set leaves is identified and the set judged against that floor (white +
the process' σ², :func:`apply_one`), so that a product the identification alone would
read as noise is proposed as a term.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _aux as aux_cols
from .._signal_builder import batch_inputs, input_signals
from .._signal_catalogue import CATALOGUE, present
from ..effects import RATES, STANDARD, Term, parse_factors, signal_value
from ..fit import fit as fit_fn
from ..model import ErrorModel
from ..signals import TempNorm
from ._floor import white_noise_rms
from ._results import Candidate
from ._thresholds import Thresholds

#: Contiguous time blocks of the selection (each held out in turn).
N_BLOCKS = 10
#: Most synthesised terms proposed together.
MAX_TERMS = 3
#: Time constants tried for a lag candidate, as fractions of the record.
LAG_FRACTIONS = (0.005, 0.01, 0.02, 0.04, 0.08)
#: Paired t over the blocks a step must reach (or no block worse by more than the
#: thresholds' ``consistency`` times the mean gain, as for a built-in candidate).
T_MIN = 3.0
#: Held-out MSE gain (fraction of the floor's MSE) a synthesised term must bring: many
#: candidates are tried, so a term must matter, not merely be significant.
GAIN_MIN = 0.25
#: Built-in products: the term grammar does not offer these again.
BUILT_IN = frozenset({"temp^2", "temp*w"})
NOTE = "synthesised from the recording's signals (term grammar); fit it to learn any time constant"


@dataclass
class Proposal:
    """A synthesised set: the terms added (spec text), their held-out numbers."""

    terms: list[str]
    spec: str
    heldout_rms: float
    rms: float
    t: float
    folds_improved: int
    #: The floor (rad/s) the set reached when judged against the identified noise of the
    #: residual it leaves (white + Gauss–Markov, :func:`_against_noise`); None: the white one.
    noise_floor: float | None = None


def qualifies(d, th: Thresholds) -> bool:
    """A device the vocabulary leaves open: ``missing_effect`` and no built-in term, nor
    the greedy pair, closes ``rw_prefer`` of the gap; or ``adequate`` only because no
    candidate is significant while the held-out error is :data:`GAIN_MIN` or more above
    the floor (a gap no built-in term can close)."""
    if not math.isfinite(d.heldout_rms):
        return False
    if d.verdict == "adequate":
        return d.excess >= GAIN_MIN and not any(c.significant for c in d.candidates)
    if d.verdict != "missing_effect":
        return False
    b = d.best
    if b is not None and not b.stochastic and b.closure >= th.rw_prefer:
        return False
    return not (d.next is not None and d.next.closure >= th.rw_prefer)


def _varies(x: np.ndarray) -> bool:
    x = np.asarray(x, float)
    if x.size == 0 or not np.all(np.isfinite(x)):
        return False
    lo, hi = float(x.min()), float(x.max())
    return hi - lo > 1e-9 * max(abs(lo), abs(hi), 1e-300)


def signal_names(rec, aux_names) -> list[str]:
    """The grammar's signals this recording holds and that vary on it."""
    out = []
    if rec.temp is not None and float(np.ptp(rec.temp)) >= 1.0:
        out += [k for k, s in CATALOGUE.items() if s.reads == {"temp"}]
    if rec.temp_ext is not None and rec.temp is not None and _varies(rec.temp_ext):
        out.append("temp_ext")
    if rec.accel is not None:
        out += [f"a{c}" for k, c in enumerate("xyz") if _varies(rec.accel[:, k])]
    if rec.rate is not None:
        live = [f"r{c}" for k, c in enumerate("xyz") if _varies(rec.rate[:, k])]
        out += live + (["w"] if live else [])
    out += [k for k in aux_names if k in rec.aux and _varies(rec.aux[k])]
    order = list(STANDARD)
    return sorted(set(out), key=lambda n: (order.index(n) if n in order else len(order), n))


def library(model: ErrorModel, names: list[str]) -> list[str]:
    """Grammar expressions to try (canonical text), without duplicates."""
    exprs: list[str] = []
    for i, a in enumerate(names):
        for b in names[i:]:
            if a == b and a == "heating":
                continue
            if a in RATES and b in RATES and "w" in (a, b) and a != b:
                continue  # w·r_x mixes the axis' own rate with a named one: skipped
            exprs.append(f"{a}*{b}")
    for a in names:
        if a not in STANDARD or a == "temp_ext":
            exprs += [f"lag({a})", f"{a}*lag({a})"]
        elif a == "temp":
            exprs.append("temp*lag(temp)")  # lag(temp) alone is thermal_lag's
    for t in model.terms:
        if isinstance(t, Term) and "temp" in names:
            exprs.append(f"temp*{t.expr}")
    out, seen = [], {t.expr for t in model.terms if isinstance(t, Term)}
    for e in exprs:
        try:
            canon = Term.parse_argument(e)
        except Exception:  # e.g. a power above the maximum
            continue
        if canon in seen or canon in BUILT_IN or canon in names:
            continue
        seen.add(canon)
        out.append(canon)
    return out


@eqx.filter_jit
def _columns(model, rivals, inp, theta_b):
    """Per device of a chunk: base design (L, 3, p), the rival built-in terms' columns
    (L, 3, r), ``gyro − rate`` (L, 3) and the grammar's signals by name (compiled once per
    model and rivals: the library's products are formed on the host, :func:`_products`)."""
    def one(inp, theta_b):
        sig = input_signals(inp, inp["window"])
        dtype = sig.gyro.dtype
        n = sig.t.shape[0]
        x = model.design(sig, theta_b) if model.n_params else jnp.zeros((n, 3, 0), dtype)
        cols = [t.columns(sig, jnp.zeros((0,), dtype)) for t in rivals]
        r = jnp.concatenate(cols, axis=-1) if cols else jnp.zeros((n, 3, 0), dtype)
        std = [k for k, s in CATALOGUE.items() if not s.per_axis and present(sig, k)]
        have = {k: signal_value(sig, k) for k in std + list(sig.aux)}
        return x, r, sig.gyro - sig.rate, have

    return jax.vmap(one)(inp, theta_b)


def _lagged(x: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``x`` through a first-order lag τ at a uniform step ``dt``, starting settled (the
    recursion of :func:`diffgyro.effects.first_order_lag`, for selection; the
    fit then uses the exact one on the recording's own times)."""

    from scipy.signal import lfilter  # 0.45 s of import, for a lagged term only

    a = -np.expm1(-dt / tau)
    return lfilter([a], [1.0, a - 1.0], x, zi=[(1.0 - a) * x[0]])[0]


def _products(terms, taus, sig: dict, rate: np.ndarray, n: int, dt: float) -> np.ndarray:
    """The grammar terms' columns (n, 3, m) from the signals on the host; ``taus[j]`` the
    time constant of term j's lagged factor (None: none)."""
    cols = np.empty((n, 3, len(terms)))
    for j, (term, tau) in enumerate(zip(terms, taus)):
        out = np.ones((n, 3))
        for name, lagged, p in term.factors:
            x = rate[:n] if name == "w" else sig[name][:n]
            if lagged:
                x = _lagged(x, tau, dt)
            x = x**p
            out *= x if x.ndim == 2 else x[:, None]
        cols[:, :, j] = out
    return cols


def _block_sums(z: np.ndarray, y: np.ndarray, n_blocks: int):
    """Per contiguous block: ZᵀZ (B, 3, q, q), Zᵀy (B, 3, q), yᵀy (B, 3), counts (B,)."""
    n = z.shape[0]
    edges = np.linspace(0, n, n_blocks + 1).astype(int)
    zz, zy, yy, cnt = [], [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        zb, yb = z[lo:hi], y[lo:hi]
        za = np.ascontiguousarray(zb.transpose(1, 0, 2))  # (3, n, q): one matrix product per axis
        zz.append(za.transpose(0, 2, 1) @ za)              # BLAS, not einsum's loops
        zy.append(np.einsum("nip,ni->ip", zb, yb))
        yy.append(np.einsum("ni,ni->i", yb, yb))
        cnt.append(hi - lo)
    return np.stack(zz), np.stack(zy), np.stack(yy), np.asarray(cnt, float)


def _heldout(zz, zy, yy, cols: list[int]) -> np.ndarray:
    """Held-out SSE (B,) of the columns ``cols``, each block fitted on the others."""
    ix = np.asarray(cols)
    g = zz[:, :, ix[:, None], ix[None, :]]             # (B, 3, k, k)
    r = zy[:, :, ix]                                   # (B, 3, k)
    gt, rt = g.sum(0) - g, r.sum(0) - r                # training sums
    d = np.sqrt(np.maximum(np.einsum("...kk->...k", gt), 1e-300))
    gs = gt / (d[..., :, None] * d[..., None, :]) + 1e-10 * np.eye(len(ix))
    try:
        beta = np.linalg.solve(gs, (rt / d)[..., None])[..., 0] / d
    except np.linalg.LinAlgError:
        return np.full(zz.shape[0], np.inf)
    sse = yy - 2.0 * np.einsum("bik,bik->bi", beta, r) + np.einsum("bik,bikl,bil->bi", beta, g, beta)
    return sse.sum(-1)


def _full_sse(zz, zy, yy, cols: list[int]) -> float:
    ix = np.asarray(cols)
    g, r = zz.sum(0)[:, ix[:, None], ix[None, :]], zy.sum(0)[:, ix]
    beta = _full_beta(zz, zy, cols)
    return float(yy.sum() - 2.0 * np.sum(beta * r) + np.einsum("ik,ikl,il->", beta, g, beta))


def select(zz, zy, yy, cnt, base: list[int], groups: list[list[int]], floor2: float,
           th: Thresholds, max_terms: int = MAX_TERMS,
           vocabulary: frozenset = frozenset(), keys: list | None = None) -> tuple[list[int], np.ndarray]:
    """Forward selection of candidate groups (column indices) on top of ``base``; returns
    the chosen groups' indices (empty when no set reaches the floor or closes the thresholds'
    ``rw_prefer`` of the gap to it) and the held-out SSE per block of the final set. Groups
    in ``vocabulary`` (built-in terms) need the thresholds' ``gain_min``, synthesised ones
    :data:`GAIN_MIN`. ``keys``: per group, what it claims (:func:`claims`): the term it is
    (one lag term on a grid of time constants is several groups) and the column it lags; a
    claim is taken once."""
    chosen, sses = forward(zz, zy, yy, cnt, base, groups, floor2, th, max_terms, vocabulary, keys)
    # the floor reached, or the gap closed as a built-in term must close it to be preferred
    # to the random walk (flicker and read-out quantisation stay above the white floor)
    return (chosen if reached(sses[0], sses[-1], cnt, floor2, th) else []), sses[-1]


def reached(sse_base: np.ndarray, sse: np.ndarray, cnt: np.ndarray, floor2: float,
            th: Thresholds) -> bool:
    """A set whose held-out MSE is within the thresholds' ``excess_min`` of ``floor2`` or
    that closes their ``rw_prefer`` of the base's gap to it."""
    mse = sse.sum() / (3.0 * cnt.sum())
    return bool(mse <= floor2 * (1.0 + th.excess_min)
                or _closure(sse_base, sse, cnt, floor2) >= th.rw_prefer)


def _closure(sse_base: np.ndarray, sse: np.ndarray, cnt: np.ndarray, floor2: float) -> float:
    """The share of the base's held-out gap to ``floor2`` that a set closes."""
    denom = 3.0 * cnt.sum()
    mse, mse_base = sse.sum() / denom, sse_base.sum() / denom
    return (mse_base - mse) / (mse_base - floor2) if mse_base > floor2 else 0.0


def forward(zz, zy, yy, cnt, base: list[int], groups: list[list[int]], floor2: float,
            th: Thresholds, max_terms: int = MAX_TERMS,
            vocabulary: frozenset = frozenset(), keys: list | None = None,
            ) -> tuple[list[int], list[np.ndarray]]:
    """The forward path of :func:`select`: the groups added in order, each improving the
    held-out error consistently and materially against ``floor2``, until it reaches the
    floor; and the held-out SSE per block before the first and after each step."""
    keys = [(j,) for j in range(len(groups))] if keys is None else keys
    cur = list(base)
    sse_cur = _heldout(zz, zy, yy, cur)
    sses = [sse_cur]
    chosen: list[int] = []
    denom = 3.0 * cnt
    for _ in range(max_terms):
        if sse_cur.sum() / denom.sum() <= floor2 * (1.0 + th.excess_min):
            break
        best, best_sse = None, None
        taken = {k for c in chosen for k in keys[c]}
        for j, g in enumerate(groups):
            if taken.intersection(keys[j]):
                continue
            s = _heldout(zz, zy, yy, cur + g)
            if np.all(np.isfinite(s)) and (best_sse is None or s.sum() < best_sse.sum()):
                best, best_sse = j, s
        if best is None:
            break
        diff = (sse_cur - best_sse) / denom
        sd = float(np.std(diff, ddof=1))
        t = float(np.mean(diff)) / (sd / math.sqrt(diff.size)) if sd > 0 else 0.0
        gain = float((sse_cur.sum() - best_sse.sum()) / denom.sum()) / floor2
        mean = float(np.mean(diff))
        steady = mean > 0 and (t >= T_MIN or float(np.min(diff)) >= -th.consistency * mean)
        if not (steady and gain >= (th.gain_min if best in vocabulary else GAIN_MIN)):
            break
        chosen.append(best)
        cur = cur + groups[best]
        sse_cur = best_sse
        sses.append(sse_cur)
    return chosen, sses


def _inputs(batch, res, idx: np.ndarray, aux: dict) -> dict:
    """The devices ``idx`` as the compiled columns take them (padded rows, masked)."""
    norm = res.norm if batch.temp is not None else None
    return dict(batch_inputs(batch, idx, norm, aux),
                window=jnp.full(len(idx), float(res.options.dtemp_window)))


#: Devices per compiled call of the library's columns.
CHUNK = 8


def propose(i: int, floor: float, batch, res, model: ErrorModel, aux: dict, builtins: list,
            th: Thresholds) -> Proposal | None:
    """The smallest synthesised set that reaches device ``i``'s white-noise ``floor``
    (rad/s), or None. ``res``: the fit of ``model`` on ``batch``; ``aux``: the extra
    columns, centred and scaled ((devices, n) each); ``builtins``: linear built-in
    candidates (CandidateSpec) that compete with the synthesised terms."""
    return propose_many([i], [floor], batch, res, model, aux, [builtins], th).get(i)


def propose_many(idx: list[int], floors: list[float], batch, res, model: ErrorModel, aux: dict,
                 builtins: list[list], th: Thresholds,
                 residual_floor=None) -> dict[int, Proposal]:
    """:func:`propose` for the devices ``idx`` (their floors and built-in rivals), their
    library columns computed :data:`CHUNK` devices at a time. ``residual_floor(i, e)``: the
    floor² per axis (3,) of device i's residual ``e`` (n, 3) after a synthesised set, from
    its identified noise (white + Gauss–Markov); given, a set is proposed when it reaches
    that floor (:func:`_against_noise`), not the white one."""
    if not idx:
        return {}
    recs = {i: batch.recording(i) for i in idx}
    names = {i: signal_names(recs[i], [k for k in aux if k in recs[i].aux]) for i in idx}
    union = sorted({n for i in idx for n in names[i]},
                   key=lambda n: (list(STANDARD).index(n) if n in STANDARD else len(STANDARD), n))
    exprs = library(model, union)
    rivals, seen = [], set()
    for bl in builtins:
        for c in bl:
            if c.spec not in seen:
                seen.add(c.spec)
                rivals.append(c)
    terms, fracs, labels = [], [], []
    for e in exprs:
        term = Term(expr=e)
        for f in (LAG_FRACTIONS if term.n_nonlinear else (None,)):
            terms.append(term)
            fracs.append(f)
            labels.append(term.spec)
    terms += [c.term for c in rivals]
    fracs += [None] * len(rivals)
    labels += [c.spec for c in rivals]
    if not exprs:
        return {}
    p = model.n_params
    n_grammar = len(terms) - len(rivals)
    groups, k = [], p
    for j, term in enumerate(terms):
        old = None if j < n_grammar else rivals[j - n_grammar].old
        groups.append(list(range(k + (old.n_params if old is not None else 0), k + term.n_params)))
        k += term.n_params
    out = {}
    order = list(idx)
    grammar = [t for t in terms if isinstance(t, Term)]
    # a column the model already lags is not lagged again (:func:`claims`)
    base_lags = {k for t in model.terms for k in claims(t, "")[1:]}
    for start in range(0, len(order), CHUNK):
        part = order[start:start + CHUNK]
        pad = np.asarray(part + [part[-1]] * (CHUNK - len(part)) if len(order) > CHUNK else part)
        theta_b = jnp.asarray(np.asarray(res.params.theta)[pad])
        xs, rs, ys, sigs = jax.device_get(_columns(model, tuple(c.term for c in rivals),
                                                    _inputs(batch, res, pad, aux), theta_b))
        for r, i in enumerate(part):
            n = int(batch.n_valid[i])
            t = np.asarray(batch.t[i, :n], np.float64)
            dt = float(np.median(np.diff(t))) if n > 1 else 1.0
            taus = [None if f is None else max(f * float(t[-1] - t[0]), 1.0)
                    for f in fracs[:n_grammar]]
            rate = np.zeros((n, 3)) if batch.rate is None else np.asarray(batch.rate[i, :n], float)
            cols = np.concatenate([_products(grammar, taus, {k: np.asarray(v[r]) for k, v in
                                                              sigs.items()}, rate, n, dt),
                                   np.asarray(rs[r])[:n]], axis=-1)
            fl = floors[idx.index(i)]
            allowed = set(names[i])
            mine = {c.spec for c in builtins[idx.index(i)]}
            usable = [j for j, t in enumerate(terms)
                      if ((isinstance(t, Term) and {n for n, _, _ in t.factors} <= allowed)
                          or (not isinstance(t, Term) and labels[j] in mine))
                      and not base_lags.intersection(claims(t, labels[j]))]
            check = None if residual_floor is None else (lambda e, i=i: residual_floor(i, e))
            prop = _select_device(np.asarray(xs[r])[:n], cols, np.asarray(ys[r])[:n], n, fl, p,
                                  terms, labels, groups, usable, rivals, model, th, check)
            if prop is not None:
                out[i] = prop
    return out


def _select_device(x, c, y, n, floor, p, terms, labels, groups, usable, rivals, model,
                   th, residual_floor=None) -> Proposal | None:
    z = np.concatenate([x, c], axis=-1)[:n]
    y = y[:n]
    ok = np.all(np.isfinite(z), axis=(1, 2)) & np.all(np.isfinite(y), axis=1)
    z, y = np.where(ok[:, None, None], z, 0.0), np.where(ok[:, None], y, 0.0)
    zz, zy, yy, cnt = _block_sums(z, y, N_BLOCKS)
    floor2 = max(floor ** 2, 1e-300)
    vocab = frozenset(k for k, j in enumerate(usable) if not isinstance(terms[j], Term))
    grouped = [groups[j] for j in usable]
    keys = [claims(terms[j], labels[j]) for j in usable]
    noise2 = None
    if residual_floor is None:
        chosen, sse = select(zz, zy, yy, cnt, list(range(p)), grouped, floor2, th, vocabulary=vocab,
                             keys=keys)
    else:
        chosen, sse, noise2 = _against_noise(z, y, zz, zy, yy, cnt, p, grouped, floor2, th, vocab,
                                             residual_floor, keys)
    chosen = [usable[k] for k in chosen]
    new = [labels[j] for j in chosen if isinstance(terms[j], Term)]
    if not new:
        return None  # nothing reaches the floor, or the vocabulary alone does
    kept = [next(r for r in rivals if r.spec == labels[j]) for j in chosen
            if not isinstance(terms[j], Term)]
    base_sse = _heldout(zz, zy, yy, list(range(p)))
    diff = (base_sse - sse) / (3.0 * cnt)
    sd = float(np.std(diff, ddof=1))
    t = float(np.mean(diff)) / (sd / math.sqrt(diff.size)) if sd > 0 else math.inf
    cols = list(range(p)) + [q for j in chosen for q in groups[j]]
    return Proposal(terms=new, spec=_canonical(model, kept, new),
                    heldout_rms=math.sqrt(float(sse.sum()) / (3.0 * cnt.sum())),
                    rms=math.sqrt(max(_full_sse(zz, zy, yy, cols), 0.0) / (3.0 * cnt.sum())),
                    t=t, folds_improved=int(np.sum(diff > 0)),
                    noise_floor=None if noise2 is None else math.sqrt(noise2))


def claims(term, label: str) -> tuple[str, ...]:
    """What a candidate takes from the selection once chosen: its term (one lag term on the
    grid of time constants is several groups) and the column it lags. A proposal lags a
    column once: ``lag(x)`` beside ``x*lag(x)`` would be fitted with two time constants of
    one thermal path, which the data do not tell apart (the fit came back rank-deficient,
    its coefficients cancelling in the millions)."""
    lagged = getattr(term, "lagged", None) if isinstance(term, Term) else None
    return (label,) + ((f"lag:{lagged}",) if lagged else ())


def _against_noise(z, y, zz, zy, yy, cnt, p: int, groups: list[list[int]], floor2: float,
                   th: Thresholds, vocab: frozenset, residual_floor, keys: list):
    """:func:`select` where the residual holds a Gauss–Markov process that no term predicts:
    the forward path is taken as against the white floor ``floor2`` (each step consistent
    and material against it), then the noise of the residual the whole path leaves is
    identified (``residual_floor``) and the shortest prefix that reaches that floor (white
    + Gauss–Markov, or closes ``rw_prefer`` of the gap to it) and closes the thresholds'
    ``closure_min`` of the gap to the white floor (as a built-in term must) is chosen.
    Identified after the terms, the process' power is not inflated by the effect they take
    out; the closure keeps a term that takes a sliver off an effect whose rest reads as a
    process of seconds out."""
    path, sses = forward(zz, zy, yy, cnt, list(range(p)), groups, floor2, th, vocabulary=vocab,
                         keys=keys)
    if not path:
        return [], sses[0], None
    cols = list(range(p)) + [q for k in path for q in groups[k]]
    beta = _full_beta(zz, zy, cols)                       # (3, k)
    e = y - np.einsum("nik,ik->ni", z[:, :, cols], beta)
    noise2 = max(float(np.mean(residual_floor(e))), floor2)
    for k in range(1, len(path) + 1):
        if reached(sses[0], sses[k], cnt, noise2, th) and \
                _closure(sses[0], sses[k], cnt, floor2) >= th.closure_min:
            return path[:k], sses[k], noise2
    return [], sses[-1], None


def _full_beta(zz, zy, cols: list[int]) -> np.ndarray:
    """Per axis, the coefficients (3, k) of the columns ``cols`` fitted on every block."""
    ix = np.asarray(cols)
    g, r = zz.sum(0)[:, ix[:, None], ix[None, :]], zy.sum(0)[:, ix]
    d = np.sqrt(np.maximum(np.einsum("ikk->ik", g), 1e-300))
    return np.linalg.solve(g / (d[..., :, None] * d[..., None, :]) + 1e-10 * np.eye(len(ix)),
                           (r / d)[..., None])[..., 0] / d


def _canonical(model: ErrorModel, kept: list, new: list[str]) -> str:
    """The proposed model's spec: the base with the built-in candidates kept (an order
    raised replaces its term), then the synthesised terms."""
    terms = list(model.terms)
    for c in kept:
        terms = [c.term if t == c.old else t for t in terms] if c.old is not None else terms + [c.term]
    return ErrorModel.from_spec("+".join([*(t.spec for t in terms), *new])).spec


def describe(expr: str) -> str:
    """A grammar term in words, with a physical reading where one is known."""
    words = Term(expr=expr).describe()
    fs = parse_factors(expr)
    names = {n for n, _, _ in fs}
    lagged = any(lg for _, lg, _ in fs)
    reading = ""
    if "temp" in names and names & {"ax", "ay", "az"} and len(fs) == 2:
        reading = ": a g-sensitivity that changes with temperature"
    elif names <= {"ax", "ay", "az"} and sum(p for *_, p in fs) == 2:
        reading = ": a g²-sensitivity (anisoelastic error)"
    elif names <= {"rx", "ry", "rz", "w"} and sum(p for *_, p in fs) == 2:
        reading = ": a rate-squared (cross-coupling) error"
    elif lagged and len(fs) == 1:
        reading = ": a signal reaching the gyro through its own thermal path (first-order lag)"
    elif lagged and len(fs) == 2 and len(names) == 1:
        reading = ": a signal times its own lagged value (its present and its thermal history)"
    elif lagged and len(fs) == 2 and len(names) == 1:
        reading = ": a signal times its own lagged value (its present and its thermal history)"
    elif "temp" in names and len(fs) == 2:
        reading = ": a sensitivity that changes with temperature"
    return f"the bias follows {words}{reading}"


def extra_columns(batch, model: ErrorModel, res) -> dict[str, np.ndarray]:
    """Every extra column of ``batch``, centred and scaled ((devices, n), zero where not
    finite): those the model reads as the fit did, the others over each device's range."""

    used = aux_cols.aux_names(model.requires())
    fresh = [k for k in batch.aux if k not in used]
    with np.errstate(all="ignore"):
        norms = {**{k: TempNorm(centre=np.asarray(v.centre), scale=np.asarray(v.scale))
                    for k, v in res.aux_norm.items()}, **aux_cols.norms(batch, fresh)}
        scaled = aux_cols.scaled(batch, norms)
    return {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in scaled.items()}


def apply(devices: list, batch, res, model: ErrorModel, cands: list, ok: np.ndarray,
          th: Thresholds) -> dict[int, Proposal]:
    """Propose a synthesised term for every device the vocabulary leaves open (in place:
    its best candidate, verdict and explanation); returns the proposals by device index.
    ``cands``: diagnose's scored candidates, ``ok`` (devices, candidates) where supported."""
    idx = [i for i, d in enumerate(devices) if qualifies(d, th)]
    rivals = [_rivals(devices[i], i, cands, ok) for i in idx]
    if not idx:
        return {}
    out = propose_many(idx, [devices[i].white_noise_rms for i in idx], batch, res, model,
                       extra_columns(batch, model, res), rivals, th)
    for i, prop in out.items():
        _record(devices[i], prop)
    return out


def apply_one(i: int, d, batch, res, model: ErrorModel, cands: list, ok: np.ndarray,
              th: Thresholds, floor: float, residual_floor) -> Proposal | None:
    """:func:`apply` for device ``i`` alone, its diagnosis ``d`` (decided against the
    residual's identified noise) qualifying: the steps taken against the white ``floor``
    (rad/s), the set judged against the noise the residual holds once the terms are taken
    out (``residual_floor(i, e)``: floor² per axis, :func:`propose_many`). Any verdict
    qualifies but a built-in term that closes ``rw_prefer`` of the gap: against a floor
    raised by a process that absorbed the effect, the gap may look closed already."""
    b = d.best
    if b is not None and not b.stochastic and b.closure >= th.rw_prefer:
        return None
    prop = propose_many([i], [floor], batch, res, model, extra_columns(batch, model, res),
                        [_rivals(d, i, cands, ok)], th, residual_floor).get(i)
    if prop is not None:
        _record(d, prop, floor)
    return prop


def _rivals(d, i: int, cands: list, ok: np.ndarray) -> list:
    """The linear built-in candidates significant on device ``i`` (``d``) that compete with
    the synthesised terms."""
    sig_names = {c.spec for c in d.candidates if c.significant and not c.stochastic}
    return [c for j, c in enumerate(cands) if c.term.n_nonlinear == 0
            and c.spec in sig_names and (ok.size == 0 or ok[i, j])]


def _record(d, prop: Proposal, floor: float | None = None) -> None:
    floor = d.white_noise_rms if floor is None else floor
    f2 = max((prop.noise_floor or floor) ** 2, 1e-300)
    hb2, hc2 = d.heldout_rms ** 2, prop.heldout_rms ** 2
    gap = hb2 - f2
    cand = Candidate(effect="term", spec=prop.spec, heldout_rms=prop.heldout_rms, significant=True,
                     gain=(hb2 - hc2) / f2, closure=(hb2 - hc2) / gap if gap > 0 else 0.0,
                     t=prop.t, folds_improved=prop.folds_improved, rms=prop.rms, note=NOTE,
                     term="+".join(prop.terms))
    d.candidates = sorted([cand, *d.candidates],
                          key=lambda c: c.heldout_rms if math.isfinite(c.heldout_rms) else math.inf)
    d.best, d.alternatives, d.next = cand, [], None
    if d.random_walk is not None:
        d.random_walk.significant = False
    d.verdict = "missing_effect"
    words = "; ".join(describe(t[len("term("):-1]) for t in prop.terms)
    against = (f"a white-noise floor of {floor:.3g}" if prop.noise_floor is None else
               f"the noise the residual holds without it, {prop.noise_floor:.3g} (white "
               f"{floor:.3g} + Gauss–Markov, identified after the term: a product of logged "
               f"signals, not a noise process)")
    d.explanation = (
        f"{d.device}: no built-in term closes the gap; a term built from the recording's signals "
        f"does: {words} ({', '.join(prop.terms)}). Held-out RMS {d.heldout_rms:.3g} → "
        f"{prop.heldout_rms:.3g} rad/s against {against} (selected on held-out time blocks). "
        f"Fit it: diffgyro fit --model '{prop.spec}', then "
        f"carry the calibration to a second recording (diffgyro compensate --json).")


def propose_all(model: ErrorModel | str, batch, res=None, th: Thresholds | None = None,
                residual_floor=None, **fit_options) -> dict[int, Proposal]:
    """The synthesis on every device of ``batch``, as if no built-in term closed its gap:
    fits ``model`` (unless ``res`` is its fit), scales the extra columns as diagnose does
    and returns the proposals by device index (a device without one is left out).
    ``residual_floor(e, t, white_axes)`` (:func:`.noise_model.residual_floor`): every device
    as if its residual held a Gauss–Markov process, each set judged against the noise of
    the residual it leaves (:func:`_against_noise`)."""

    model = ErrorModel.from_spec(model) if isinstance(model, str) else model
    res = res if res is not None else fit_fn(model, batch, **fit_options)
    th = th or Thresholds()
    aux = extra_columns(batch, model, res)
    floors, white = [], []
    for i in range(batch.n_devices):
        n = int(batch.n_valid[i])
        rate = None if batch.rate is None else np.asarray(batch.rate[i, :n], np.float64)
        gyro = np.asarray(batch.gyro[i, :n], np.float64)
        axes = white_noise_rms(gyro if rate is None else gyro - rate, np.ones(n, bool), rate)
        white.append(np.asarray(axes, np.float64))
        floors.append(float(np.sqrt(np.mean(np.asarray(axes) ** 2))))
    idx = list(range(batch.n_devices))
    check = None if residual_floor is None else (
        lambda k, e: residual_floor(e, batch.t[k], white[k]))
    return propose_many(idx, floors, batch, res, model, aux, [[] for _ in idx], th, check)
