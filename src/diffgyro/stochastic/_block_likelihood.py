"""The slow part of a structure chosen by the exact likelihood of the record's block means.

The wavelet-variance criterion sees a record's slowest content through its last one
or two dyadic scales, each the mean of a few independent terms: a Gauss–Markov bias
of correlation time near a tenth of the record, a weak random walk beside one, a ramp
beside either are told apart there, or not at all. The Gaussian likelihood uses all
of the record's low-frequency content. Here it is exact, for a short series that keeps it:

* ``ȳ_k``: the mean of block k of ``b`` samples (:data:`BLOCKS` blocks a record);
  ``d_k = ȳ_k − ȳ_(k−1)``, stationary under every component, the walk's included (a
  second difference of the angle). Its autocovariance is exact for each component,
  with ``τ = b·dt``, φ = exp(−dt/T), v = 1 − φ, ψ = φ^b, u = 1 − ψ:

  =================  ====================================================================
  white N²           c(0) = 2N²/τ, c(1) = −N²/τ
  quantization Q²    c(0) = 6Q²/τ², c(1) = −4Q²/τ², c(2) = Q²/τ²
  Gauss–Markov σ²,T  c(0) = 2·AVAR(τ), c(h ≥ 2) = −σ²φψ^(h−2)u⁴/(v²b²), and c(1) from
                     Σ_h c(h) = 0 (a difference of a stationary series): −c(0)/2 + σ²φu³/(v²b²)
  random walk K²     c(0) = K²dt(2b/3 + 1/(3b)), c(1) = K²dt(b − 1/b)/6
  rate ramp R        the mean R·τ of every d_k: a regressor
  =================  ====================================================================

* ``−2 log L = log det Σ + rᵀΣ⁻¹r`` with Σ the Toeplitz covariance of d and r = d less
  its mean: zero without a ramp; with one, the generalised least-squares mean (the
  ramp fitted out as a deterministic trend, the profile likelihood). Between two
  models that differ by the ramp alone the statistic is χ² with one degree of freedom.
  (The Whittle approximation of this likelihood fails here: the differences' spectrum
  vanishes at zero frequency without a walk, and on white noise it took a walk far more
  often than the test's level.)

Each candidate is refitted by Levenberg–Marquardt steps (the exact gradient
``tr(Σ⁻¹∂Σ) − αᵀ∂Σα``, α = Σ⁻¹r; the Whittle approximation of the Fisher information
as the metric; the deviance and its gradient in O(M²) by the Durbin–Levinson recursion
and the Gohberg–Semencul form of Σ⁻¹, :mod:`.toeplitz`) from its wavelet-variance estimate. The criterion is
``−2 log L + penalty × k``: a likelihood-ratio test of each added parameter at the
level :data:`PENALTY` states; where that test is close, the statistic's law is drawn instead
(:mod:`.slow_bootstrap`). Only the slow part is chosen here (:func:`choose_slow`):
the white noise, quantization and the Gauss–Markov processes faster than
:data:`FAST_BLOCKS` blocks, which the block means average into white noise, stay
those of the wavelet-variance choice.
"""

from __future__ import annotations

import math

import numpy as np

from ._slow_bootstrap import Settle, beyond, gm_slots, settle

#: Blocks of a record at least (the block length b = n // BLOCKS samples, at least 1): fewer
#: blocks say less on a slow Gauss–Markov beside a walk; the cost grows as their square.
BLOCKS = 256
#: A Gauss–Markov process of the wavelet-variance choice with T below this many blocks is
#: part of the fast structure, kept as chosen: the block means see it as white noise.
FAST_BLOCKS = 0.5
#: Levenberg–Marquardt iterations per candidate at most.
ITERATIONS = 20
#: A candidate whose accepted step lowers −2 log L by less than this has converged.
TOLERANCE = 1e-4
#: Criterion difference below which an alternative is reported as hardly told apart from
#: the chosen structure (2 log L of 2: evidence "not worth more than a bare mention",
#: Kass & Raftery 1995).
CLOSE = 2.0
#: Criterion per parameter: the 99 % point of χ² with one degree of freedom. A parameter
#: on its boundary (a random walk or ramp of power 0) enters a record that does not hold
#: it with probability about 0.5 %.
PENALTY = 6.635


def block_differences(y: np.ndarray, n_valid: int, blocks: int = BLOCKS) -> tuple[np.ndarray, int]:
    """(d, b): the differences of the means of consecutive blocks of ``b`` samples over the
    first ``n_valid`` samples of ``y`` (the last ``n_valid mod b`` left out)."""
    b = max(1, int(n_valid) // blocks)
    mcount = int(n_valid) // b
    means = np.asarray(y[:mcount * b], np.float64).reshape(mcount, b).mean(axis=1)
    return np.diff(means), b


def periodogram(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(I, w): the periodogram of ``d`` at j = 0 … ⌊M/2⌋ (the mean kept: j = 0 carries it)
    and each ordinate's weight in −2 log L."""
    m = d.shape[-1]
    spec = np.abs(np.fft.rfft(d)) ** 2 / m
    w = np.full(spec.shape[-1], 2.0)
    w[0] = 1.0
    if m % 2 == 0:
        w[-1] = 1.0
    return spec, w


def _avar_gm(s2, t, tau, dt):
    """Allan variance of the sampled Gauss–Markov process at τ (numpy; as
    :func:`.components.avar_gauss_markov`)."""
    m = tau / dt
    a = dt / t
    one_phi = -np.expm1(-a)
    phi = 1.0 - one_phi
    one_phim = -np.expm1(-a * m)
    x = a * m
    series = (m * m - m) * a**2 / 2.0 - (m**3 - m) * a**3 / 6.0 + (m**4 - m) * a**4 / 24.0
    inner = np.where(x < 1e-3, series, m * one_phi - one_phim)
    return s2 * (m + (2.0 * phi * inner - phi * one_phim**2) / one_phi**2) / m**2


def gm_acov(t: np.ndarray, b: int, dt: float, lags: int) -> np.ndarray:
    """Autocovariance (..., lags) of the block-mean differences of a unit-variance
    Gauss–Markov process of correlation time ``t`` (module docstring)."""
    t = np.asarray(t, np.float64)[..., None]
    v = -np.expm1(-dt / t)
    phi = 1.0 - v
    u = -np.expm1(-b * dt / t)
    c0 = 2.0 * _avar_gm(1.0, t, b * dt, dt)
    h = np.arange(lags)
    tail = -phi * np.exp(-(np.maximum(h, 2) - 2) * b * dt / t) * u**4 / (v**2 * b**2)
    c1 = -0.5 * c0 + phi * u**3 / (v**2 * b**2)
    return np.where(h == 0, c0, np.where(h == 1, c1, tail))


def short_acov(b: int, dt: float, lags: int) -> np.ndarray:
    """Autocovariance (3, lags) of the block-mean differences of unit white noise (N² = 1),
    quantization (Q² = 1) and random walk (K² = 1)."""
    tau = b * dt
    out = np.zeros((3, lags))
    out[0, :2] = [2.0 / tau, -1.0 / tau]
    out[1, :3] = [6.0 / tau**2, -4.0 / tau**2, 1.0 / tau**2][:min(3, lags)]
    out[2, :2] = [dt * (2.0 * b / 3.0 + 1.0 / (3.0 * b)), dt * (b - 1.0 / b) / 6.0]
    return out


def expected_periodogram(acov: np.ndarray) -> np.ndarray:
    """E_j = Σ_(|h|<M) (1 − |h|/M) c(h) e^(−iω_j h) at j = 0 … ⌊M/2⌋ from c(0 … M−1)."""
    m = acov.shape[-1]
    a = acov * (1.0 - np.arange(m) / m)
    return 2.0 * np.fft.rfft(a).real - acov[..., :1]


class BlockLikelihood:
    """The exact Gaussian likelihood of the block-mean differences of one record, or of
    several with the same number of differences (one row each), for models in the
    wavelet-variance fit's log-parameters (:data:`.components.LAYOUT`)."""

    def __init__(self, y: np.ndarray, n_valid, dt, blocks: int = BLOCKS):
        """``y`` (n,) or (S, n); ``n_valid`` and ``dt`` a scalar or one per series."""
        y = np.asarray(y)
        ys = y.reshape((-1, y.shape[-1]))
        nv = np.broadcast_to(np.asarray(n_valid), ys.shape[:1])
        parts = [block_differences(ys[i], int(nv[i]), blocks) for i in range(ys.shape[0])]
        if len({p[0].shape[-1] for p in parts}) != 1:
            raise ValueError("the series of one BlockLikelihood need the same number of blocks")
        self.ds = np.stack([p[0] for p in parts])  # (S, M)
        self.bs = np.array([p[1] for p in parts])
        self.dts = np.broadcast_to(np.asarray(dt, np.float64), ys.shape[:1]).copy()
        self.m = self.ds.shape[-1]
        self.units = np.stack([short_acov(int(b), float(t), self.m)
                               for b, t in zip(self.bs, self.dts)])  # (S, 3, M)
        self.d, self.b, self.dt, self.unit = self.ds[0], int(self.bs[0]), float(self.dts[0]), self.units[0]
        self.w = periodogram(np.zeros(self.m))[1]
        from ._toeplitz import toeplitz_deviance  # numba: compiled on first use
        self._deviance = toeplitz_deviance

    @classmethod
    def of_differences(cls, ds: np.ndarray, b: int, dt: float) -> "BlockLikelihood":
        """The likelihood of given block-mean differences ``ds`` (S, M) of blocks of ``b``
        samples every ``dt`` seconds (one row each): the bootstrap's draws."""
        from ._toeplitz import toeplitz_deviance

        self = cls.__new__(cls)
        self.ds = np.atleast_2d(np.asarray(ds, np.float64))
        count, self.m = self.ds.shape
        self.bs = np.full(count, int(b))
        self.dts = np.full(count, float(dt))
        self.units = np.broadcast_to(short_acov(int(b), float(dt), self.m), (count, 3, self.m))
        self.d, self.b, self.dt, self.unit = self.ds[0], int(b), float(dt), self.units[0]
        self.w = periodogram(np.zeros(self.m))[1]
        self._deviance = toeplitz_deviance
        return self

    def _gm(self, log_t, rows):
        """(c, ∂c/∂log T) (C, M) of unit-variance Gauss–Markov processes of times exp(log_t)
        (C,) in the series ``rows`` (C,)."""
        h = 1e-5
        lt = np.stack([log_t, log_t + h, log_t - h], axis=-1)
        c = gm_acov(np.exp(lt), self.bs[rows, None, None], self.dts[rows, None, None], self.m)
        return c[..., 0, :], (c[..., 1, :] - c[..., 2, :]) / (2.0 * h)

    def acov(self, theta: np.ndarray, mask: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(c (C, M), ∂c/∂θ (C, 8, M)) for log-parameters ``theta`` (C, 8) under ``mask`` in
        the series ``rows`` (C,)."""
        p = np.exp(theta) * mask
        unit = self.units[rows]
        d = np.zeros((theta.shape[0], 8, self.m))
        d[:, 0] = p[:, 0, None] * unit[:, 0]
        d[:, 1] = p[:, 1, None] * unit[:, 1]
        for iv in (2, 4):  # the Gauss–Markov slots, where a candidate has them
            on = np.flatnonzero(mask[:, iv])
            if on.size:
                g, dg = self._gm(theta[on, iv + 1], rows[on])
                d[on, iv] = p[on, iv, None] * g
                d[on, iv + 1] = p[on, iv, None] * dg
        d[:, 6] = p[:, 6, None] * unit[:, 2]
        return d[:, [0, 1, 2, 4, 6]].sum(axis=1), d

    def deviance(self, c: np.ndarray, ramp: bool, grad: bool = False, row: int = 0):
        """−2 log L (less its constant) of series ``row`` for the autocovariance ``c`` (M,) of
        one candidate (inf where its covariance is not positive definite); ``ramp``: the mean
        of the differences is free (its generalised least-squares estimate). With ``grad``:
        also tr(Σ⁻¹T_h) − αᵀT_hα for each lag's Toeplitz indicator T_h (M,), α = Σ⁻¹(d − mean),
        whose product with ∂c/∂θ is the gradient."""
        if not grad:
            return self._deviance(c, self.ds[row], ramp)
        g = np.empty(self.m)
        dev = self._deviance(c, self.ds[row], ramp, g)
        return (dev, g) if np.isfinite(dev) else (np.inf, np.full(self.m, np.nan))

    def fisher(self, c: np.ndarray, dc: np.ndarray) -> np.ndarray:
        """The Whittle approximation of the Fisher information (C, 8, 8): the step's metric."""
        e = np.maximum(expected_periodogram(c), 1e-300)
        de = expected_periodogram(dc) / e[:, None, :]
        return np.einsum("j,cpj,cqj->cpq", self.w, de, de)

    def fit(self, theta0: np.ndarray, masks: np.ndarray, lo: np.ndarray, hi: np.ndarray,
            free: np.ndarray | None = None, iterations: int = ITERATIONS,
            rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(θ (C, 8), −2 log L (C,)): every candidate refitted by Levenberg–Marquardt steps
        (the exact gradient, the Whittle metric) within the bounds ``lo``, ``hi``; ``free``
        (C, 8): the parameters refitted (default: all those switched on); ``rows`` (C,): the
        series of each candidate (default: the first). The candidates' steps are taken side
        by side, each on its own."""
        masks = np.asarray(masks, bool)
        rows = np.zeros(masks.shape[0], int) if rows is None else np.asarray(rows, int)
        on = (masks if free is None else masks & free).astype(np.float64)
        on[:, 7] = 0.0  # the ramp is the profiled mean, not a covariance parameter
        ramp = masks[:, 7]
        lo = np.broadcast_to(lo, masks.shape)
        hi = np.broadcast_to(hi, masks.shape)
        th = np.clip(np.asarray(theta0, np.float64), lo, hi)
        eye = np.eye(8)
        count = th.shape[0]
        lam = np.full(count, 1e-2)
        c, dc = self.acov(th, masks, rows)
        cost, gl = np.empty(count), np.empty((count, self.m))
        for k in range(count):
            cost[k], gl[k] = self.deviance(c[k], ramp[k], True, rows[k])
        done = ~np.isfinite(cost)
        for _ in range(iterations):
            act = np.flatnonzero(~done)
            if act.size == 0:
                break
            g = np.einsum("cpm,cm->cp", dc[act], gl[act]) * on[act]
            f = self.fisher(c[act], dc[act]) * on[act, :, None] * on[act, None, :]
            damp = lam[act, None] * (np.diagonal(f, axis1=1, axis2=2) + 1e-9) + (1.0 - on[act])
            step = -np.linalg.solve(f + damp[:, :, None] * eye, g[:, :, None])[..., 0] * on[act]
            trial = np.clip(th[act] + step, lo[act], hi[act])
            c_t, dc_t = self.acov(trial, masks[act], rows[act])
            for r, k in enumerate(act):
                new = self.deviance(c_t[r], ramp[k], False, rows[k])
                if not (np.isfinite(new) and new < cost[k]):
                    lam[k] = min(lam[k] * 4.0, 1e9)
                    done[k] = lam[k] > 1e4  # no step of any length lowers it: converged
                    continue
                done[k] = cost[k] - new < TOLERANCE
                th[k], c[k], dc[k] = trial[r], c_t[r], dc_t[r]
                if done[k]:  # converged: no further step needs the gradient
                    cost[k] = new
                else:
                    cost[k], gl[k] = self.deviance(c[k], ramp[k], True, rows[k])
                lam[k] = max(lam[k] / 5.0, 1e-9)
        return th, cost


def choose_slow(y: np.ndarray, n_valid: int, dt: float, masks: np.ndarray, pick: int,
                theta_all: np.ndarray, long_time: float, penalty: float = PENALTY,
                blocks: int = BLOCKS, bootstrap: bool = True) -> dict:
    """The candidate of least ``−2 log L + penalty × k`` among those that keep the chosen
    one's fast part (its white noise, quantization and the Gauss–Markov processes with T
    below :data:`FAST_BLOCKS` blocks) and differ in the slow part only: Gauss–Markov
    processes with T between that and ``long_time``, a random walk, a ramp. The fast part
    starts from the chosen fit and stays fast; the slow part starts from each candidate's
    own wavelet-variance fit and from the low frequencies' level, the better kept.
    ``bootstrap``: the close calls settled by the statistic's drawn law
    (:mod:`.slow_bootstrap`). Returns ``pick`` and, per candidate, ``deviance`` and
    ``criterion`` (NaN off the set), and ``tests`` (the bootstrap tests made)."""
    return choose_slow_many(np.asarray(y)[None], [n_valid], [dt], masks, [pick],
                            np.asarray(theta_all)[None], [long_time], penalty, blocks,
                            bootstrap)[0]


def choose_slow_many(y: np.ndarray, n_valid, dt, masks: np.ndarray, picks, theta_all: np.ndarray,
                     long_time, penalty: float = PENALTY, blocks: int = BLOCKS,
                     bootstrap: bool = True) -> list[dict]:
    """:func:`choose_slow` of every series ``y`` (S, n) (``n_valid``, ``dt``, ``picks``,
    ``long_time`` (S,); ``theta_all`` (S, K, 8)): the series with the same number of
    blocks refitted side by side (one Levenberg–Marquardt loop over all their candidates)."""
    masks = np.asarray(masks, bool)
    nv = np.asarray(n_valid, np.int64)
    count = [int(v) // max(1, int(v) // blocks) - 1 for v in nv]  # the differences of each
    out: list[dict] = [{}] * len(nv)
    for m in sorted(set(count)):
        group = [i for i in range(len(nv)) if count[i] == m]
        lik = BlockLikelihood(np.asarray(y)[group], nv[group], np.asarray(dt, np.float64)[group], blocks)
        sets = [_candidates(lik, r, int(nv[i]), masks, int(picks[i]),
                            np.asarray(theta_all[i], np.float64)) for r, i in enumerate(group)]
        rows = np.concatenate([np.full(len(c[0]), r) for r, c in enumerate(sets)])
        th, dev = lik.fit(*(np.concatenate([c[k] for c in sets]) for k in (1, 2, 3, 4, 5)),
                          rows=rows)
        at = 0
        for r, i in enumerate(group):
            alt = sets[r][0]
            part = slice(at, at + len(alt))
            at += len(alt)
            st = (Settle(lik, r, th[part], dev[part], *sets[r][2:], float(long_time[i]), penalty)
                  if bootstrap else None)
            out[i] = _chosen(masks, alt, th[part], dev[part], int(picks[i]), float(long_time[i]),
                             penalty, np.shape(theta_all[i]), int(lik.bs[r]), st)
    return out


def _candidates(lik: BlockLikelihood, row: int, n_valid: int, masks: np.ndarray, pick: int,
                theta_all: np.ndarray):
    """(alt, starts, masks, lo, hi, free) of :func:`choose_slow`'s candidates of series ``row``."""
    b, dt = int(lik.bs[row]), float(lik.dts[row])
    record = n_valid * dt
    fast_time = FAST_BLOCKS * b * dt
    chosen, th_s = masks[pick], theta_all[pick]
    fast = sorted((th_s[iv], th_s[it]) for iv, it in gm_slots(chosen) if math.exp(th_s[it]) < fast_time)
    fast = sorted(fast, key=lambda p: p[1])
    gm_count = masks[:, 2].astype(int) + masks[:, 4].astype(int)
    alt = np.flatnonzero((masks[:, 0] == chosen[0]) & (masks[:, 1] == chosen[1])
                         & (gm_count >= len(fast)))
    # the level of the lowest frequencies, for the slow powers' second start
    low = slice(1, 5)
    level = float(np.mean(periodogram(lik.ds[row])[0][low]))
    unit_rw = float(np.mean(expected_periodogram(lik.units[row, 2])[low]))
    slow_t0 = max(2.0 * fast_time, 0.02 * record)
    unit_gm = float(np.mean(expected_periodogram(
        lik._gm(np.array([math.log(slow_t0)]), np.array([row]))[0][0])[low]))
    starts, lo, hi, free = [], [], [], []
    for i in alt:
        th_i = theta_all[i]
        a = np.full(8, -150.0)
        a[[0, 1]] = th_s[[0, 1]]
        lo_i, hi_i, free_i = np.full(8, -150.0), np.full(8, 150.0), np.ones(8, bool)
        slots = gm_slots(masks[i])
        own_slow = sorted(((th_i[iv], th_i[it]) for iv, it in slots
                           if math.exp(th_i[it]) >= fast_time), key=lambda p: p[1])
        for k, (iv, it) in enumerate(slots):
            if k < len(fast):  # the fast part as chosen
                a[iv], a[it] = fast[k]
                free_i[[iv, it]] = False
                continue
            j = k - len(fast)
            a[iv], a[it] = (own_slow[j] if j < len(own_slow)
                            else (math.log(0.5 * level / unit_gm), math.log(slow_t0)))
            lo_i[it], hi_i[it] = math.log(fast_time), math.log(20.0 * record)
        a[6] = max(th_i[6], math.log(0.1 * level / unit_rw))
        starts.append(a)
        lo.append(lo_i)
        hi.append(hi_i)
        free.append(free_i)
    return alt, np.array(starts), masks[alt], np.array(lo), np.array(hi), np.array(free)


def _chosen(masks, alt, th, dev, pick, long_time, penalty, shape, block, st=None) -> dict:
    """:func:`choose_slow`'s answer from its candidates' refits; ``st``: the close calls'
    bootstrap (:class:`.slow_bootstrap.Settle`), or None."""
    k = masks[alt].sum(axis=1)
    crit = dev + penalty * k
    long = beyond(th, masks[alt], math.log(long_time))
    crit_ok = np.where(np.isfinite(crit) & ~long, crit, np.inf)
    best = int(pick)
    if np.isfinite(crit_ok).any():
        first = int(np.argmin(crit_ok))
        best = int(alt[settle(st, first, crit_ok) if st is not None else first])
    dev_all = np.full(masks.shape[0], np.nan)
    crit_all = np.full(masks.shape[0], np.nan)
    dev_all[alt] = dev
    crit_all[alt] = np.where(long, np.nan, crit)
    theta_w = np.full(shape, np.nan)
    theta_w[alt] = th
    tests = [] if st is None else [{**t, "simpler": int(alt[t["simpler"]]),
                                    "richer": int(alt[t["richer"]])} for t in st.tests]
    return {"pick": best, "deviance": dev_all, "criterion": crit_all, "theta": theta_w,
            "block": block, "tests": tests}
