"""The host noise floor (``diffgyro.noise``): the same order statistics as the pure-JAX
``fit._noise_floor`` and as ``numpy.nanmedian``'s definition, chunked on threads, and
the same numbers from both fit paths."""
from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro import Batch, Recording, noise
from diffgyro.fit import _noise_floor, fit


def nanmedian_definition(y, rate, mask):
    """1.4826 · MAD(Δy) / √2 per device and axis, by numpy.nanmedian."""
    y = y if rate is None else y - rate
    dy = np.diff(y, axis=1)
    pair = (mask[:, 1:] & mask[:, :-1])[..., None]
    dy = np.where(pair, dy, np.nan)
    with warnings.catch_warnings():  # a device without a valid pair: an all-NaN slice
        warnings.simplefilter("ignore", RuntimeWarning)
        med = np.nanmedian(dy, axis=1, keepdims=True)
        return 1.4826 * np.nanmedian(np.abs(dy - med), axis=1) / np.sqrt(2.0)


def catalogue():
    """(gyro, rate, mask) cases: odd and even counts, ties, constant axes, NaN samples,
    gaps, a device without one valid pair, heavy tails, with and without a rate."""
    rng = np.random.default_rng(11)
    cases = []
    for n in (2, 3, 4, 11, 1001):
        d = 4
        g = rng.normal(size=(d, n, 3)) * 1e-3 + rng.standard_cauchy(size=(d, n, 3)) * 1e-5
        g[:, : n // 3, 1] = 0.25  # ties
        g[1, :, 2] = -1.0  # a constant axis: every difference 0
        rate = rng.normal(size=(d, n, 3)) if n % 2 else None
        mask = rng.random((d, n)) > 0.3
        mask[0] = True
        mask[2] = False  # no valid pair
        if n > 3:
            g[3, 1, 0] = np.nan  # a NaN sample inside the mask: its differences are left out
        cases.append((g, rate, mask))
    q = np.round(rng.normal(size=(3, 500, 3)) * 2.0) / 2.0  # coarsely quantised: many ties
    cases.append((q, None, np.ones((3, 500), bool)))
    return cases


@pytest.mark.parametrize("case", range(len(catalogue())))
def test_equals_the_nanmedian_definition_and_the_jax_version(case):
    g, rate, mask = catalogue()[case]
    got = noise.noise_axes(g, rate, mask)
    np.testing.assert_allclose(got, nanmedian_definition(g, rate, mask), rtol=1e-15, atol=0,
                               equal_nan=True)
    y = jnp.asarray(g if rate is None else g - rate)
    jaxed = np.asarray(jax.vmap(_noise_floor)(y, jnp.asarray(mask)))
    np.testing.assert_allclose(got, jaxed, rtol=1e-15, atol=0, equal_nan=True)
    no_pair = ~(mask[:, 1:] & mask[:, :-1]).any(axis=1)
    assert np.isnan(got[no_pair]).all() and np.isfinite(got[~no_pair]).all()


def test_single_sample_devices_have_no_floor():
    assert np.isnan(noise.noise_axes(np.zeros((2, 1, 3)), None, np.ones((2, 1), bool))).all()


@pytest.mark.parametrize("threads", [1, 3])
def test_chunks_on_threads_give_the_one_call_answer(monkeypatch, threads):
    rng = np.random.default_rng(3)
    g, mask = rng.normal(size=(37, 64, 3)), rng.random((37, 64)) > 0.1
    monkeypatch.setattr(noise, "CHUNK_SAMPLES", 5 * 64)  # chunks of 5 devices, the last of 2
    floor, axes = noise.start(g, None, mask, threads=threads)()
    np.testing.assert_array_equal(axes, noise.noise_axes(g, None, mask))
    np.testing.assert_allclose(floor, np.sqrt(np.mean(axes**2, axis=1)), rtol=1e-15)
    empty_floor, empty_axes = noise.start(g[:0], None, mask[:0])()
    assert empty_floor.shape == (0,) and empty_axes.shape == (0, 3)


def test_both_fit_paths_report_the_same_floor():
    # the sums path computes the floor on the host, the direct path inside its compiled fit
    rng = np.random.default_rng(5)
    recs = []
    for k, n in enumerate((1500, 1700, 1600)):  # ragged: the shorter devices end masked
        t = np.arange(n) * 0.5
        temp = 25 + 10 * np.sin(t / 300 + k)
        gyro = 1e-3 * (temp[:, None] - 25) / 10 + 2e-4 * rng.normal(size=(n, 3))
        recs.append(Recording(t=t, gyro=gyro, temp=temp, device=f"u{k}"))
    batch = Batch.from_recordings(recs)
    mask = batch.mask.copy()
    mask[1, 200:450] = False  # and a gap
    batch = Batch(t=batch.t, gyro=batch.gyro, mask=mask, n_valid=mask.sum(1), temp=batch.temp,
                  devices=batch.devices)
    sums = fit("bias_poly(1)", batch, path="sums")
    direct = fit("bias_poly(1)", batch, path="direct")
    np.testing.assert_allclose(np.asarray(sums.noise_axes), np.asarray(direct.noise_axes),
                               rtol=1e-14, atol=0)
    np.testing.assert_allclose(np.asarray(sums.noise_floor), np.asarray(direct.noise_floor),
                               rtol=1e-14, atol=0)
    assert np.all(np.asarray(sums.noise_floor) > 1e-4)  # the simulated white noise, per axis
