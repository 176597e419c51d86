"""The host noise floor (``diffgyro._noise``): the same numbers as the pure-JAX
``_noise_jax.device_noise_floor`` and as its definition written with numpy's median and quantile,
chunked on threads, the same numbers from both fit paths, and the simulated σ on
plain and quantised output."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro import Batch, Recording
from diffgyro import _noise as noise
from diffgyro._noise_jax import device_noise_floor
from diffgyro.fit import fit

#: The JAX floor of every device, compiled whole as the fit runs it (vmapped op by op it
#: compiled some sixty small programs per shape).
jax_floor = jax.jit(jax.vmap(device_noise_floor))


def exact(d):
    """The floor of one row of valid differences, written out with numpy's median and
    quantile: the truncation-corrected RMS of |Δy − median| inside 4 · 1.4826 · MAD, or,
    when fewer than 90 % are inside (the MAD collapsed on quantised output), of all but
    the largest 0.5 %, over √2."""
    dev = np.abs(d - np.median(d))
    inside = dev <= 4 * 1.4826 * np.median(dev)
    ms = np.mean(dev[inside] ** 2) / noise.TRUNC4
    if inside.sum() < 0.9 * dev.size:  # the MAD collapsed (coarse quantisation)
        ms = np.mean(dev[dev <= np.quantile(dev, 0.995)] ** 2)
        if not ms > 0:
            ms = np.mean(dev**2)
    return np.sqrt(ms / 2)


def subsampled(d):
    """The floor of a row of more than SUBSAMPLE valid differences, written out with
    numpy's median and variance: the variance of the differences inside the window placed
    by the median and MAD of the evenly spread subsample; the exact floor where the
    subsample cannot place it (fewer than 95 % inside, a quarter of it tied at its
    median, an infinite difference)."""
    k = noise.SUBSAMPLE
    sub = d[(2 * np.arange(k) + 1) * d.size // (2 * k)]
    med = np.median(sub)
    dev = np.abs(sub - med)
    half = 4 * 1.4826 * np.median(dev)
    inside = (d - med) ** 2 <= half**2
    if inside.sum() < 0.95 * d.size or (dev == 0).sum() >= 0.25 * k or np.isinf(d).any():
        return exact(d)
    return np.sqrt(np.var(d[inside]) / noise.TRUNC4 / 2)


def definition(y, rate, mask, floor=None):
    """The floor per device and axis (``floor`` of each row's valid differences; by
    default the statistic :mod:`diffgyro._noise` documents)."""
    y = y if rate is None else y - rate
    out = np.full((y.shape[0], 3), np.nan)
    for i in range(y.shape[0]):
        pair = mask[i, 1:] & mask[i, :-1]
        for k in range(3):
            d = np.diff(y[i, :, k])[pair]
            d = d[~np.isnan(d)]
            if d.size:
                out[i, k] = (floor or (subsampled if d.size > noise.SUBSAMPLE else exact))(d)
    return out


def catalogue():
    """(gyro, rate, mask) cases: odd and even counts, ties, constant axes, NaN samples,
    gaps, a device without one valid pair, heavy tails, with and without a rate."""
    rng = np.random.default_rng(11)
    cases = []
    for n in (2, 3, 4, 11, 1001, 2500):  # 2500: the window placed from a subsample
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
    coarse = np.round(rng.normal(size=(3, 500, 3)) / 3.0) * 3.0  # most differences 0
    cases.append((coarse, None, rng.random((3, 500)) > 0.1))
    return cases


@pytest.mark.parametrize("case", range(len(catalogue())))
def test_equals_the_definition_and_the_jax_version(case):
    g, rate, mask = catalogue()[case]
    got = noise.noise_axes(g, rate, mask)
    np.testing.assert_allclose(got, definition(g, rate, mask), rtol=1e-13, atol=0,
                               equal_nan=True)
    np.testing.assert_allclose(noise.noise_axes(g, rate, mask, compiled=True), got, rtol=1e-13,
                               atol=0, equal_nan=True)  # numba's passes, numpy's numbers
    y = jnp.asarray(g if rate is None else g - rate)
    jaxed = np.asarray(jax_floor(y, jnp.asarray(mask)))
    np.testing.assert_allclose(got, jaxed, rtol=1e-13, atol=0, equal_nan=True)
    no_pair = ~(mask[:, 1:] & mask[:, :-1]).any(axis=1)
    assert np.isnan(got[no_pair]).all() and np.isfinite(got[~no_pair]).all()


@pytest.mark.parametrize("n", [2, 3, 4, 1000, 1001, 3000])
def test_every_pair_valid_equals_the_definition(n):
    # every pair valid (fit's usual case, selected without the masked path's padding):
    # odd and even counts, ties, a constant axis, heavy tails, an axis whose MAD
    # collapses, NaN samples of either sign (those blocks go again through the masked
    # path, which leaves the NaN differences out) and ±0
    rng = np.random.default_rng(n)
    g = rng.normal(size=(6, n, 3)) * 1e-3 + rng.standard_cauchy(size=(6, n, 3)) * 1e-5
    g[0, : n // 3, 1] = 0.25
    g[1, :, 2] = -1.0
    g[2, :, 0] = np.cumsum(np.where(rng.random(n) < 0.15, rng.normal(size=n), 0.0))  # most Δ 0
    g[3, :, 1] = np.where(rng.random(n) < 0.5, 0.0, -0.0)
    mask = np.ones((6, n), bool)
    want = definition(g, None, mask)
    np.testing.assert_allclose(noise.noise_axes(g, None, mask), want, rtol=1e-13, atol=0)
    g[4, n // 2, 0] = np.nan
    g[5, n - 1, 2] = -np.nan
    g[2, 0, 0] = np.inf * 0.0  # the x86 default NaN, sign bit set
    got = noise.noise_axes(g, None, mask)
    np.testing.assert_allclose(got, definition(g, None, mask), rtol=1e-13, atol=0,
                               equal_nan=True)
    np.testing.assert_allclose(noise.noise_axes(g, None, mask, compiled=True), got, rtol=1e-13,
                               atol=0, equal_nan=True)
    jaxed = np.asarray(jax_floor(jnp.asarray(g), jnp.asarray(mask)))
    np.testing.assert_allclose(got, jaxed, rtol=1e-13, atol=0, equal_nan=True)
    g[4, n // 2, 0] = g[5, n - 1, 2] = 0.0
    g[2, n // 2, 0] = np.nan  # the only NaN now on the axis whose MAD collapsed
    np.testing.assert_allclose(noise.noise_axes(g, None, mask), definition(g, None, mask),
                               rtol=1e-13, atol=0)


@pytest.mark.parametrize("lsb", [0.0, 0.3, 0.7, 1.0, 1.5, 3.0])
def test_the_subsample_keeps_the_floor_of_quantised_output(lsb):
    # white noise quantised from finely to coarser than σ (the MAD locks to whole LSBs, then
    # collapses): within 1 % of the exact statistic, exactly it where the subsample is tied
    rng = np.random.default_rng(17)
    y = 0.01 * np.arange(6000)[None, :, None] + rng.normal(size=(4, 6000, 3))
    if lsb:
        y = np.round(y / lsb) * lsb
    mask = np.ones((4, 6000), bool)
    got = noise.noise_axes(y, None, mask, compiled=True)
    want = definition(y, None, mask, floor=exact)
    np.testing.assert_allclose(got, want, rtol=0.01)
    if lsb >= 1.5:  # a quarter of the subsample or more at its median
        np.testing.assert_allclose(got, want, rtol=1e-13)


def test_the_compiled_window_is_numpys_order_statistics():
    # the subsample's median and MAD selected without a branch per value are numpy's
    # partition's values: noise, output quantised to ties, heavy tails, zeros, infinities
    from diffgyro import _noise_passes

    rng = np.random.default_rng(29)
    k = noise.SUBSAMPLE
    sub = np.concatenate([rng.normal(size=(8, k)), np.round(rng.normal(size=(8, k)) / 2.0) * 2.0,
                          rng.standard_cauchy(size=(8, k)), np.zeros((2, k)),
                          rng.integers(-3, 4, size=(4, k)).astype(float)])
    sub[-1, :10] = np.inf
    sub[-2, -20:] = -np.inf
    centre, half_width, ties = _noise_passes.place(sub.copy())
    want = noise._middle(sub.copy(), k)
    dev = np.abs(sub - want[:, None])
    np.testing.assert_array_equal(centre, want)
    np.testing.assert_array_equal(ties, np.count_nonzero(dev == 0, axis=1))
    np.testing.assert_array_equal(half_width, 4.0 * 1.4826 * noise._middle(dev, k, bits=True))


def test_a_device_has_one_floor_alone_or_in_a_ragged_batch():
    # the shorter device of a batch ends masked: its valid differences are packed and get
    # the window of the same subsample as when it is fitted alone (fit and diagnose agree
    # whatever the batch); a gap or a NaN sample leaves its differences out of the ranks
    rng = np.random.default_rng(23)
    short = rng.normal(size=(1, 3000, 3)) + 0.1 * rng.standard_cauchy(size=(1, 3000, 3))
    alone = noise.noise_axes(short, None, np.ones((1, 3000), bool), compiled=True)
    g = np.concatenate([np.pad(short, ((0, 0), (0, 2000), (0, 0))),
                        rng.normal(size=(1, 5000, 3))])
    mask = np.ones((2, 5000), bool)
    mask[0, 3000:] = False
    np.testing.assert_array_equal(noise.noise_axes(g, None, mask, compiled=True)[:1], alone)
    mask[1, 1000:1400] = False
    g[1, 2500, 1] = np.nan
    g[1, 4000, 2] = np.inf  # its two differences are valid, infinite: the exact statistic
    got = noise.noise_axes(g, None, mask, compiled=True)
    np.testing.assert_allclose(got, definition(g, None, mask), rtol=1e-13)
    np.testing.assert_allclose(noise.noise_axes(g, None, mask, compiled=False), got, rtol=1e-13)
    assert np.isfinite(got).all()


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
    # long rows: the batch, not each chunk, chooses the compiled passes
    g = rng.normal(size=(7, 1100, 3)) + 0.1 * rng.standard_cauchy(size=(7, 1100, 3))
    mask = np.ones((7, 1100), bool)
    monkeypatch.setattr(noise, "CHUNK_SAMPLES", 2 * 1100)
    monkeypatch.setattr(noise, "COMPILED_SAMPLES", 7 * 1100)
    _, axes = noise.start(g, None, mask, threads=threads)()
    np.testing.assert_array_equal(axes, noise.noise_axes(g, None, mask, compiled=True))
    np.testing.assert_array_equal(axes, noise.noise_axes(g, None, mask))


def test_the_floor_waits_for_its_work_and_claims_each_chunk_once(monkeypatch):
    from concurrent.futures import Future

    rng = np.random.default_rng(4)
    g, mask = rng.normal(size=(23, 64, 3)), np.ones((23, 64), bool)
    monkeypatch.setattr(noise, "CHUNK_SAMPLES", 4 * 64)  # 6 chunks, the last of 3 devices
    real, chunks = noise.noise_axes, []
    monkeypatch.setattr(noise, "noise_axes", lambda g, *a: chunks.append(len(g)) or real(g, *a))
    first = Future()
    result = noise.start(g, None, mask, threads=2, after=first)
    assert chunks == []  # nothing before the work it waits for
    first.set_result(None)
    floor, axes = result()  # one worker and the caller claim the chunks
    assert sorted(chunks) == [3, 4, 4, 4, 4, 4]
    np.testing.assert_array_equal(axes, real(g, None, mask))


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
                               rtol=1e-13, atol=0)
    np.testing.assert_allclose(np.asarray(sums.noise_floor), np.asarray(direct.noise_floor),
                               rtol=1e-13, atol=0)
    np.testing.assert_allclose(np.asarray(sums.noise_floor), 2e-4, rtol=0.08)  # the simulated σ


@pytest.mark.parametrize("lsb", [0.0, 0.3, 0.9, 1.5])
def test_the_white_noise_sigma_on_quantised_output(lsb):
    # Quantised to about its σ, the output's differences take a few values and their
    # MAD locks to whole LSBs (6-9 % low at 0.3-0.9 σ per LSB, 44 % high at 1.5);
    # the floor is the noise of what is recorded, σ² + LSB²/12 (Sheppard).
    rng = np.random.default_rng(7)
    sigma = 1.0
    y = 0.01 * np.arange(40_000)[None, :, None] + sigma * rng.normal(size=(2, 40_000, 3))
    if lsb:
        y = np.round(y / lsb) * lsb
    got = noise.noise_axes(y, None, np.ones((2, 40_000), bool))
    np.testing.assert_allclose(got, np.sqrt(sigma**2 + lsb**2 / 12), rtol=0.025)
