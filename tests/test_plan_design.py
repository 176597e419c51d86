"""Test-plan design: the differentiable plan's physics, the Fisher prediction against closed
forms, plan gradients against finite differences, and an optimised plan against fog-one-run — predicted
and by Monte Carlo."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro.fit import FitOptions
from diffgyro.model import ErrorModel
from diffgyro.plan_design import (
    DEG,
    EARTH_RATE,
    OperatingRange,
    PlanConfig,
    budget_for_accuracy,
    default_truth,
    heading_study,
    monte_carlo,
    optimise_plan,
    plan_duration,
    plan_environment,
    plan_sensitivity,
    predict_plan,
    s2_plan,
    smooth_max,
)

OP = OperatingRange()
MODEL = ErrorModel.from_spec("bias_poly(3)+scale_poly(2)+gradient")
ARW = 1e-5


def test_s2_timeline_and_physics():
    plan = s2_plan()
    cfg = PlanConfig(n_samples=8192, n_headings=2)
    minutes = (65 + 11 * 10) / 1.5 + 12 * 30
    assert abs(float(plan_duration(plan, cfg)) / 60 - minutes) < 1e-3
    # (one compiled program per config, as inside the predictions: op by op it compiled
    # some eighty small ones)
    environment = eqx.filter_jit(plan_environment)
    env = environment(plan, cfg)
    t, chamber, temp = map(np.asarray, (env.t, env.chamber, env.temp))
    ramp_end = np.cumsum(np.r_[65, np.full(11, 10)] / 1.5 * 60 + np.r_[0, np.full(11, 1800)])
    for k, start in enumerate(ramp_end):
        soak = (t > start + 300) & (t < start + 1500)  # away from the rounded corners
        np.testing.assert_allclose(chamber[soak], -40 + 10 * k, atol=1e-4)
        end = np.argmin(np.abs(t - (start + 1790)))
        # the sensor (τ = 10 min) trails a ramp by at most ramp·τ, then settles as exp(−t/τ):
        # above the set point after cooling (first soak), below it after heating
        lag = (temp[end] - (-40 + 10 * k)) * (1 if k == 0 else -1)
        assert 0 < lag < 1.5 / 60 * 600 * math.exp(-(1790 - 60) / 600)
    # table: ±10 °/s along the tilted mount, equal time each way (net angle zero)
    table = np.asarray(environment(plan, PlanConfig(n_samples=8192, earth_rate="none")).rate_true)
    omega = table @ np.ones(3) / math.sqrt(3)
    np.testing.assert_allclose(table, omega[:, None] * np.ones(3) / math.sqrt(3), atol=1e-15)
    # (segment edges are logistic, 5 s wide: a one-minute spin peaks within 1 % of its rate)
    assert abs(np.max(omega) / (10 * DEG) - 1) < 0.01 and abs(np.min(omega) / (10 * DEG) + 1) < 0.01
    assert abs(np.sum(omega) * float(env.dt)) < 1e-4  # rad
    # at rest the true rate is Earth's, which the reference holds (known)
    still = np.abs(omega) < 1e-9
    rate = np.asarray(env.rate_true)
    np.testing.assert_allclose(np.linalg.norm(rate[still], axis=1), EARTH_RATE, rtol=1e-4)
    np.testing.assert_array_equal(rate, np.asarray(env.rate_ref))


def test_prediction_matches_closed_form_information():
    """A constant bias under white noise: σ = ARW / √(time), at every operating point."""
    cfg = PlanConfig(n_samples=2048, earth_rate="none")
    plan = s2_plan()
    model = ErrorModel.from_spec("bias_poly(0)")
    pred = predict_plan(plan, cfg, model, ARW, OP)
    env = eqx.filter_jit(plan_environment)(plan, cfg)  # (one program, not eighty)
    want = ARW / math.sqrt(float(env.dt) * cfg.n_samples)
    np.testing.assert_allclose(np.asarray(pred.sigma), want, rtol=1e-10)
    # a scale factor: its error grows with the rate and vanishes at rest
    pred2 = predict_plan(plan, cfg, ErrorModel.from_spec("bias_poly(0)+scale_poly(0)"), ARW, OP)
    sig = np.asarray(pred2.sigma).reshape(OP.n_temps, 3, 3)  # (temps, −Ω/0/+Ω, axis)
    assert np.all(sig[:, 0] > sig[:, 1]) and np.all(sig[:, 2] > sig[:, 1])


def _plan_fd(f, plan, field, idx, h):
    def shifted(s):
        leaf = getattr(plan, field)
        new = leaf.at[idx].add(s) if leaf.ndim else leaf + s
        return eqx.tree_at(lambda p: getattr(p, field), plan, new)

    d1 = (f(shifted(h)) - f(shifted(-h))) / (2 * h)
    d2 = (f(shifted(h / 2)) - f(shifted(-h / 2))) / h
    return (4 * d2 - d1) / 3


GRADIENT_CASES = [
    # the Fisher information alone (closed form)
    ("bias_poly(3)+scale_poly(2)+gradient", None, 1024, 1.0, 1e-5),
    # a truth the model lacks: the expected fit through solve_device (lineax Cholesky)
    ("bias_poly(1)+scale_poly(0)", "bias_poly(1)+scale_poly(0)+temp_diff", 1024, 1.0, 1e-5),
    # ... and through optimistix's implicit adjoint (the thermal-lag time constant). The
    # forward solve is good to ~1e-8 in log τ, which limits the finite differences (not the
    # adjoint: see test_sensitivity for 1e-5 agreement on the data); larger steps, 1e-4.
    ("bias_poly(1)+thermal_lag", "bias_poly(1)+thermal_lag+warmup", 512, 10.0, 1e-4),
]


@pytest.mark.parametrize("spec,truth_spec,n,step,tol", GRADIENT_CASES,
                         ids=["fisher", "closed", "implicit"])
def test_plan_gradients_match_finite_differences(spec, truth_spec, n, step, tol):
    cfg = PlanConfig(n_samples=n, self_heating=2.0, earth_rate="none")
    plan = s2_plan()
    model = ErrorModel.from_spec(spec)
    kw = {}
    if truth_spec:
        tm = ErrorModel.from_spec(truth_spec)
        beta = default_truth(tm).beta.at[:, -1].set(3e-5 if "temp_diff" in truth_spec else 2e-4)
        kw = dict(truth_model=tm, truth=eqx.tree_at(lambda p: p.beta, default_truth(tm), beta),
                  fit_options=FitOptions(n_folds=2, n_blocks=2, rtol=jnp.asarray(1e-13),
                                         atol=jnp.asarray(1e-18), max_steps=200))

    def worst(pl):
        return smooth_max(predict_plan(pl, cfg, model, ARW, OP, **kw).total)

    # one compiled program gives both the value (for the differences) and the gradient: the
    # forward pass is the same computation in either, and a program of the value alone
    # would compile it a second time (compiling is what this test costs)
    value_and_grad = jax.jit(jax.value_and_grad(worst))
    value, grad = value_and_grad(plan)

    def f(pl):
        return value_and_grad(pl)[0]

    # steps of about 1e-3 of each number (× step); Richardson removes the truncation error
    checks = [("temps", 3, 0.1), ("soaks", 0, 2.0), ("soaks", 11, 2.0), ("ramp", None, 2.5e-5),
              ("spin_fraction", None, 1e-4), ("rates", 0, 2e-4)]
    for field, idx, h in checks:
        g = getattr(grad, field)
        ad = float(g[idx] if idx is not None else g)
        if field in ("spin_fraction", "rates") and not model.rate_dependent:
            assert ad == 0.0  # no term of the model sees the table
            continue
        fd = float(_plan_fd(f, plan, field, idx if idx is not None else (), h * step))
        print(f"{field}: AD {ad:.6e} FD {fd:.6e}")
        assert abs(ad - fd) <= tol * abs(ad) + 1e-12 * float(value), field


def test_headings_cancel_an_unknown_earth_rate():
    plan = s2_plan()
    model = ErrorModel.from_spec("bias_poly(3)+scale_poly(2)")
    # (a grid fine enough that the one-minute spins turn the table smoothly)
    unknown = heading_study(plan, PlanConfig(n_samples=2048, earth_rate="unknown"), model, ARW, OP,
                            headings=(1, 2))
    known = float(predict_plan(plan, PlanConfig(n_samples=2048), model, ARW, OP).worst)
    print("worst case by headings, Earth rate unknown:", unknown, "known:", known)
    assert unknown[1] > 1.8 * unknown[2] > 1.8 * 5 * known
    # the horizontal Earth rate (Ω_E cos 45°) is the size of the one-heading error
    assert 0.5 * EARTH_RATE < unknown[1] < EARTH_RATE


#: Adam steps of every optimisation here (the design and each trial of the equal-accuracy
#: search): the step count is the length of the compiled loop, so one program serves both.
STEPS = 120
#: Monte Carlo devices per plan (one compiled batch for both plans): the worst-case RMS of
#: 300 devices has a relative standard error of about 1/√600 ≈ 4 %, the 15 % tolerance ~3.7σ.
MC_DEVICES = 300


@pytest.fixture(scope="module")
def designed():
    cfg = PlanConfig(n_samples=2048)
    s2 = s2_plan()
    res = optimise_plan(s2, cfg, MODEL, ARW, OP, steps=STEPS)
    return cfg, s2, res


def test_optimised_plan_beats_s2_and_monte_carlo_agrees(designed):
    cfg, s2, res = designed
    pred_s2 = predict_plan(s2, cfg, MODEL, ARW, OP)
    assert abs(float(res.prediction.duration) / float(pred_s2.duration) - 1) < 1e-9  # same time
    h = np.asarray(res.history)
    assert h[-1] < h[0]
    mc_opt = monte_carlo(res.plan, cfg, MODEL, ARW, OP, n_devices=MC_DEVICES, seed=3)
    mc_s2 = monte_carlo(s2, cfg, MODEL, ARW, OP, n_devices=MC_DEVICES, seed=4)
    p_opt, p_s2 = float(res.prediction.worst), float(pred_s2.worst)
    m_opt, m_s2 = float(mc_opt.worst), float(mc_s2.worst)
    print(f"worst-case 1σ compensation error over −40…70 °C, ±10 °/s (rad/s): fog-one-run predicted "
          f"{p_s2:.3e}, Monte Carlo {m_s2:.3e}; optimised predicted {p_opt:.3e}, "
          f"Monte Carlo {m_opt:.3e} ({100 * (m_opt / p_opt - 1):+.1f} %); "
          f"accuracy gained at equal time {100 * (1 - p_opt / p_s2):.0f} %")
    assert set(np.asarray(mc_opt.status).tolist()) == {0}
    assert abs(m_opt / p_opt - 1) < 0.15
    assert abs(m_s2 / p_s2 - 1) < 0.15
    assert p_opt < 0.5 * p_s2 and m_opt < 0.5 * m_s2


def test_plan_sensitivity_and_equal_accuracy_time(designed):
    cfg, s2, _ = designed
    sens = plan_sensitivity(s2, cfg, MODEL, ARW, OP)
    el = sens["elasticity"]
    # longer or faster spins help; the coldest and hottest soaks matter most
    assert float(el.spin_fraction) < 0 and float(el.rates[0]) < 0
    soak = np.abs(np.asarray(el.soaks))
    assert max(soak[0], soak[-1]) == soak.max()
    np.testing.assert_allclose(float(el.ramp), float(sens["grad"].ramp * s2.ramp / sens["worst"]))
    target = float(sens["worst"])
    t_s2 = float(plan_duration(s2, cfg))
    # four trials after the longest time: a miss at ``lo``, two hits by regula falsi and a
    # miss that moves the other end (each trial is a whole optimisation)
    t_eq, res = budget_for_accuracy(target, s2, cfg, MODEL, ARW, OP, lo=1800.0, hi=t_s2,
                                    iterations=4, steps=STEPS)
    print(f"fog-one-run accuracy in {t_eq / 3600:.2f} h instead of {t_s2 / 3600:.2f} h")
    assert float(res.prediction.worst) <= target
    assert abs(float(res.prediction.duration) - t_eq) < 1e-6 * t_eq
    assert t_eq < 0.6 * t_s2
