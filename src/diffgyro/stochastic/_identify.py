"""Identify the stochastic model of every series: fit the catalogue, choose, give intervals.

Per series (vmapped over devices × axes; steps 2 and 3 one compiled program, the choice and
step 4 another, :data:`_fits_batch`):

1. the empirical Haar wavelet variance ν̂ on dyadic scales (:mod:`.wavelet_variance`);
2. every candidate of the catalogue fitted with first-stage (diagonal) weights
   (:mod:`.estimator`);
3. Ω_ref: the inverse covariance of ν̂ (:mod:`.covariance`) under the
   candidate that step 2 scores best; every candidate refitted with it and
   scored by the criterion (:mod:`.selection`);
4. the chosen structure's intervals from the sandwich (:mod:`.intervals`) with
   Ω_ref as the weight and Σ at the chosen estimate;
5. where asked (``slow_penalty``), outside the compiled program, per series: the slow
   part chosen again by the exact likelihood of the record's block means
   (:mod:`.block_likelihood`; its close calls by a parametric bootstrap,
   :mod:`.slow_bootstrap`), the intervals recomputed (step 4) where the choice moved.

The functions the program calls at several places (:func:`.components.avar_gauss_markov`,
:func:`.covariance.wv_covariance`, :func:`.estimator.log_moments`,
:func:`.estimator.scaled_chol`) are ``jax.jit`` functions: in the trace each is a call,
traced once per shape and batched once per pattern of batched arguments, instead of again
at every place and in every pass of a ``scan``'s batching. XLA inlines the calls and
compiles the same program, which traces in less time. (As a call,
:func:`.components.model_wv_jac` moved the program's last bits: it is not one.)
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from .._jit import by_work, filter_jit
from .._xla_options import LIGHT_COMPILE, ONE_PART
from ._block_likelihood import BLOCKS, CLOSE, choose_slow_many
from ._components import component_avar, model_wv, row_mask
from ._covariance import wv_covariance
from ._estimator import (
    diag_rel_cov,
    jacobian_log,
    levenberg_marquardt,
    log_moments,
    scaled_chol,
    start_pairs,
    starting_values,
    tau_grid,
    whitener,
)
from ._intervals import Z95, sandwich
from ._resolution import LONG_SHARE, judge, limit_param, long_limit, merge_short, notes, short_limit
from ._selection import PENALTY, catalogue, effective_rank, label, structure_mask
from ._wavelet_variance import dyadic_m, haar_wv, haar_wv_ahead

#: Series per call of the compiled program. Larger batches of this program hung XLA's CPU
#: runtime (every worker idle, the caller waiting: observed at 60 series, not at 8); a fixed
#: chunk also keeps to one compiled program whatever the batch.
CHUNK = 8
#: Series per call on a GPU or TPU, where one call must carry more work.
ACCEL_CHUNK = 128


def _scales(wv_hat, count, dt, m):
    """A series' valid scales, its wavelet variances there (1 elsewhere), τ, the cluster sizes
    and the counts as reals."""
    valid = jnp.isfinite(wv_hat) & (wv_hat > 0) & (count > 1)
    mf = m.astype(wv_hat.dtype)
    return valid, jnp.where(valid, wv_hat, 1.0), mf * dt, mf, count.astype(wv_hat.dtype)


def _fits_one(wv_hat, count, n, dt, m, masks, n_scales):
    """Steps 2 and 3 for one series: every candidate fitted twice (first-stage weights, then
    Ω_ref); returns (θ (candidates, 8), objective (candidates,), Ω_ref's Cholesky factor)."""
    valid, wv_hat, tau, mf, cnt = _scales(wv_hat, count, dt, m)
    log_wv = jnp.log(wv_hat)
    grid = tau_grid(n_scales, dt)
    pairs = start_pairs(n_scales)
    rel0 = diag_rel_cov(cnt, mf)
    weight1 = 1.0 / jnp.diag(rel0)
    th0 = jax.vmap(lambda mk: starting_values(mk, wv_hat, valid, tau, dt, weight1, grid, pairs))(masks)

    def rel_cov(th, mk):
        nu = model_wv(th, mk, tau, dt)
        return wv_covariance(th, mk, mf, cnt, n, dt) / (nu[:, None] * nu[None, :])

    def weights(rel):
        cov_log, bias = log_moments(rel)
        return scaled_chol(cov_log, valid), log_wv - bias

    k_nominal = jnp.sum(masks, axis=1)

    def stage(carry, k):
        # stage 0: diagonal first-stage weights; stage 1: Ω_ref, from the covariance of ν̂
        # under the candidate that stage 0 scored best (its own objective + 2 per parameter)
        th, obj = carry
        ref = jnp.argmin(jnp.where(jnp.isfinite(obj), obj + 2.0 * k_nominal, jnp.inf))
        chol, target = weights(jnp.where(k == 0, rel0, rel_cov(th[ref], masks[ref])))
        linv = whitener(chol)
        th, obj = jax.vmap(lambda t, mk: levenberg_marquardt(t, mk, target, valid, tau, dt, n, linv))(
            th, masks)
        return (th, obj), chol

    obj0 = jnp.zeros(masks.shape[0], wv_hat.dtype)
    (th2, obj), chols = jax.lax.scan(stage, (th0, obj0), jnp.arange(2))
    return th2, obj, chols[1]


def _choice_one(wv_hat, count, n, dt, m, masks, penalty, th2, obj, chol_ref):
    """Steps 3 and 4 for one series from its fits (:func:`_fits_one`): every candidate's
    criterion and rank, the choice, and the chosen model's intervals and detection limits."""
    valid, _, tau, mf, cnt = _scales(wv_hat, count, dt, m)
    k_nominal = jnp.sum(masks, axis=1)
    linv_ref = whitener(chol_ref)
    nus, ds = jax.vmap(lambda th, mask: jacobian_log(th, mask, valid, tau, dt))(th2, masks)
    rank = jax.vmap(lambda d: effective_rank(linv_ref @ d))(ds)
    crit = obj + penalty * k_nominal
    # a Gauss–Markov time beyond the record's share is a walk or ramp: not a candidate
    # (:mod:`.resolution`)
    long = LONG_SHARE * n * dt
    admissible = ~((masks[:, 2] & (th2[:, 3] > jnp.log(long)))
                   | (masks[:, 4] & (th2[:, 5] > jnp.log(long))))
    pick = jnp.argmin(jnp.where(jnp.isfinite(crit) & admissible, crit, jnp.inf))
    at = _at_pick(th2[pick], masks[pick], valid, tau, dt, mf, cnt, n, chol_ref, penalty,
                  (nus[pick], ds[pick]))
    return dict(valid=valid, theta_all=th2, objective=obj, rank=rank, criterion=crit, pick=pick,
                admissible=admissible, chol_ref=chol_ref, **at)


def _at_pick(th, mask, valid, tau, dt, mf, cnt, n, chol_ref, penalty, nu_d=None):
    """The chosen model's covariance (the sandwich with the weight ``chol_ref``), the wavelet
    variances' model standard deviation and the detection limits; ``nu_d``: its wavelet
    variances and log-Jacobian (:func:`.estimator.jacobian_log`) where already computed."""
    nu, d = jacobian_log(th, mask, valid, tau, dt) if nu_d is None else nu_d
    rel_at = wv_covariance(th, mask, mf, cnt, n, dt) / (nu[:, None] * nu[None, :])
    cov_log_at, _ = log_moments(rel_at)
    vv = valid[:, None] & valid[None, :]
    cov_theta = sandwich(d, chol_ref, jnp.where(vv, cov_log_at, 0.0), mask)
    wv_sd = jnp.sqrt(jnp.diag(rel_at)) * nu
    limits = detection_limits(d, mask, valid, tau, dt, nu, scaled_chol(cov_log_at, valid), penalty)
    return dict(theta=th, cov=cov_theta, wv_sd=wv_sd, limits=limits)


@filter_jit(persistent=True)
def _at_pick_batch(wv_hat, count, n, dt, m, theta, mask, chol_ref, penalty):
    """:func:`_at_pick` for a batch of series whose structure the likelihood of the slow part
    changed."""
    def one(w, c, nn, d, th, mk, ch):
        valid = jnp.isfinite(w) & (w > 0) & (c > 1)
        mf = m.astype(w.dtype)
        return _at_pick(th, mk, valid, mf * d, d, mf, c.astype(w.dtype), nn, ch, penalty)

    return jax.vmap(one)(wv_hat, count, n, dt, theta, mask, chol_ref)


def detection_limits(d, mask, valid, tau, dt, nu, chol, penalty):
    """(K, R): the smallest random walk (rad/s/√s) and ramp (rad/s²) the criterion would
    take, added to the chosen model: power = √penalty × its standard error at zero, the
    chosen model's other parameters free, under the efficient weight ``chol`` (the
    covariance of log ν̂ at the chosen estimate; :mod:`.resolution`)."""
    on = mask.astype(d.dtype)
    walk = jnp.where(valid, 0.5 * (tau / 3.0 + dt**2 / (6.0 * tau)) / nu, 0.0)
    ramp = jnp.where(valid, 0.25 * tau**2 / nu, 0.0)

    def power(col):
        dd = jnp.concatenate([d, col[:, None]], axis=1)
        w = jax.scipy.linalg.solve_triangular(chol, dd, lower=True)
        free = jnp.concatenate([on, jnp.ones((1,), d.dtype)])
        f = w.T @ w + jnp.diag(1.0 - free)
        ev, v = jnp.linalg.eigh(f)
        inv = jnp.where(ev > 1e-12 * jnp.max(ev), 1.0 / ev, 1e12 / jnp.max(ev))
        var = jnp.sum(v[-1] ** 2 * inv)
        return jnp.sqrt(jnp.sqrt(penalty) * jnp.sqrt(var))

    return jnp.stack([power(walk), power(ramp)])


def _fits_series(wv_hat, count, n, dt, m, masks, n_scales):
    f = lambda w, c, nn, d: _fits_one(w, c, nn, d, m, masks, n_scales)  # noqa: E731
    return jax.vmap(f)(wv_hat, count, n, dt)


def _choice_series(wv_hat, count, n, dt, m, masks, penalty, th2, obj, chol_ref):
    f = lambda w, c, nn, d, th, ob, ch: _choice_one(w, c, nn, d, m, masks, penalty,  # noqa: E731
                                                    th, ob, ch)
    return jax.vmap(f)(wv_hat, count, n, dt, th2, obj, chol_ref)


#: The identification as two programs, the fits (:func:`_fits_series`) and the choice with
#: its intervals (:func:`_choice_series`), each compiled for a batch's size
#: (:func:`~diffgyro._jit.by_work`) and kept on disk (a later process skips the traces and
#: the lowerings); a large batch's with XLA's loop emitters and LLVM's level-1 pipeline
#: (:data:`~diffgyro._xla_options.LIGHT_COMPILE`: a quarter less compile time, a tenth
#: more run time). Two programs, because a first call traces in Python (one core) and
#: compiles in XLA (without the GIL): the choice is traced while the fits compile, and the
#: two compile side by side; a small batch's each as one LLVM part
#: (:data:`~diffgyro._xla_options.ONE_PART`), since the two already keep both cores busy.
_fits_batch = by_work(_fits_series, compiler_options=LIGHT_COMPILE, persistent=True,
                      small_options=ONE_PART)
_choice_batch = by_work(_choice_series, compiler_options=LIGHT_COMPILE, persistent=True,
                        small_options=ONE_PART)


def _programs(samples: int) -> tuple:
    """The fits' and the choice's programs for a batch of ``samples`` (series × samples)."""
    return _fits_batch(samples), _choice_batch(samples)


@dataclass
class NoiseModels:
    """Identified models of a batch of series (leading shape ``lead``, e.g. devices × axes).

    ``theta``/``cov``: log-parameters of the chosen structure and their covariance;
    ``choice``: index into ``structures``; ``criterion``: every candidate's value (``objective`` + penalty × ``rank``);
    ``tau``/``wv``/``wv_sd``: the empirical Haar wavelet variance, its model-based
    standard deviation; ``dt``: sample interval per series."""

    structures: list[tuple[str, ...]]
    masks: np.ndarray
    tau: np.ndarray
    wv: np.ndarray
    wv_sd: np.ndarray
    valid: np.ndarray
    dt: np.ndarray
    choice: np.ndarray
    theta: np.ndarray
    cov: np.ndarray
    criterion: np.ndarray
    theta_all: np.ndarray
    objective: np.ndarray
    rank: np.ndarray
    admissible: np.ndarray | None = None
    limits: np.ndarray | None = None
    n_valid: np.ndarray | None = None
    slow_criterion: np.ndarray | None = None

    @property
    def lead(self) -> tuple[int, ...]:
        return self.choice.shape

    def structure(self, *idx) -> tuple[str, ...]:
        return self.structures[int(self.choice[idx])]

    def _resolved(self, idx):
        """(θ, cov, mask, merged) of the chosen model with the Gauss–Markov processes too
        short for the sampling merged into the white part (:func:`.resolution.merge_short`)."""
        return merge_short(self.theta[idx], self.cov[idx], self.masks[int(self.choice[idx])],
                           float(self.dt[idx]))

    def components(self, *idx) -> list[dict]:
        """The chosen model of one series as the JSON contract's components (SI units), what
        the record cannot resolve merged or judged (:mod:`.resolution`): each parameter with
        its ``status``, ``display`` units and, where ``not_identified``, ``why``."""
        theta, cov, mask, _ = self._resolved(idx)
        return [{**c, "params": {k: judge(k, p) for k, p in c["params"].items()}}
                for c in components_of(theta, cov, mask)]

    def reported_structure(self, *idx) -> tuple[str, ...]:
        """The structure as reported: the chosen one less the processes merged into white."""
        s = list(self.structure(*idx))
        for _ in self._resolved(idx)[3]:
            s.remove("gauss_markov")
        return tuple(s)

    def record_length(self, *idx) -> float:
        """Samples × interval of one series (s)."""
        if self.n_valid is None:  # built by hand: the longest scale is at most n/4 samples
            return 4.0 * float(self.tau[idx][-1])
        return float(self.n_valid[idx]) * float(self.dt[idx])

    def resolution(self, *idx) -> dict:
        """What the record of one series resolves (:mod:`.resolution`): the Gauss–Markov
        times it can tell from white noise and from a walk, the processes merged into the
        white part, the better-fitting candidates left out as unresolvable, and the smallest
        random walk and ramp the criterion would take; ``notes``: the same as sentences."""
        dt = float(self.dt[idx])
        record = self.record_length(*idx)
        _, _, _, merged = self._resolved(idx)
        crit = self.criterion[idx]
        excluded = []
        adm = self.admissible[idx] if self.admissible is not None else np.ones(len(crit), bool)
        floor = np.min(np.where(adm & np.isfinite(crit), crit, np.inf))
        for i in np.argsort(crit, kind="stable"):
            i = int(i)
            if adm[i] or not np.isfinite(crit[i]) or crit[i] >= floor:
                continue
            th, mk = self.theta_all[idx][i], self.masks[i]
            taus = [math.exp(th[t]) for v, t in ((2, 3), (4, 5)) if mk[v]]
            excluded.append({"structure": label(self.structures[i]), "better_by": float(floor - crit[i]),
                             "tau": max(taus)})
        lim = self.limits[idx] if self.limits is not None else (np.nan, np.nan)
        out = {"sample_interval": dt, "record_length": record,
               "gauss_markov_tau": {"min": short_limit(dt), "max": long_limit(record), "unit": "s"},
               "random_walk_limit": limit_param("rrw", float(lim[0])),
               "rate_ramp_limit": limit_param("r", float(lim[1])),
               "merged": [{"kind": "gauss_markov", "sigma": s, "tau": t, "into": "white"}
                          for s, t in merged],
               "excluded": excluded}
        out["close"] = self._close(idx)
        out["notes"] = notes(out, list(self.reported_structure(*idx)))
        return out

    def _close(self, idx) -> list[dict]:
        """The slow part's alternatives within :data:`.block_likelihood.CLOSE` of the chosen
        one on the block-mean likelihood's criterion: structures this record hardly tells
        from the chosen one."""
        if self.slow_criterion is None:
            return []
        slow = self.slow_criterion[idx]
        best = int(self.choice[idx])
        if not np.isfinite(slow[best]):
            return []
        return [{"structure": label(self.structures[i]), "likelihood_delta": float(slow[i] - slow[best])}
                for i in np.argsort(slow) if i != best and np.isfinite(slow[i])
                and slow[i] - slow[best] < CLOSE]

    def rejected(self, *idx) -> list[dict]:
        """The other candidates with their criterion values (``delta``: the wavelet-variance
        criterion's difference from the chosen one). First the slow part's alternatives
        (:mod:`.block_likelihood`), best first by ``likelihood_delta``; then the rest by
        ``delta``; those the record cannot resolve (a Gauss–Markov time beyond its share)
        last, ``resolvable`` false."""
        crit = self.criterion[idx]
        best = int(self.choice[idx])
        adm = self.admissible[idx] if self.admissible is not None else np.ones(len(crit), bool)
        slow = (self.slow_criterion[idx] if self.slow_criterion is not None
                else np.full(len(crit), np.nan))
        order = [int(i) for i in np.argsort(crit, kind="stable") if int(i) != best]
        alt = sorted((i for i in order if np.isfinite(slow[i])), key=lambda i: slow[i])
        order = alt + [i for i in order if adm[i] and i not in alt] \
            + [i for i in order if not adm[i] and i not in alt]
        out = []
        for i in order:
            r = {"structure": label(self.structures[i]), "kinds": list(self.structures[i]),
                 "criterion": float(crit[i]) if np.isfinite(crit[i]) else None,
                 "delta": float(crit[i] - crit[best]) if np.isfinite(crit[i]) else None}
            if np.isfinite(slow[i]) and np.isfinite(slow[best]):
                r["likelihood_delta"] = float(slow[i] - slow[best])
            if not adm[i] and i not in alt:
                r.update(resolvable=False, why="a Gauss–Markov correlation time beyond "
                         f"{LONG_SHARE:g} of the record")
            out.append(r)
        return out

    def model_curve(self, idx, tau) -> tuple[np.ndarray, np.ndarray]:
        """(per-component Allan variance (6, len τ), total) of one series' chosen model."""

        mask = jnp.asarray(self.masks[int(self.choice[idx])])
        rows = np.asarray(component_avar(jnp.asarray(self.theta[idx]), jnp.asarray(tau),
                                         float(self.dt[idx])))
        rows = np.where(np.asarray(row_mask(mask))[:, None], rows, np.nan)
        return rows, np.nansum(rows, axis=0)


def _param(log_power, log_var, unit, power=True):
    """{"value", "ci", "unit"} of an amplitude √power (``power``) or of a time."""
    h = 0.5 if power else 1.0
    lv = h * log_power
    se = h * np.sqrt(max(float(log_var), 0.0))
    lo, hi = np.exp(lv - Z95 * se), np.exp(lv + Z95 * se)
    clean = lambda x: float(x) if np.isfinite(x) else None  # noqa: E731
    return {"value": clean(np.exp(lv)), "ci": [clean(lo), clean(hi)], "unit": unit}


def components_of(theta, cov, mask) -> list[dict]:
    """JSON components of one model (log-parameters ``theta``, covariance ``cov``).

    **Arguments:**

    - ``theta``: the model's log-parameters.
    - ``cov``: their covariance.
    - ``mask``: which parameters the structure has (:func:`structure_mask`).
    """
    theta = np.asarray(theta)
    var = np.diag(np.asarray(cov))
    out = []
    if mask[0]:
        out.append({"kind": "white", "params": {"arw": _param(theta[0], var[0], "rad/s/√Hz")}})
    if mask[1]:
        out.append({"kind": "quantization", "params": {"q": _param(theta[1], var[1], "rad")}})
    gms = [(theta[i + 1], i) for i in (2, 4) if mask[i]]
    for _, i in sorted(gms):  # shortest correlation time first
        out.append({"kind": "gauss_markov", "params": {
            "sigma": _param(theta[i], var[i], "rad/s"),
            "tau": _param(theta[i + 1], var[i + 1], "s", power=False)}})
    if mask[6]:
        out.append({"kind": "random_walk", "params": {"rrw": _param(theta[6], var[6], "rad/s²/√Hz")}})
    if mask[7]:
        out.append({"kind": "rate_ramp", "params": {"r": _param(theta[7], var[7], "rad/s²")}})
    return out


def identify(y, dt, n_valid=None, structures=None, penalty: float = PENALTY,
             slow_penalty: float | None = None, slow_bootstrap: bool = True) -> NoiseModels:
    """Identify the stochastic model of every series ``y`` (..., n) in rad/s sampled every ``dt``
    seconds (scalar or per series); ``n_valid``: real samples of each padded series;
    ``structures``: the candidates (default :func:`~.selection.catalogue`), each with white
    noise; ``penalty``: the criterion's factor per parameter (:data:`~.selection.PENALTY`).

    **Arguments:**

    - ``y``: the series (..., n), rad/s.
    - ``dt``: the sampling interval, s: a scalar or one per series.
    - ``n_valid``: the real samples of each padded series (default: all n).
    - ``structures``: the candidate structures (default: :func:`~.selection.catalogue`).
    - ``penalty``: the criterion's factor per parameter.
    - ``slow_penalty``: the slow part chosen again by the block means' exact likelihood
      (step 5), with this criterion per parameter (:data:`SLOW_PENALTY`: a test at 1 %);
      None (default) skips it: it decides the slow components better on long records
      with several of them, at about twice the cost of the rest of identify (the
      bootstrap's draws more).
    - ``slow_bootstrap``: with ``slow_penalty``, the close calls between slow structures
      settled by a parametric bootstrap of the likelihood ratio
      (:mod:`.slow_bootstrap`); False keeps the χ² rule alone.
    """
    y = jnp.asarray(y, jnp.float64)
    lead = y.shape[:-1]
    n = y.shape[-1]
    structures, masks = _ordered(structures)
    nv = np.broadcast_to(np.asarray(n if n_valid is None else n_valid, np.int64), lead)
    dtb = np.broadcast_to(np.asarray(dt, np.float64), lead)
    m = dyadic_m(n)
    total = math.prod(lead)
    fits, choice = _programs(total * n)
    # the identification's programs traced here and compiled on threads of their own (XLA
    # holds no GIL) while the wavelet variances' program compiles and runs; those compiled
    # ahead before (``noise``'s :func:`load_ahead`) are not compiled again
    compiled = _compile_ahead(total * n, total, n, structures)
    # numpy in and out around the compiled programs: an eager operation on a JAX array is a
    # program of its own (lowered and read from the cache: milliseconds each)
    wv, count = haar_wv(y, dtb, None if n_valid is None else nv, m)
    flat = lambda a: np.asarray(a).reshape((-1,) + a.shape[len(lead):])  # noqa: E731
    args = [flat(a) for a in (wv, count, nv.astype(np.float64), dtb)]
    step = _chunk(total)
    for thread in compiled:
        thread.join()
    parts = []
    for lo in range(0, total, step):
        chunk = [a[lo:lo + step] for a in args]
        short = step - chunk[0].shape[0]
        if short:  # pad the last chunk with copies of its first series
            chunk = [np.concatenate([c, np.repeat(c[:1], short, axis=0)]) for c in chunk]
        # the fits as host arrays (the choice was compiled ahead for arrays placed on no
        # device in particular: JAX arrays would compile it again); a weak-typed scalar put
        # on the device as it is (jnp.asarray would run a program)
        fitted = [np.asarray(a) for a in fits(*chunk, m, masks, len(m))]
        res = choice(*chunk, m, masks, jax.device_put(float(penalty)), *fitted)
        parts.append({k: np.asarray(v)[:step - short] for k, v in res.items()})
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    slow = np.full((total, len(structures)), np.nan)
    if slow_penalty is not None:
        slow = _choose_slow(np.asarray(y).reshape(total, n), args, out, masks, m, step,
                            float(penalty), float(slow_penalty), slow_bootstrap)
    out = {k: v.reshape(lead + v.shape[1:]) for k, v in out.items()}
    tau = m[None, :] * dtb.reshape(-1, 1)
    return NoiseModels(structures=structures, masks=masks, tau=tau.reshape(lead + (len(m),)),
                       wv=np.asarray(wv), wv_sd=out["wv_sd"], valid=out["valid"], dt=dtb,
                       choice=out["pick"], theta=out["theta"], cov=out["cov"],
                       criterion=out["criterion"], theta_all=out["theta_all"],
                       objective=out["objective"], rank=out["rank"], admissible=out["admissible"],
                       limits=out["limits"], n_valid=nv,
                       slow_criterion=slow.reshape(lead + (len(structures),)))


def _ordered(structures) -> tuple[list[tuple[str, ...]], np.ndarray]:
    """The candidates (default :func:`~.selection.catalogue`) and their masks, ordered by
    their number of parameters (ties keep the given order)."""
    structures = list(structures) if structures is not None else catalogue()
    masks = np.stack([structure_mask(s) for s in structures])
    order = np.argsort(masks.sum(1), kind="stable")
    return [structures[i] for i in order], masks[order]


def _chunk(series: int) -> int:
    """Series per call: a fixed chunk, or the power of two at or above fewer series (a few
    compiled programs for any batch)."""
    return min(CHUNK if jax.default_backend() == "cpu" else ACCEL_CHUNK,
               1 << (max(series, 1) - 1).bit_length())


def chunk_specs(series: int, n: int, structures=None) -> tuple[jax.ShapeDtypeStruct, ...]:
    """Shapes and dtypes of the arguments :func:`identify` passes its programs for
    ``series`` series of ``n`` samples: the wavelet variances, their counts, the samples,
    the intervals (one row per series of a chunk), the cluster sizes, the candidates'
    masks and the penalty (the choice's only)."""
    step, scales = _chunk(series), len(dyadic_m(n))
    masks = _ordered(structures)[1]
    real, whole = np.dtype(np.float64), np.dtype(np.int64)
    spec = jax.ShapeDtypeStruct
    return (spec((step, scales), real), spec((step, scales), whole), spec((step,), real),
            spec((step,), real), spec((scales,), whole), spec(masks.shape, np.bool_),
            spec((), jax.dtypes.canonicalize_dtype(real), weak_type=True))


def program_specs(series: int, n: int, structures=None) -> tuple[tuple, tuple]:
    """The arguments :func:`identify` passes the fits' and the choice's programs for
    ``series`` series of ``n`` samples (shapes and dtypes, and the scales' number): the
    choice's end with the fits' results, the candidates' log-parameters and objectives and
    Ω_ref's Cholesky factor of every series of a chunk."""
    *data, penalty = chunk_specs(series, n, structures)
    (step, scales), (kinds, params) = data[0].shape, data[5].shape
    real = np.dtype(np.float64)
    spec = jax.ShapeDtypeStruct
    fitted = (spec((step, kinds, params), real), spec((step, kinds), real),
              spec((step, scales, scales), real))
    return (*data, scales), (*data, penalty, *fitted)


def _compile_ahead(samples: int, series: int, n: int, structures=None) -> list[threading.Thread]:
    """The fits' program and then the choice's lowered here and compiled on threads of their
    own (:func:`program_specs`): the choice's trace runs while the fits' program compiles."""
    fits, choice = _programs(samples)
    fits_args, choice_args = program_specs(series, n, structures)
    return [fits.compile_ahead(*fits_args), choice.compile_ahead(*choice_args)]


def load_ahead(series: int, n: int, structures=None, lead: tuple[int, ...] | None = None
               ) -> list[threading.Thread]:
    """Start what :func:`identify` of ``series`` series of ``n`` samples (``structures``:
    its candidates; ``lead``: the series' leading shape, default ``(series,)``) will run:
    its programs lowered here and compiled, or read from the persistent cache, on threads
    of their own (XLA holds no GIL meanwhile), and so the wavelet variances' program
    (:func:`~.wavelet_variance.haar_wv_ahead`), while the caller does other work
    (``noise`` checks that the devices are at rest). Join the threads before
    :func:`identify`, which then finds the programs loaded."""
    threads = _compile_ahead(series * n, series, n, structures)
    return threads + [haar_wv_ahead((series,) if lead is None else tuple(lead), n)]


def _choose_slow(y, args, out, masks, m, step, penalty, slow_penalty, bootstrap=True):
    """Per series, the slow part chosen by the block-mean likelihood
    (:func:`.block_likelihood.choose_slow_many`); ``out`` (flat over series) updated in place where
    the choice changed, the chosen model's intervals recomputed. Returns the likelihood
    criterion of every candidate (NaN off the slow alternatives)."""
    wv, count, nv, dtb = args
    total = y.shape[0]
    crit = np.full((total, masks.shape[0]), np.nan)
    changed = []
    idx = np.flatnonzero(nv >= 4 * BLOCKS)  # shorter: too short for blocks, the wavelet variances decide
    if idx.size:
        answers = choose_slow_many(y[idx], nv[idx].astype(np.int64), dtb[idx], masks,
                                   out["pick"][idx], out["theta_all"][idx],
                                   LONG_SHARE * nv[idx] * dtb[idx], slow_penalty,
                                   bootstrap=bootstrap)
        for i, res in zip(idx, answers):
            crit[i] = res["criterion"]
            if res["pick"] != out["pick"][i]:
                out["pick"][i] = res["pick"]
                changed.append(int(i))
    for lo in range(0, len(changed), step):
        idx = np.array(changed[lo:lo + step])
        idx = np.concatenate([idx, np.repeat(idx[:1], step - len(idx))])
        res = _at_pick_batch(*(jnp.asarray(a[idx]) for a in (wv, count, nv, dtb)), jnp.asarray(m),
                             jnp.asarray(out["theta_all"][idx, out["pick"][idx]]),
                             jnp.asarray(masks[out["pick"][idx]]), jnp.asarray(out["chol_ref"][idx]),
                             jnp.asarray(penalty))
        for k, v in res.items():
            out[k][idx] = np.asarray(v)
    return crit


def model_wv_np(theta, mask, tau, dt) -> np.ndarray:
    """The Haar wavelet variance of one model at τ (numpy in, numpy out)."""
    return np.asarray(model_wv(jnp.asarray(theta), jnp.asarray(mask), jnp.asarray(tau), dt))
