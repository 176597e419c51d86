"""The block means' likelihood that chooses a noise model's slow part: its autocovariances
against the covariance of the block-mean differences formed sample by sample, and the
likelihood-ratio statistic of a walk on records without one at its nominal level."""

from __future__ import annotations

import math

import numpy as np
import pytest

from diffgyro.internal import BlockLikelihood, gm_acov, short_acov

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
