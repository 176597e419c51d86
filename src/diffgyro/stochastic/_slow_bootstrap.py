"""The slow part's close calls settled by a parametric bootstrap of the likelihood ratio.

The block means' likelihood (:mod:`.block_likelihood`) chooses the slow part by
``−2 log L + penalty × k``: each added parameter a likelihood-ratio test at χ²₁'s 1 %
point. That law holds for many independent frequencies; a slow Gauss–Markov process, a
walk and a ramp are told apart on the record's lowest few, where it does not. There the
statistic of a ramp added beside a walk and a slow process exceeds χ²₁'s 1 % point in
several per cent of records, and that of a slow process against a walk (not nested once
the process's time is held within a tenth of the record) far less often than χ²₁ says.

So the statistic's law is drawn where the test between the chosen structure and a
competitor is close: block-mean differences simulated from the simpler structure S's fit
(its Toeplitz covariance, a ramp's mean where S has one), both structures refitted to each
draw as they were to the record (the same starts, bounds and the same exclusion of a
Gauss–Markov time beyond a tenth of the record, which counts as R not fitting), and the
richer R taken where the Monte Carlo p-value ``(1 + #{T_b ≥ T})/(B + 1)`` of
T = −2 log L(S) − (−2 log L(R)) is at most :data:`LEVEL` (Davison & Hinkley 1997, ch. 4);
the draws stop as soon as it cannot be. Which pairs:

* S's slow components a subset of R's (nested): R must pass both χ²₁'s point per added
  parameter and the drawn law's (a test that rejects only where two tests at 1 % both do
  is one at 1 % at most). The draws are made only where χ² takes R: they can only hold it
  back, where the few lowest frequencies make the statistic's law heavier than χ²'s (a
  ramp beside a slow process and a walk); at a boundary (a walk of power zero) χ²'s point
  is the stricter one and stays;
* neither within the other (a slow process against a walk or a ramp; not nested once the
  process's time is held within a tenth of the record): no χ² law; the draws decide where
  T lies between :data:`MIN_GAIN` and :data:`CLEAR` per added parameter.

Structures of one size are ranked by their likelihood, and pairs that call for no draws
by the χ² rule. The structure chosen is the one that wins its comparison with each
contender (those within :data:`CLEAR` of the χ²-rule's best criterion), looked for in the
order of that criterion; where none does (the draws' answers need not be transitive), the
χ² rule's pick stays. At most :data:`MAX_TESTS` pairs a series are drawn; beyond them the χ²
rule answers.
"""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import Float
from scipy.linalg import cholesky, solve_toeplitz, toeplitz

#: Level of each test (the χ²₁ penalty's).
LEVEL = 0.01
#: Draws of the statistic at most per test: the p-value (1 + e)/(B + 1) with B = 99 takes R
#: where no draw reaches the record's statistic, and a test is stopped at its first exceedance.
DRAWS = 99
#: Draws per batch; the test stops once the exceedances rule R out.
BATCH = 50
#: A statistic beyond this many units per added parameter is no close call (the χ² rule
#: decides it): the largest of 200 draws of a ramp's statistic beside a slow process and a
#: walk, where χ²₁ is anti-conservative, was 13.8.
CLEAR = 2.0 * 6.635
#: Below this many units per added parameter the simpler structure stays without draws (the
#: richer must at least pass Akaike's criterion): a walk or ramp fitted to nothing lowers
#: −2 log L by a rounding error, which the draws' own rounding would call significant.
MIN_GAIN = 2.0
#: Pairs drawn per series at most.
MAX_TESTS = 4
#: Seed of the draws (the same standard normals for every test: the choice is reproducible).
SEED = 20261128


def gm_slots(mask) -> list[tuple[int, int]]:
    """The Gauss–Markov slots (variance, time: (2, 3) then (4, 5) of the parameter vector) a
    mask switches on."""
    return [(iv, it) for iv, it in ((2, 3), (4, 5)) if mask[iv]]


def beyond(th, masks, log_long: float) -> np.ndarray:
    """Per candidate (rows of ``th`` and ``masks``): a Gauss–Markov time beyond
    ``exp(log_long)`` (the record's share, where the candidate does not fit)."""
    return np.array([any(t[it] > log_long for _, it in gm_slots(mk)) for t, mk in zip(th, masks)],
                    bool)


def simulate(c: Float[np.ndarray, " m"], mean: float, draws: int,
             rng: np.random.Generator) -> Float[np.ndarray, "draws m"]:
    """``draws`` series of M block-mean differences with autocovariance ``c`` (M,) and mean
    ``mean`` (the Cholesky factor of the Toeplitz covariance)."""
    chol = cholesky(toeplitz(c), lower=True)
    return mean + rng.standard_normal((draws, c.shape[0])) @ chol.T


def gls_mean(c: Float[np.ndarray, " m"], d: Float[np.ndarray, " m"]) -> float:
    """The generalised least-squares mean of ``d`` under the Toeplitz covariance of ``c``: a
    ramp's fitted mean of the differences."""
    w = solve_toeplitz(c, np.ones_like(d))
    return float(w @ d / w.sum())


class Settle:
    """The close calls of one series' slow part (:func:`settle`'s state): its likelihood
    ``lik`` and row, and the candidates' refits (θ, −2 log L, masks, bounds, free
    parameters) as :func:`.block_likelihood.choose_slow_many` made them."""

    def __init__(self, lik, row, th, dev, masks, lo, hi, free, long_time, penalty):
        self.lik, self.row, self.penalty = lik, int(row), float(penalty)
        self.th, self.dev, self.masks = th, dev, np.asarray(masks, bool)
        self.lo, self.hi, self.free = lo, hi, free
        self.log_long = math.log(long_time)
        self.k = self.masks.sum(axis=1)
        self.tests: list[dict] = []
        self._won: dict[tuple[int, int], int] = {}

    def draws(self, s: int, r: int, d: np.ndarray) -> np.ndarray:
        """T = −2 log L(S) − (−2 log L(R)) on each row of simulated differences ``d``; −inf
        where R's refit runs beyond the record's share."""
        lik = self.lik
        rep = type(lik).of_differences(d, int(lik.bs[self.row]), float(lik.dts[self.row]))
        count = d.shape[0]
        pick = np.repeat(np.array([s, r]), count)
        rows = np.tile(np.arange(count), 2)
        th, dev = rep.fit(self.th[pick], self.masks[pick], self.lo[pick], self.hi[pick],
                          self.free[pick], rows=rows)
        alt = np.where(beyond(th[count:], self.masks[pick][count:], self.log_long), np.inf,
                       dev[count:])
        return dev[:count] - alt

    def p_value(self, s: int, r: int, t: float) -> tuple[float, int]:
        """(Monte Carlo p-value of T = ``t`` under S's fit, draws taken)."""
        lik = self.lik
        c = lik.acov(self.th[[s]], self.masks[[s]], np.array([self.row]))[0][0]
        mean = gls_mean(c, lik.ds[self.row]) if self.masks[s, 7] else 0.0
        rng = np.random.default_rng(SEED)
        d = simulate(c, mean, DRAWS, rng)
        exceed, taken = 0, 0
        while taken < DRAWS:
            batch = d[taken:taken + BATCH]
            exceed += int(np.sum(self.draws(s, r, batch) >= t))
            taken += batch.shape[0]
            if (1 + exceed) / (DRAWS + 1) > LEVEL:  # R cannot pass any more
                break
        return (1 + exceed) / (taken + 1), taken

    def pair(self, a: int, b: int) -> int:
        """The winner of candidates ``a`` and ``b`` (module docstring)."""
        key = (min(a, b), max(a, b))
        if key not in self._won:
            self._won[key] = self._pair(*key)
        return self._won[key]

    def _pair(self, a: int, b: int) -> int:
        if self.k[a] == self.k[b]:
            return a if self.dev[a] <= self.dev[b] else b
        s, r = (a, b) if self.k[a] < self.k[b] else (b, a)
        t = float(self.dev[s] - self.dev[r])
        extra = int(self.k[r] - self.k[s])
        chi2 = r if t > self.penalty * extra else s
        if not np.isfinite(t) or not MIN_GAIN * extra < t < CLEAR * extra:
            return chi2  # no close call
        if np.all(self.masks[s] <= self.masks[r]) and chi2 == s:
            return s  # nested, and χ² keeps S: the draws could only make the test laxer
        if len(self.tests) >= MAX_TESTS:
            return chi2
        p, taken = self.p_value(s, r, t)
        self.tests.append({"simpler": int(s), "richer": int(r), "statistic": t, "p": p,
                           "draws": taken})
        return r if p <= LEVEL else s


def settle(st: Settle, first: int, crit: np.ndarray) -> int:
    """The pick after the close calls (module docstring), from the χ²-rule's pick ``first``
    among candidates of finite criterion ``crit``."""
    near = [int(i) for i in np.argsort(crit) if crit[i] < crit[first] + CLEAR]
    for c in near:
        if all(st.pair(c, x) == c for x in near if x != c):
            return c
    return first
