"""The one-pass sums path of linear fits equals the direct (design-matrix) path.

Every number fit() reports — coefficients, rms, held-out rms and per-fold
errors, covariance, σ, noise floor, status, flags, normalisation — must agree
to 1e-9 relative, on plans that exercise every kind of column (temperature
polynomials, scale factor, misalignment, g-sensitivity, gradient, temp_diff),
on devices of different lengths, masks with holes, odd block/fold counts and
batches split over many compiled groups.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import registered

import diffgyro._fit_sums as fs
from diffgyro import Batch, Recording
from diffgyro.data import valid_samples
from diffgyro.effects import AbstractEffect
from diffgyro.fit import fit
from diffgyro.internal import per_axis
from diffgyro.simulate import simulate

FIELDS = ("rms", "heldout_rms", "fold_mse", "cov", "sigma", "noise_floor", "noise_axes",
          "n_samples", "temp_range")
EXACT = ("status", "range_flags", "collinear", "steps")


def assert_same(direct, sums, rtol=1e-9):
    assert direct.devices == sums.devices
    b1, b2 = np.asarray(direct.params.beta), np.asarray(sums.params.beta)
    scale = np.max(np.abs(b1), axis=-1, keepdims=True)  # per device and axis
    assert np.max(np.abs(b1 - b2) / scale) < rtol
    for name in FIELDS:
        a, b = getattr(direct, name), getattr(sums, name)
        if a is None:
            assert b is None, name
            continue
        a, b = np.asarray(a), np.asarray(b)
        assert a.shape == b.shape, name
        if name == "cov":  # relative to each parameter's own variance
            d = np.sqrt(np.abs(np.einsum("...ii->...i", a)))
            a, b = a / (d[..., :, None] * d[..., None, :]), b / (d[..., :, None] * d[..., None, :])
            np.testing.assert_allclose(b, a, rtol=0, atol=rtol, err_msg=name)
        else:
            np.testing.assert_allclose(b, a, rtol=rtol, atol=0, err_msg=name)
    for name in EXACT:
        np.testing.assert_array_equal(np.asarray(getattr(direct, name)),
                                      np.asarray(getattr(sums, name)), err_msg=name)
    np.testing.assert_allclose(np.asarray(sums.norm.centre), np.asarray(direct.norm.centre),
                               rtol=1e-14)
    np.testing.assert_allclose(np.asarray(sums.norm.scale), np.asarray(direct.norm.scale),
                               rtol=1e-14)


CASES = [
    ("thermal", "bias_poly(3)", dict(duration=3600.0, sample_rate=1.0)),
    ("rate_table", "bias_poly(2)+scale_poly(2)+gradient+temp_diff", dict(sample_rate=1.0)),
    ("six_face", "bias_poly(0)+g_sens+scale_poly(0)+misalignment", dict(sample_rate=2.0)),
]


@pytest.mark.parametrize("plan,spec,kw", CASES, ids=[c[0] for c in CASES])
def test_sums_equals_direct(plan, spec, kw):
    batch, truth = simulate(plan, 3, effects=spec, seed=3, **kw)
    direct = fit(spec, batch, path="direct")
    sums = fit(spec, batch, path="sums")
    auto = fit(spec, batch)
    assert set(np.asarray(direct.status)) == {0}
    assert_same(direct, sums)
    np.testing.assert_array_equal(np.asarray(auto.params.beta), np.asarray(sums.params.beta))


def _thermal_recordings(lengths, seed=0):
    rng = np.random.default_rng(seed)
    recs = []
    for k, n in enumerate(lengths):
        t = np.arange(n) * 0.5
        temp = 25 + 12 * np.sin(t / 400 + k) + 0.05 * rng.normal(size=n)
        ts = (temp - 25) / 12
        beta = rng.normal(size=(3, 3)) * 1e-3
        gyro = np.stack([ts**j for j in range(3)], 1) @ beta.T + 2e-4 * rng.normal(size=(n, 3))
        recs.append(Recording(t=t, gyro=gyro, temp=temp, device=f"u{k}"))
    return recs


@pytest.mark.parametrize("opts", [{}, {"n_blocks": 7, "n_folds": 3}, {"n_blocks": 20}])
def test_uneven_lengths_odd_blocks(opts):
    # a device shorter than the blocks' chunk (c = 1) alongside long ones, lengths not
    # multiples of any chunk, and block counts that do not divide into the folds
    batch = Batch.from_recordings(_thermal_recordings([2500, 1999, 1003, 150]))
    spec = "bias_poly(2)"
    assert_same(fit(spec, batch, path="direct", **opts), fit(spec, batch, path="sums", **opts))


def test_mask_with_holes():
    batch = Batch.from_recordings(_thermal_recordings([3000, 2800, 2900], seed=1))
    mask = batch.mask.copy()
    mask[0, 100:400] = False  # a gap
    mask[1, ::7] = False  # dropped samples
    mask[2, :50] = False  # late start
    holes = Batch(t=batch.t, gyro=batch.gyro, mask=mask, n_valid=mask.sum(1), temp=batch.temp,
                  devices=batch.devices)
    spec = "bias_poly(3)"
    assert_same(fit(spec, holes, path="direct"), fit(spec, holes, path="sums"))


def test_many_groups(monkeypatch):
    # tiny groups: many compiled calls, the last one padded with repeats
    monkeypatch.setattr(fs.groups, "GROUP_SAMPLES", 4096)
    monkeypatch.setattr(fs.groups, "FUSED_GROUP_FACTOR", 1)
    batch = Batch.from_recordings(_thermal_recordings([1800] * 11, seed=2))
    assert fs.group_size(batch.n_devices, batch.length) == 2
    spec = "bias_poly(1)"
    assert_same(fit(spec, batch, path="direct"), fit(spec, batch, path="sums"))


def test_noise_floor_off_and_given_norm():
    batch = Batch.from_recordings(_thermal_recordings([2000, 2100], seed=4))
    from diffgyro.signals import TempNorm

    norm = TempNorm(centre=jnp.asarray(24.0), scale=jnp.asarray(10.0))
    full = fit("bias_poly(2)", batch, norm=norm)
    quick = fit("bias_poly(2)", batch, norm=norm, noise_floor=False)
    assert np.all(np.isnan(np.asarray(quick.noise_floor)))
    np.testing.assert_array_equal(np.asarray(quick.params.beta), np.asarray(full.params.beta))
    np.testing.assert_allclose(np.asarray(full.norm.centre), 24.0)
    assert_same(fit("bias_poly(2)", batch, norm=norm, path="direct"), full)


class _RunningMeanTemp(AbstractEffect):
    """A test-only linear term whose column reads earlier samples (not pointwise)."""

    name = "test_running_mean_temp"
    description = "running mean of temperature (test only)"
    needs = frozenset({"temp"})

    def param_names(self):
        return ("m",)

    def columns(self, sig, theta):
        return per_axis(jnp.cumsum(sig.temp_s) / jnp.arange(1, sig.temp_s.shape[0] + 1))


@pytest.fixture
def running_mean_term():
    """The test's own term in the registry while it runs (registered at import, it would be
    in every test file's registry read after this one)."""
    with registered(_RunningMeanTemp):
        yield


def test_columns_that_read_other_samples(running_mean_term):
    # such a column is formed once on the whole recording and its rows are gathered
    batch = Batch.from_recordings(_thermal_recordings([1500, 1600], seed=5))
    spec = "bias_poly(1)+test_running_mean_temp"
    present = frozenset(batch.signals)
    assert not fs.layout_of(fit.__globals__["ErrorModel"].from_spec(spec), present)[0].pointwise
    assert_same(fit(spec, batch, path="direct"), fit(spec, batch))
    with pytest.raises(ValueError, match="unknown fit path"):
        fit("bias_poly(1)", batch, path="fast")
    with pytest.raises(ValueError, match="solver"):
        fit("bias_poly(1)", batch, path="sums", solver="lm")


@pytest.fixture(scope="module")
def lagged():
    """Four devices, one hour at 0.5 Hz: about twenty lag time constants (τ 130-180 s),
    which pins each τ to within 1 % (the check allows 5 %)."""
    batch, truth = simulate("thermal", 4, effects="bias_poly(1)+thermal_lag", seed=11,
                            duration=3600.0, sample_rate=0.5,
                            noise={"rrw": 0.0, "bias_instability": 0.0, "quantum": 0.0})
    return batch, truth


def test_separable_sums_equals_direct(lagged):
    # variable projection on sums (Newton on the time constant) against optimistix LM on
    # the design: the same optimum, the sums path at least as low a cost
    batch, truth = lagged
    spec = "bias_poly(1)+thermal_lag"
    # two folds: the held-out RMS is compared all the same, and the direct path's LM runs
    # once per fold (five folds doubled its run time)
    direct = fit(spec, batch, path="direct", n_folds=2)
    sums = fit(spec, batch, path="sums", n_folds=2)
    ok = (np.asarray(direct.status) == 0) & (np.asarray(sums.status) == 0)
    assert ok.sum() >= 3
    th_d, th_s = np.asarray(direct.params.theta)[ok], np.asarray(sums.params.theta)[ok]
    assert np.max(np.abs(th_d - th_s)) < 1e-6
    b1, b2 = np.asarray(direct.params.beta)[ok], np.asarray(sums.params.beta)[ok]
    assert np.max(np.abs(b1 - b2) / np.max(np.abs(b1), axis=-1, keepdims=True)) < 1e-6
    assert np.all(np.asarray(sums.rms)[ok] <= np.asarray(direct.rms)[ok] * (1 + 1e-9))
    for name in ("heldout_rms", "sigma", "noise_floor"):
        np.testing.assert_allclose(np.asarray(getattr(sums, name))[ok],
                                   np.asarray(getattr(direct, name))[ok], rtol=1e-6)
    d = np.sqrt(np.einsum("...ii->...i", np.asarray(direct.cov)[ok]))
    np.testing.assert_allclose(np.asarray(sums.cov)[ok] / (d[..., :, None] * d[..., None, :]),
                               np.asarray(direct.cov)[ok] / (d[..., :, None] * d[..., None, :]),
                               atol=1e-5)
    assert np.all(np.asarray(sums.steps)[ok] <= 12)  # Newton: a handful of steps
    # the true time constant is found
    tau_true = np.exp(np.asarray(truth.params.theta)[:, 0])[ok]
    tau = np.exp(th_s[:, 0])
    assert np.max(np.abs(tau - tau_true) / tau_true) < 0.05


@pytest.mark.parametrize("order", [1, 2, 3])
def test_thermal_lag_jet_equals_forward_mode(order):
    # the one-recursion jet of the lag against forward mode through the lag's scan, on
    # irregular sampling, inside and beyond the clip of log τ
    from diffgyro.effects import AbstractEffect, ThermalLag
    from diffgyro.signals import make_signals

    rng = np.random.default_rng(order)
    n = 400
    t = np.cumsum(rng.uniform(0.2, 3.0, n))
    temp = 20.0 + np.cumsum(rng.normal(size=n))
    # (one compiled program: op by op, make_signals compiled some seventy small ones)
    sig = eqx.filter_jit(make_signals)(jnp.asarray(t), jnp.zeros((n, 3)), jnp.ones(n, bool),
                                       temp=jnp.asarray(temp))
    term = ThermalLag(order=order)

    @jax.jit  # one program per order for the five time constants
    def jets(th):
        return (term.columns_jet(sig, th), AbstractEffect.columns_jet(term, sig, th),
                term.columns(sig, th))

    for log_tau in (np.log(40.0), np.log(0.7), 9.0, 20.0, -10.0):
        got, ref, cols = jets(jnp.asarray([log_tau]))
        np.testing.assert_allclose(np.asarray(got[0]), np.asarray(cols), rtol=0, atol=1e-13)
        for g, r in zip(got, ref):
            assert g.shape == r.shape
            scale = max(float(jnp.max(jnp.abs(r))), 1e-300)
            assert float(jnp.max(jnp.abs(g - r))) <= 1e-12 * scale + 1e-15


# the sums path on a term without a jet of its own (warmup: forward mode) against LM on
# the design: tests/test_fit.py::test_nonlinear_start_far_away_is_flagged_alone


def test_layout_shares_products():
    from diffgyro.model import ErrorModel

    present = frozenset({"t", "gyro", "temp", "rate"})
    lay, need = fs.layout_of(ErrorModel.from_spec("bias_poly(3)"), present)
    # Hankel structure: T^0..T^6 once for all axes (T^0 is the sample count)
    assert len(lay.xx) == 6 and all(lay.shared)
    assert need == {"temp"}  # no time, no rate, no dT/dt
    lay, need = fs.layout_of(ErrorModel.from_spec("bias_poly(1)+scale_poly(1)+gradient"), present)
    assert lay.shared == (True, True, False, False, True)
    assert {"temp", "rate", "t", "dt"} <= need


@pytest.mark.parametrize("k", range(1, 12))
def test_masked_median_equals_nanmedian(k):
    # the integer-sort median gives nanmedian's number exactly, signed zeros, infinities,
    # subnormals and NaN included (the noise floor's order statistics: tests/test_noise.py)
    from diffgyro.internal import masked_median

    masked_median = jax.jit(masked_median)  # as the noise floor runs it: one program a length
    x = np.array([-3.0, -0.0, 0.0, 2.0, -1e300, np.inf, -np.inf, np.nan, 5e-324, -5e-324, 7.0])
    got = float(masked_median(jnp.asarray(x[:k]), jnp.ones(k, bool)))
    want = float(np.nanmedian(x[:k]))
    assert got == want or (np.isnan(got) and np.isnan(want))
    valid = np.arange(k) % 2 == 0
    got = float(masked_median(jnp.asarray(x[:k]), jnp.asarray(valid)))
    want = float(np.nanmedian(np.where(valid, x[:k], np.nan)))
    assert got == want or (np.isnan(got) and np.isnan(want))


def test_reference_rate_is_subtracted_for_bias_only_models():
    # the fit is of gyro − rate even when no column reads the rate
    rng = np.random.default_rng(7)
    recs = []
    for k in range(2):
        n = 2400
        t = np.arange(n) * 0.5
        temp = 25 + 10 * np.sin(t / 300 + k)
        rate = np.repeat(rng.choice([-1.0, 0.0, 1.0], size=(n // 100, 3)), 100, axis=0)
        bias = 1e-3 * (1 + 0.5 * (temp - 25) / 10)
        gyro = rate + bias[:, None] + 1e-5 * rng.normal(size=(n, 3))
        recs.append(Recording(t=t, gyro=gyro, temp=temp, rate=rate, device=f"r{k}"))
    batch = Batch.from_recordings(recs)
    sums = fit("bias_poly(1)", batch, path="sums")
    assert_same(fit("bias_poly(1)", batch, path="direct"), sums)
    assert float(np.max(np.asarray(sums.rms))) < 1e-4


def _products(src, mask):
    return [jnp.where(mask, src[:, 0], 0.0), jnp.where(mask, src[:, 1] * src[:, 2], 0.0),
            mask.astype(src.dtype)]


@pytest.mark.parametrize("n,n_blocks", [(1000, 100), (1024, 100), (97, 7), (64, 100), (10, 3)])
def test_block_windows_equal_chunked_sums(n, n_blocks):
    """The window sums of devices whose valid samples come first (block starts from the
    host) equal the chunked sums that handle any mask, for every length down to
    fewer samples than blocks and windows clamped at the recording's end."""
    rng = np.random.default_rng(n)
    lengths = np.unique(np.clip([n, n - 1, n - n_blocks + 1, (3 * n) // 4, 2, 0], 0, n))
    x = jnp.asarray(rng.normal(size=(n, 3)))
    # compiled as in the fit's programs: the windows once per (n, n_blocks), the chunked
    # sums once per chunk size
    sums = jax.jit(fs.fold_sums, static_argnums=(0, 4, 5, 6, 7))
    windows = jax.jit(lambda x, mask, nv, pos: fs.fold_sums(_products, x, mask, nv, n_blocks,
                                                            5, 1, pos))
    for nv in lengths:
        mask = jnp.arange(n) < nv
        pos = jnp.asarray(fs.block_starts([nv], n_blocks)[0])
        c = fs.chunk_size(max(int(nv), 1), n_blocks, n)
        t1, f1 = sums(_products, x, mask, jnp.asarray(nv), n_blocks, 5, c)
        t2, f2 = windows(x, mask, jnp.asarray(nv), pos)
        np.testing.assert_allclose(np.asarray(t2), np.asarray(t1), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(np.asarray(f2), np.asarray(f1), rtol=1e-12, atol=1e-12)
        assert float(t2[-1]) == nv and float(jnp.sum(f2[:, -1])) == nv
        if nv == n and n % n_blocks == 0:  # whole blocks: a reshape, no windows, no mask
            t3, f3 = sums(_products, x, mask, jnp.asarray(nv), n_blocks, 5, c, fs.ALIGNED)
            np.testing.assert_allclose(np.asarray(t3), np.asarray(t1), rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(np.asarray(f3), np.asarray(f1), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("n", [0, 7, 8, 64, 100])
def test_valid_counts(n):
    """Counts and prefix flags equal the direct ones for prefix masks, masks with holes,
    empty and full masks, lengths that are and are not whole 64-bit words."""
    rng = np.random.default_rng(n)
    d = 12
    nv = rng.integers(0, n + 1, size=d)
    nv[:2] = (0, n)
    mask = np.arange(n)[None, :] < nv[:, None]
    holes = rng.random((d, n)) < 0.2
    mask[d // 2:] &= ~holes[d // 2:]
    spare = np.zeros(d * n + 1, bool)  # a copy one byte off an 8-byte boundary
    offset = spare[1:].reshape(d, n)
    offset[...] = mask
    for m in (mask, np.asfortranarray(mask), mask[:, ::-1], offset):
        count, prefix = fs.valid_counts(m)
        want = np.count_nonzero(m, axis=1)
        np.testing.assert_array_equal(count, want)
        np.testing.assert_array_equal(valid_samples(m), m.sum(axis=1))
        assert valid_samples(m).dtype == np.int64
        np.testing.assert_array_equal(prefix, [np.array_equal(r, np.arange(n) < k)
                                               for r, k in zip(m, want)])


def test_group_results_pack_into_one_array_and_back_exactly():
    from diffgyro.internal import pack, unpack_results

    rng = np.random.default_rng(0)
    out = {"beta": rng.normal(size=(4, 3, 2)), "status": np.array([0, 3, 7, 2**20], np.int32),
           "flags": rng.random((4, 2)) > 0.5, "rms": rng.normal(size=4)}
    packed, spec = jax.jit(lambda o: pack(o, jnp.float64))(out)
    assert packed.shape == (4, 6 + 1 + 2 + 1)
    back = unpack_results(np.asarray(packed), spec)
    for k, v in out.items():
        assert back[k].dtype == v.dtype and back[k].shape == v.shape
        np.testing.assert_array_equal(back[k], v)


def test_models_with_time_constants_run_in_small_groups(monkeypatch):
    """Batched Newton loops run in lockstep (a group takes as many steps as its slowest
    device), so a model with time constants gets smaller groups than a linear one."""
    sizes = {}

    class Seen(Exception):
        pass

    def spy(model, layout, opts, c, prefix, t, gyro, *rest):
        sizes[model.n_nonlinear > 0] = gyro.shape[0]
        raise Seen  # the group size is all this test needs: nothing is compiled

    for program in (fs.group_fused, fs.group_compact, fs.group_small):
        monkeypatch.setattr(program, "eval_shape", spy)
    n, d = 10_000, 40
    rng = np.random.default_rng(0)
    temp = np.linspace(-10.0, 50.0, n)[None].repeat(d, 0)
    batch = Batch(t=np.arange(n, dtype=float)[None].repeat(d, 0),
                  gyro=1e-4 * rng.normal(size=(d, n, 3)), mask=np.ones((d, n), bool),
                  n_valid=np.full(d, n), temp=temp, devices=tuple(f"u{i}" for i in range(d)))
    for spec in ("bias_poly(1)", "bias_poly(1)+thermal_lag"):
        with pytest.raises(Seen):
            fit(spec, batch, noise_floor=False)
    assert sizes[True] == 2 < sizes[False]


def test_collinear_columns_report_the_real_rms():
    """An extra column that is the temperature (3·T + 1) beside ``bias_poly(1)``: the
    columns are collinear, the status ``rank_deficient``, and the rms is the residual of
    the column space the two span, which ``bias_poly(1)`` alone spans: the same number on
    both paths (the sums path read 0.0 or NaN, its coefficients' sums cancelling)."""
    rng = np.random.default_rng(0)
    n = 3000
    t = np.arange(n, dtype=float)
    temp = 20.0 + 10.0 * np.sin(t / 900.0)
    gyro = 1e-3 + 2e-4 * np.outer(temp - 20.0, [1.0, -1.0, 0.5]) + 5e-4 * rng.standard_normal((n, 3))
    batch = Batch.from_recordings([Recording(t=t, gyro=gyro, temp=temp,
                                             aux={"v": 3.0 * temp + 1.0}, device="d")])
    plain = fit("bias_poly(1)", batch).records()[0]
    assert plain["status"] == "ok"
    for path in ("sums", "direct"):
        rec = fit("bias_poly(1)+aux(v)", batch, path=path).records()[0]
        assert rec["status"] == "rank_deficient", path
        np.testing.assert_allclose(rec["rms"], plain["rms"], rtol=1e-6, err_msg=path)
