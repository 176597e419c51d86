"""fit(): closed form vs optimistix vs lstsq, batching, padding, recovery of known truth
for every registered effect (and the calibration file written from that fit), honest
covariance, compensation, per-device status, gradients through the fit."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from effect_cases import WHITE, fit_cases, simulate_case

from diffgyro import Batch, ErrorModel, calibration
from diffgyro import apply as A
from diffgyro.fit import FitOptions, fit, solve_device
from diffgyro.internal import batch_signals
from diffgyro.simulate import simulate


def _sim(plan, effects, n=4, seed=0, **kw):
    kw.setdefault("noise", WHITE)
    return simulate(plan, n, effects=effects, seed=seed, **kw)


@pytest.fixture(scope="module")
def thermal():
    return _sim("thermal", "bias_poly(2)+gradient", n=4, duration=3600.0, sample_rate=1.0)


def test_closed_form_equals_lm_and_lstsq(thermal):
    batch, truth = thermal
    spec = "bias_poly(2)+gradient"
    closed = fit(spec, batch, norm=truth.norm)
    lm = fit(spec, batch, norm=truth.norm, solver="lm")
    assert set(np.asarray(closed.status)) == {0} and set(np.asarray(lm.status)) == {0}
    b1, b2 = np.asarray(closed.params.beta), np.asarray(lm.params.beta)
    assert np.max(np.abs(b1 - b2) / np.abs(b1)) < 1e-8
    # numpy lstsq on the same design, per device and axis
    model = ErrorModel.from_spec(spec)
    sig = batch_signals(batch, norm=truth.norm)
    for d in range(batch.n_devices):
        s = jax.tree.map(lambda a, d=d: a[d], sig)
        n = int(batch.n_valid[d])
        x = np.asarray(model.design(s, jnp.zeros(0)))[:n]
        y = np.asarray(s.gyro - s.rate)[:n]
        for i in range(3):
            ref = np.linalg.lstsq(x[:, i], y[:, i], rcond=None)[0]
            assert np.max(np.abs(ref - b1[d, i]) / np.abs(ref)) < 1e-8


def test_batch_equals_single_and_padding(thermal):
    batch, truth = thermal
    spec = "bias_poly(2)+gradient"
    whole = fit(spec, batch, norm=truth.norm)
    for d in (0, 3):
        rec = batch.recording(d)
        alone = fit(spec, Batch.from_recordings([rec]), norm=truth.norm)
        padded = fit(spec, Batch.from_recordings([rec], length=2 * batch.length), norm=truth.norm)
        for other in (alone, padded):
            np.testing.assert_allclose(np.asarray(other.params.beta[0]),
                                       np.asarray(whole.params.beta[d]), rtol=1e-10, atol=1e-16)
            np.testing.assert_allclose(float(other.heldout_rms[0]), float(whole.heldout_rms[d]),
                                       rtol=1e-10)


#: Every registered effect term the fit recovers, read from the registry (effect_cases.py):
#: a term registered anywhere is covered here without editing this file.
FIT_CASES = fit_cases()


@pytest.fixture(scope="module", params=FIT_CASES, ids=[c.name for c in FIT_CASES])
def fitted(request):
    """One case's simulated devices (3, known truth) and their fit, shared by the recovery
    and calibration-file tests."""
    case = request.param
    batch, truth = simulate_case(case, n=3, seed=11)
    return case, batch, truth, fit(case.fit[1], batch, norm=truth.norm)


def test_recovers_truth(fitted):
    case, batch, truth, res = fitted
    spec = case.fit[1]
    assert [res.status_name(i) for i in range(3)] == ["ok"] * 3, [res.status_detail(i) for i in range(3)]
    true_beta = np.asarray(truth.params.beta)
    true_theta = np.asarray(truth.params.theta)
    for d in range(3):
        se = res.stderr(d)
        z_beta = (np.asarray(res.params.beta[d]) - true_beta[d]) / np.asarray(se.beta)
        assert np.all(np.abs(z_beta) < 5.0), (spec, z_beta)
        if true_theta.shape[-1]:
            z_theta = (np.asarray(res.params.theta[d]) - true_theta[d]) / np.asarray(se.theta)
            assert np.all(np.abs(z_theta) < 5.0), (spec, z_theta)
    # the fit closes the gap to the white noise
    assert np.all(np.asarray(res.heldout_rms) < 1.1 * np.asarray(res.noise_floor))


def test_calibration_file_compensates(fitted, tmp_path):
    """The calibration file written from the fit holds its coefficients exactly, loads
    again unchanged, and compensates a recording to the white noise: with the numpy-only
    ``apply`` where the term has a numpy form (the first device: apply is a reference, not
    fast), else with ``calibration.compensate`` (every device)."""
    case, batch, truth, res = fitted
    path = tmp_path / "cal.json"
    calibration.save(calibration.from_fit(res, batch), path)
    cal = calibration.load(path)
    assert cal.model == ErrorModel.from_spec(case.fit[1]).spec
    doc = json.loads(path.read_text())
    assert json.loads(json.dumps(cal.to_json())) == doc
    if not case.has_numpy_form:
        corrected, _ = calibration.compensate(cal, batch)
    for d, dev in enumerate(cal.devices):
        assert dev.device == batch.devices[d]
        np.testing.assert_array_equal(np.asarray(dev.beta), np.asarray(res.params.beta[d]))
        np.testing.assert_array_equal(np.asarray(dev.theta), np.asarray(res.params.theta[d]))
        rec = batch.recording(d)
        if case.has_numpy_form and d > 0:
            continue
        if case.has_numpy_form:
            rate = A.compensate(doc, dev.device, rec.t, rec.gyro, temp=rec.temp,
                                temp_ext=rec.temp_ext, accel=rec.accel, aux=rec.aux,
                                terms=case.apply_terms)
        else:
            rate = np.asarray(corrected.gyro[d, : rec.n])
        err = (rate - rec.rate).std(axis=0)
        assert np.all(err < 1.1 * np.asarray(res.noise_axes[d])), (case.name, err)


def test_intervals_cover_truth():
    """Over 240 devices the nominal 95 % intervals cover the truth 93–97 % of the time."""
    spec = "bias_poly(3)+temp_diff"
    batch, truth = _sim("thermal", spec, n=240, seed=5, duration=1800.0, sample_rate=1.0,
                        noise={**WHITE, "temp_noise": 0.0})
    res = fit(spec, batch, norm=truth.norm)
    assert np.all(np.asarray(res.status) == 0)
    se = np.stack([np.asarray(res.stderr(d).beta) for d in range(batch.n_devices)])
    z = (np.asarray(res.params.beta) - np.asarray(truth.params.beta)) / se
    coverage = float(np.mean(np.abs(z) < 1.959964))
    print(f"coverage of nominal 95 % intervals: {coverage:.3f} over {z.size} parameters")
    assert 0.93 <= coverage <= 0.97


def test_compensate_reaches_noise_on_heldout_data():
    spec = "bias_poly(1)+scale_poly(1)+misalignment+scale_asym"
    batch, truth = _sim("rate_table", spec, n=3, seed=2)
    res = fit(spec, batch, norm=truth.norm)
    assert np.all(np.asarray(res.status) == 0)
    cal = calibration.from_fit(res, batch)
    # a second run of the same devices (same coefficients, new noise)
    again, truth2 = _sim("rate_table", spec, n=3, seed=3, params=truth.params,
                         temp_norm=truth.norm)
    with pytest.warns(UserWarning, match="clamped"):  # its sensors warm differently
        corrected, clamped = calibration.compensate(cal, again)
    sigma = np.asarray(truth2.noise.arw) * np.sqrt(2.0)  # σ per sample at 2 Hz
    for d in range(3):
        n = int(again.n_valid[d])
        lo, hi = cal.devices[d].temp_range
        temp = np.asarray(again.temp[d, :n])
        inside = (temp >= lo) & (temp <= hi)   # judged where the calibration is valid
        assert clamped.get(again.devices[d], 0) == int(np.sum(~inside))
        err = (np.asarray(corrected.gyro[d, :n]) - np.asarray(again.rate[d, :n]))[inside]
        ratio = err.std(axis=0) / sigma[d]
        assert np.all(np.abs(ratio - 1.0) < 0.05), ratio


def _corrupt(batch, idx, **fields):
    recs = batch.recordings()
    for i in idx:
        r = recs[i]
        recs[i] = type(r)(**{**{k: getattr(r, k) for k in ("t", "gyro", "temp", "temp_ext", "accel",
                                                           "mag", "rate", "quat")},
                              **{k: f(r) for k, f in fields.items()}},
                           device=r.device, source=r.source)
    return Batch.from_recordings(recs, length=batch.length)


def test_bad_devices_do_not_sink_the_batch():
    spec = "bias_poly(3)+temp_diff"
    batch, truth = _sim("thermal", spec, n=1000, seed=9, duration=1200.0, sample_rate=0.5)
    const = list(range(0, 25, 5))          # constant temperature
    collinear = list(range(500, 525, 5))   # temp_ext a linear function of temp
    bad = _corrupt(batch, const, temp=lambda r: np.full_like(r.temp, 25.0))
    bad = _corrupt(bad, collinear, temp_ext=lambda r: 0.5 * r.temp - 3.0)
    res = fit(spec, bad)
    good = np.setdiff1d(np.arange(1000), const + collinear)
    ref = fit(spec, batch.select(good), options=FitOptions())
    names = [res.status_name(i) for i in range(1000)]
    assert all(names[i] == "insufficient_range" for i in const)
    assert all(names[i] == "rank_deficient" for i in collinear)
    assert "temp_diff" in res.status_detail(collinear[0])
    assert all(names[i] == "ok" for i in good)
    np.testing.assert_allclose(np.asarray(res.params.beta)[good], np.asarray(ref.params.beta),
                               rtol=1e-12, atol=1e-18)


def test_nonlinear_start_far_away_is_flagged_alone():
    spec = "bias_poly(0)+warmup"
    batch, truth = _sim("warmup", spec, n=8, seed=4, duration=1800.0, sample_rate=0.5)
    theta0 = np.tile(np.asarray(truth.params.theta)[:, :1], 1)
    theta0[2] = 16.0  # τ ≈ 100 days: the start sees no transient at all
    # LM on the design (path="direct") stalls on that plateau: flagged, the others untouched
    res = fit(spec, batch, theta0=theta0, path="direct")
    ref = fit(spec, batch, theta0=np.asarray(truth.params.theta), path="direct")
    names = [res.status_name(i) for i in range(8)]
    assert names[2] == "not_converged", names  # stuck on a plateau worse than the grid
    others = [i for i in range(8) if i != 2]
    assert all(names[i] == "ok" for i in others)
    np.testing.assert_allclose(np.asarray(res.params.beta)[others],
                               np.asarray(ref.params.beta)[others], rtol=1e-12)
    # warmup has no jet of its own: the sums path differentiates its columns in forward
    # mode; from the same start, the same optimum and held-out error as LM on the design
    direct = ref
    ref = fit(spec, batch, theta0=np.asarray(truth.params.theta))
    assert [direct.status_name(i) for i in range(8)] == ["ok"] * 8
    assert [ref.status_name(i) for i in range(8)] == ["ok"] * 8
    np.testing.assert_allclose(np.asarray(ref.params.theta), np.asarray(direct.params.theta),
                               rtol=0, atol=1e-6)
    b1, b2 = np.asarray(direct.params.beta), np.asarray(ref.params.beta)
    assert np.max(np.abs(b1 - b2) / np.max(np.abs(b1), axis=-1, keepdims=True)) < 1e-6
    for name in ("rms", "heldout_rms", "sigma"):
        np.testing.assert_allclose(np.asarray(getattr(ref, name)),
                                   np.asarray(getattr(direct, name)), rtol=1e-6)
    # Newton on the projected cost (the default sums path) leaves the plateau: the far
    # start reaches the optimum of the true start, in more steps, and only it takes more
    res = fit(spec, batch, theta0=theta0)
    assert [res.status_name(i) for i in range(8)] == ["ok"] * 8
    np.testing.assert_allclose(np.asarray(res.params.beta), np.asarray(ref.params.beta),
                               rtol=1e-9)
    np.testing.assert_allclose(np.asarray(res.params.theta), np.asarray(ref.params.theta),
                               rtol=1e-9)
    steps = np.asarray(res.steps)
    assert steps[2] > np.max(steps[others])
    np.testing.assert_array_equal(steps[others], np.asarray(ref.steps)[others])


@pytest.mark.parametrize("spec", ["bias_poly(2)+gradient", "bias_poly(1)+warmup"])
def test_gradient_through_fit_matches_finite_differences(spec):
    plan = "warmup" if "warmup" in spec else "thermal"
    batch, truth = _sim(plan, spec, n=1, seed=1, duration=1800.0)
    model = ErrorModel.from_spec(spec)
    sig = jax.tree.map(lambda a: a[0], batch_signals(batch, norm=truth.norm))
    # tight tolerances: the finite differences see the solver's stopping error
    opts = FitOptions(rtol=jnp.asarray(1e-14), atol=jnp.asarray(1e-18), max_steps=200)
    theta0 = None if model.is_linear else jnp.asarray(truth.params.theta[0])

    @jax.jit
    def params_of(gyro):
        out = solve_device(model, eqx_replace_gyro(sig, gyro), opts, theta0)
        return jnp.concatenate([out["beta"].ravel(), out["theta"]])

    g0 = sig.gyro
    jac = jax.jacrev(params_of)(g0)  # (params, n, 3): reverse mode, implicit adjoint
    rng = np.random.default_rng(0)
    v = jnp.asarray(rng.normal(size=g0.shape)) * sig.mask[:, None]
    directions = [v] + [jnp.zeros_like(g0).at[int(rng.integers(0, int(batch.n_valid[0]))),
                                              int(rng.integers(0, 3))].set(1.0) for _ in range(3)]
    for k, e in enumerate(directions):
        an = np.asarray(jnp.einsum("pna,na->p", jac, e))
        # a step well above the solver's stopping error; Richardson removes the O(h²) part
        h = 2e-3 / float(jnp.linalg.norm(e))

        def central(h, e=e):
            return np.asarray((params_of(g0 + h * e) - params_of(g0 - h * e)) / (2 * h))

        fd = (4.0 * central(h / 2) - central(h)) / 3.0
        # one sample moves a time constant by ~1e-9: the LM stopping error (~1e-9 in log τ)
        # then limits the finite difference itself, not the implicit gradient
        tol = 1e-5 if (model.is_linear or k == 0) else 1e-4
        assert np.max(np.abs(fd - an)) / np.max(np.abs(an)) < tol


def eqx_replace_gyro(sig, gyro):
    import equinox as eqx

    return eqx.tree_at(lambda s: s.gyro, sig, gyro)
