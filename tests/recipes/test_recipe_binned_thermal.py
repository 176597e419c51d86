"""binned-thermal: the published binning and line on known truth; where it falls short."""

from __future__ import annotations

import jax
import numpy as np
import pytest

from diffgyro.data import Batch, Recording
from diffgyro.errors import DataError
from diffgyro.recipes import binned_thermal

OFFSET = np.array([-0.2426, 0.0873, -0.0310])     # rad/s (−13.9 °/s, as in the patent's example)
SLOPE = np.array([2.1e-3, -1.4e-3, 0.9e-3])       # rad/s per °C


def warming(fs=10.0, hours=2.0):
    """Cold start, self-heating (log-like), then a lamp: binned-thermal's temperature history."""
    t = np.arange(0.0, hours * 3600.0, 1.0 / fs)
    temp = 15.0 + 14.0 * (1 - np.exp(-t / 900.0))
    lamp = t > 0.55 * t[-1]
    temp = temp + np.where(lamp, 12.0 * (1 - np.exp(-(t - 0.55 * t[-1]) / 600.0)), 0.0)
    return t, temp


def static_device(curvature=0.0, gradient=0.0, noise=1e-3, seed=0):
    t, temp = warming()
    rng = np.random.default_rng(seed)
    dtemp = np.gradient(temp, t)
    tc = temp - 25.0
    bias = (OFFSET + temp[:, None] * SLOPE + curvature * tc[:, None] ** 2 * np.array([1.0, -0.7, 0.5])
            + gradient * dtemp[:, None] * np.array([1.0, 0.6, -0.8]))
    gyro = bias + noise * rng.normal(size=bias.shape)
    return t, temp, gyro, bias


def test_recovers_the_line_and_accepts_it():
    t, temp, gyro, _ = static_device()
    res = binned_thermal(gyro, temp, edge="centre")
    np.testing.assert_allclose(res.slope, SLOPE, rtol=0.02)
    np.testing.assert_allclose(res.offset, OFFSET, atol=2e-3)
    assert np.all(np.abs(res.r) > 0.999) and res.accepted.all()
    # even sub-sampling: every bin carries the same count (the smallest full bin's)
    assert np.all(res.bin_count == res.per_bin)
    assert res.per_bin >= 10
    # the bins are 0.1 °C wide and cover the whole range
    np.testing.assert_allclose(np.diff(res.bin_temp).min(), 0.1, atol=1e-9)
    assert res.bin_temp[0] <= temp.min() + 0.1 and res.bin_temp[-1] >= temp.max() - 0.2
    # compensation leaves noise only
    assert np.std(res.compensate(gyro, temp)) < 1.1e-3


def test_edge_choice_shifts_the_offset_by_half_a_bin_times_the_slope():
    t, temp, gyro, _ = static_device()
    low = binned_thermal(gyro, temp, edge="low")
    centre = binned_thermal(gyro, temp, edge="centre")
    high = binned_thermal(gyro, temp, edge="high")
    np.testing.assert_allclose(low.slope, centre.slope, rtol=1e-12)
    np.testing.assert_allclose(low.offset - centre.offset, 0.05 * centre.slope, rtol=1e-9)
    np.testing.assert_allclose(centre.offset - high.offset, 0.05 * centre.slope, rtol=1e-9)


def test_rejects_a_poor_line_and_too_small_a_range():
    t, temp, gyro, _ = static_device(noise=0.2)  # noise swamps the slope: |r| < 0.999
    res = binned_thermal(gyro, temp)
    assert not res.accepted.all()
    with pytest.raises(DataError, match="temperature bins"):
        binned_thermal(gyro[:50], 25.0 + 0.01 * np.arange(50) / 50)


def test_curvature_and_gradient_break_the_line_and_the_toolkit_repairs_it():
    """Bias curved in T (2e-5 rad/s/°C²) and following dT/dt (0.05 rad/s per °C/s): the
    recipe's line leaves a systematic error (and its |r| test rejects it);
    bias_poly(2)+gradient removes it."""
    from diffgyro.fit import fit

    t, temp, gyro, bias = static_device(curvature=2e-5, gradient=0.05, noise=1e-3, seed=1)
    res = binned_thermal(gyro, temp)
    assert not res.accepted.any()       # |r| ≈ 0.997-0.998: the published test notices
    recipe_err = res.bias(temp) - bias
    rec = Recording(t=t, gyro=gyro, temp=temp)
    out = fit("bias_poly(2)+gradient", rec)
    assert out.status_name(0) == "ok"
    batch = Batch.from_recordings([rec])
    sig = out.signals(batch)
    comp = np.asarray(jax.vmap(out.model.compensate)(out.params, sig))[0, : rec.n]
    toolkit_err = (gyro - comp) - bias          # the toolkit's bias estimate minus the truth
    r_recipe = np.sqrt(np.mean(recipe_err**2))
    r_toolkit = np.sqrt(np.mean(toolkit_err**2))
    # measured: recipe 1.07e-3 rad/s systematic error, toolkit 1.9e-5 rad/s (≈ 55× better)
    assert r_recipe > 8e-4
    assert r_toolkit < 0.05 * r_recipe
