"""The block means' likelihood that chooses a noise model's slow part: its autocovariances
against the covariance of the block-mean differences formed sample by sample, its O(M²)
deviance and gradient against the dense Cholesky factor and inverse and against finite
differences, and the likelihood-ratio statistic of a walk on records without one at its
nominal level."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve, toeplitz

from diffgyro.internal import BlockLikelihood, gm_acov, short_acov
from diffgyro.stochastic._toeplitz import toeplitz_deviance

B, DT, M = 5, 0.1, 6


def _difference_map() -> np.ndarray:
    """The linear map from n = B·(M + 1) rate samples to the M block-mean differences."""
    a = np.zeros((M, B * (M + 1)))
    for k in range(M):
        a[k, (k + 1) * B:(k + 2) * B] += 1.0 / B
        a[k, k * B:(k + 1) * B] -= 1.0 / B
    return a


def _lag_row(sample_cov: np.ndarray) -> np.ndarray:
    a = _difference_map()
    return (a @ sample_cov @ a.T)[0]


def test_white_quantization_and_walk_autocovariances_are_exact():
    n = B * (M + 1)
    unit = short_acov(B, DT, M)
    np.testing.assert_allclose(unit[0], _lag_row(np.eye(n) / DT), atol=1e-12)  # N² = 1
    diff = (np.eye(n + 1)[1:] - np.eye(n + 1)[:-1]) / DT  # rate = Δ(angle error)/dt, Q² = 1
    np.testing.assert_allclose(unit[1], _lag_row(diff @ diff.T), atol=1e-9)
    walk = np.tril(np.ones((n, n)))  # rate = running sum of steps of variance K²dt, K² = 1
    np.testing.assert_allclose(unit[2], _lag_row(walk @ walk.T * DT), atol=1e-12)


@pytest.mark.parametrize("t_corr", [0.05, 0.7, 30.0, 3e4])
def test_gauss_markov_autocovariance_is_exact(t_corr):
    """From much shorter than a sample to far beyond the blocks (the closed form's
    cancellations)."""
    i = np.arange(B * (M + 1))
    phi = math.exp(-DT / t_corr)
    want = _lag_row(phi ** np.abs(i[:, None] - i[None, :]))
    np.testing.assert_allclose(gm_acov(t_corr, B, DT, M), want, rtol=1e-6,
                               atol=1e-9 * abs(want[0]))


def test_a_walk_enters_white_noise_at_the_tests_level():
    """White noise, 20 records: 2 log L of white + random walk over white alone is ½χ²₀ + ½χ²₁
    (the walk's power on its boundary), above 6.63 in 0.5 % of records."""
    rng = np.random.default_rng(7)
    dt, n = 0.01, 256 * 16
    masks = np.zeros((2, 8), bool)
    masks[:, 0] = True
    masks[1, 6] = True
    lo, hi = np.full(8, -150.0), np.full(8, 150.0)
    stats = []
    for _ in range(20):
        y = 1e-3 / math.sqrt(dt) * rng.standard_normal(n)
        lik = BlockLikelihood(y, n, dt)
        th0 = np.full((2, 8), -150.0)
        th0[:, 0] = math.log(1e-6)
        th0[1, 6] = math.log(1e-8)
        _, dev = lik.fit(th0, masks, lo, hi)
        stats.append(dev[0] - dev[1])
    stats = np.array(stats)
    assert np.all(stats > -1e-6)  # nested: the walk never fits worse
    assert np.sum(stats > 6.63) <= 1


def _catalogue(m: int) -> dict[str, np.ndarray]:
    """Autocovariances of block-mean differences (blocks of 40 samples at 100 Hz): each
    process alone and mixtures, from white-like to near a unit root."""
    b, dt = 40, 0.01
    unit = short_acov(b, dt, m)
    gm = lambda t: gm_acov(t, b, dt, m)  # noqa: E731
    return {
        "white": unit[0],
        "quantization": unit[1],
        "white + quantization": unit[0] + 40.0 * unit[1],
        "gm 0.05 s": gm(0.05),
        "gm 2 s": gm(2.0),
        "gm 50 s": gm(50.0),
        "gm 5000 s": gm(5e3),
        "walk": unit[2],
        "white + walk": unit[0] + 0.01 * unit[2],
        "white + gm + walk": unit[0] + 1e2 * gm(3.0) + unit[2],
        "white + gm×2 + walk": unit[0] + 30.0 * gm(0.2) + 10.0 * gm(40.0) + 0.1 * unit[2],
    }


def _dense(factor, d, ramp):
    """(−2 log L, gradient with respect to c) from the dense Cholesky factor and inverse."""
    m = d.shape[0]
    inv = cho_solve(factor, np.eye(m))
    one = np.ones(m)
    mean = (one @ inv @ d) / (one @ inv @ one) if ramp else 0.0
    alpha = inv @ (d - mean)
    dev = 2.0 * np.log(np.diagonal(factor[0])).sum() + (d - mean) @ alpha
    lag = np.abs(np.subtract.outer(np.arange(m), np.arange(m)))
    corr = np.correlate(alpha, alpha, "full")[m - 1:]
    corr[1:] *= 2.0
    return dev, np.bincount(lag.ravel(), inv.ravel(), minlength=m) - corr


@pytest.mark.parametrize("m", [8, 33, 128, 256])
def test_toeplitz_deviance_matches_the_dense_factor(m):
    """Durbin–Levinson and Gohberg–Semencul give the Cholesky factor's −2 log L and the dense
    inverse's gradient to 1e-9 relative; where Σ is ill conditioned (quantization alone: its
    spectrum vanishes as ω⁴ at zero frequency) both are exact to about cond(Σ)·ε only."""
    rng = np.random.default_rng(m)
    for name, c in _catalogue(m).items():
        sigma = toeplitz(c)
        factor = cho_factor(sigma, lower=True)
        eig = np.linalg.eigvalsh(sigma)
        tol = max(1e-9, 10.0 * eig[-1] / eig[0] * np.finfo(float).eps)
        d = np.tril(factor[0]) @ rng.standard_normal(m) + 0.3 * math.sqrt(c[0])
        for ramp in (False, True):
            want, want_g = _dense(factor, d, ramp)
            g = np.empty(m)
            got = toeplitz_deviance(c, d, ramp, g)
            assert abs(got - want) <= tol * max(abs(want), 1.0), (name, ramp)
            assert np.max(np.abs(g - want_g)) <= tol * np.max(np.abs(want_g)), (name, ramp)
            assert toeplitz_deviance(c, d, ramp) == pytest.approx(got, rel=1e-14, abs=1e-12)


def test_toeplitz_gradient_matches_finite_differences():
    """The gradient along each lag's autocovariance against central differences."""
    m = 40
    rng = np.random.default_rng(3)
    for name, c in _catalogue(m).items():
        if name == "quantization":  # too ill conditioned for a difference quotient's step
            continue
        d = np.linalg.cholesky(toeplitz(c)) @ rng.standard_normal(m) + 0.2 * math.sqrt(c[0])
        for ramp in (False, True):
            g = np.empty(m)
            toeplitz_deviance(c, d, ramp, g)
            h = 1e-4 * np.linalg.eigvalsh(toeplitz(c))[0]  # well inside the positive cone
            fd = np.empty(m)
            for k in range(m):
                e = np.zeros(m)
                e[k] = h
                fd[k] = (toeplitz_deviance(c + e, d, ramp) - toeplitz_deviance(c - e, d, ramp)) / (2 * h)
            np.testing.assert_allclose(g, fd, rtol=0, atol=2e-6 * np.max(np.abs(fd)), err_msg=name)


def test_not_positive_definite_is_infinite():
    """A lag-1 correlation beyond −½ of an MA(1): no covariance; the recursion says so."""
    c = np.zeros(16)
    c[:2] = [1.0, -0.6]
    g = np.empty(16)
    assert toeplitz_deviance(c, np.ones(16), False, g) == math.inf
    assert toeplitz_deviance(c, np.ones(16), True) == math.inf


def test_series_fitted_side_by_side_as_each_alone():
    """Two records (their own rates and lengths, the same number of blocks) refitted in one
    Levenberg–Marquardt loop give each record's own fit, to the last bit."""
    rng = np.random.default_rng(11)
    masks = np.zeros((3, 8), bool)
    masks[:, 0] = True
    masks[1, 6] = True
    masks[2, [2, 3]] = True
    lo, hi = np.full(8, -150.0), np.full(8, 150.0)
    th0 = np.full((3, 8), -150.0)
    th0[:, 0] = math.log(1e-6)
    th0[1, 6] = math.log(1e-8)
    th0[2, [2, 3]] = [math.log(1e-6), math.log(5.0)]
    n, dts = np.array([256 * 16, 256 * 16 + 9]), np.array([0.01, 0.05])
    y = np.cumsum(1e-4 * rng.standard_normal((2, n.max())), axis=1) * 0.01 \
        + 1e-3 * rng.standard_normal((2, n.max()))
    both = BlockLikelihood(y, n, dts)
    th, dev = both.fit(np.concatenate([th0, th0]), np.concatenate([masks, masks]), lo, hi,
                       rows=np.repeat([0, 1], 3))
    for r in range(2):
        th_r, dev_r = BlockLikelihood(y[r], n[r], dts[r]).fit(th0, masks, lo, hi)
        np.testing.assert_array_equal(th[3 * r:3 * r + 3], th_r)
        np.testing.assert_array_equal(dev[3 * r:3 * r + 3], dev_r)
