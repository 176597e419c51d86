"""The stochastic model: closed-form wavelet variances, their covariance, GMWM identification with
intervals and structure choice (a small version of benchmarks/noise_identification.py), the
``noise`` command and the filter parameters exported from it."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro.internal import (
    COV_GRID,
    avar_gauss_markov,
    dyadic_m,
    haar_wv,
    model_wv,
    model_wv_jac,
    psd,
    wv_covariance,
)
from diffgyro.stochastic import (
    SLOW_PENALTY,
    catalogue,
    identify,
    label,
    simulate_noise,
    structure_mask,
)

DT = 0.01
#: Every identification test runs 12 series of this length and interval (655 s, as the
#: benchmark's records): one compiled program for all.
N = 1 << 15
DT_ID = 0.02


def _theta(**powers):
    """Log-parameter vector from {name: value} of the layout (others 0, masked off)."""
    from diffgyro.internal import LAYOUT

    th = np.zeros(len(LAYOUT))
    for k, v in powers.items():
        th[LAYOUT.index(k)] = math.log(v)
    return jnp.asarray(th)


CASES = {  # (powers, structure)
    "white": (dict(white=1e-6), ("white",)),
    "quantization": (dict(quantization=1e-8), ("quantization",)),
    "gm short": (dict(gm1_var=1e-6, gm1_tau=3 * DT), ("gauss_markov",)),
    "gm long": (dict(gm1_var=1e-6, gm1_tau=1e4 * DT), ("gauss_markov",)),
    "random walk": (dict(random_walk=1e-8), ("random_walk",)),
}


@pytest.mark.parametrize("case", list(CASES))
def test_closed_forms_equal_the_spectral_integral(case):
    """ν²(m) = ∫|H_m|² S df with the Haar gain sin⁴(πfm)/(m² sin²πf): the closed forms of
    components.py against an independent quadrature of each component's spectrum."""
    powers, structure = CASES[case]
    th, mask = _theta(**powers), jnp.asarray(structure_mask(structure))
    m = 2.0 ** np.arange(6)
    f = (np.arange(400_000) + 0.5) / 800_000  # midpoints of (0, 1/2)
    s = np.asarray(psd(th, mask, jnp.asarray(f), DT))
    gain = np.sin(np.pi * f[None, :] * m[:, None]) ** 4 / (m[:, None] ** 2 * np.sin(np.pi * f) ** 2)
    integral = 2.0 * np.sum(gain * s, axis=1) / 800_000  # two-sided
    closed = np.asarray(model_wv(th, mask, jnp.asarray(m * DT), DT))
    np.testing.assert_allclose(closed, integral, rtol=2e-4)


def test_gauss_markov_reaches_the_ieee_continuous_form():
    """T ≫ dt: the sampled AR(1) formula tends to IEEE Std 952's σ²T/τ·(2 − T/τ(3 − 4e^{−τ/T} + e^{−2τ/T}))."""
    s2, t, dt = 1e-6, 50.0, 1e-3
    tau = np.array([1.0, 10.0, 50.0, 200.0, 1000.0])
    ieee = s2 * t / tau * (2.0 - t / tau * (3.0 - 4.0 * np.exp(-tau / t) + np.exp(-2.0 * tau / t)))
    got = np.asarray(avar_gauss_markov(s2, t, jnp.asarray(tau), dt))
    np.testing.assert_allclose(got, ieee, rtol=1e-3)


def test_empirical_wavelet_variance_and_its_covariance_match_the_model():
    """Mean of ν̂² over 256 simulated series = the closed form; their spread and neighbour
    correlation = covariance.py's (white + Gauss–Markov + random walk + ramp)."""
    n = 4096
    kw = dict(arw=1e-3, gm=((2e-3, 0.2),), rrw=1e-3, ramp=1e-3)
    sim = jax.jit(jax.vmap(lambda k: simulate_noise(k, n, DT, **kw)))
    y = sim(jax.random.split(jax.random.PRNGKey(3), 256))
    m = dyadic_m(n)
    wv, count = haar_wv(y, DT, None, m)
    th = _theta(white=1e-6, gm1_var=4e-6, gm1_tau=0.2, random_walk=1e-6, rate_ramp=1e-6)
    mask = jnp.asarray(structure_mask(("white", "gauss_markov", "random_walk", "rate_ramp")))
    theory = np.asarray(model_wv(th, mask, jnp.asarray(m * DT), DT))
    cov = np.asarray(wv_covariance(th, mask, jnp.asarray(m, float), jnp.asarray(count[0], float), n, DT))
    emp = np.asarray(wv)
    sd = np.sqrt(np.diag(cov))
    small = m <= 128  # enough terms per series for the first-order covariance
    se_mean = emp.std(0) / math.sqrt(len(emp))
    assert np.all(np.abs(emp.mean(0) - theory)[small] < 4 * se_mean[small])
    ratio = emp.std(0) / sd
    assert np.all((ratio[small] > 0.8) & (ratio[small] < 1.2)), ratio
    corr_emp = np.corrcoef(emp.T)[np.arange(4), np.arange(1, 5)]
    corr_th = (cov / np.outer(sd, sd))[np.arange(4), np.arange(1, 5)]
    np.testing.assert_allclose(corr_emp, corr_th, atol=0.12)


def test_a_ramps_wavelet_variance_spreads_as_the_model_says():
    """White noise + a ramp and no walk: where the ramp dominates, ν̂'s whole spread is its
    coefficient times the mean of the white noise's (the record's ends, order 1/M²). The
    model's standard deviation matches the spread over 400 series at every scale (it was
    a tenth of it at the longest, where the ramp's intervals then covered nothing)."""
    n, arw, r = 4096, 1e-3, 2e-3
    rng = np.random.default_rng(5)
    y = arw / math.sqrt(DT) * rng.standard_normal((400, n)) + r * DT * np.arange(n)
    m = dyadic_m(n)
    wv, count = haar_wv(jnp.asarray(y), DT, None, m)
    th = _theta(white=arw**2, rate_ramp=r**2)
    mask = jnp.asarray(structure_mask(("white", "rate_ramp")))
    cov = np.asarray(wv_covariance(th, mask, jnp.asarray(m, float), jnp.asarray(count[0], float), n, DT))
    theory = np.asarray(model_wv(th, mask, jnp.asarray(m * DT), DT))
    ratio = np.asarray(wv).std(0) / np.sqrt(np.diag(cov))
    ramp = 0.25 * r**2 * (m * DT) ** 2 > 10 * 0.5 * arw**2 / (m * DT)  # the ramp dominates
    assert ramp.sum() >= 3 and theory[-1] > 100 * 0.5 * arw**2 / (m[-1] * DT)
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio


def test_the_covariance_quadrature_is_the_rule_written_out():
    """covariance.py sums its integrand as two products of (scales × frequencies) matrices;
    the rule its docstring states, summed over a (scales, scales, frequencies) array here,
    gives the same covariance to rounding, for every component switched on."""
    n, m = 8192, 2.0 ** np.arange(11)
    count = n + 1 - 2 * m
    th = _theta(white=1e-6, quantization=1e-9, gm1_var=4e-6, gm1_tau=0.2, gm2_var=1e-6,
                gm2_tau=30.0, random_walk=1e-8)
    mask = jnp.asarray(structure_mask(("white", "quantization", "gauss_markov", "gauss_markov",
                                       "random_walk")))
    lf = np.linspace(np.log(0.02 / n), np.log(0.5), COV_GRID)
    f = np.exp(lf)
    s = np.asarray(psd(th, mask, jnp.asarray(f), DT))
    sin2 = np.sin(np.pi * f) ** 2
    arg = np.pi * f[None, :] * m[:, None]
    slow = arg < 6.0 * np.pi  # beyond: sin⁴ replaced by its average
    gain = np.where(slow, np.sin(arg) ** 4, 0.375) / (m[:, None] ** 2 * sin2)
    octaves = np.abs(np.round(np.log2(m[:, None] / m[None, :])))
    both = np.select([octaves == 0, octaves == 1], [35 / 128, 7 / 64], 9 / 64)
    prod = gain[:, None, :] * gain[None, :, :]
    fast = ~slow[:, None, :] & ~slow[None, :, :]
    prod = np.where(fast, both[:, :, None] / (m[:, None, None] ** 2 * m[None, :, None] ** 2
                                             * sin2**2), prod)
    integrand = prod * s**2 * f
    integral = (lf[1] - lf[0]) * (integrand.sum(-1) - 0.5 * (integrand[..., 0] + integrand[..., -1]))
    expect = 4.0 * integral / np.maximum(count[:, None], count[None, :])
    got = np.asarray(wv_covariance(th, mask, jnp.asarray(m), jnp.asarray(count), n, DT))
    np.testing.assert_allclose(got, expect, rtol=1e-12)


def test_the_fits_jacobian_equals_forward_differentiation():
    """The closed-form derivative of log ν(θ) the fit steps with (components.py) equals JAX's
    forward differentiation of the model and central differences, every structure."""
    tau = DT * 2.0 ** np.arange(12)
    th = _theta(white=1e-6, quantization=1e-9, gm1_var=4e-6, gm1_tau=0.2, gm2_var=1e-6,
                gm2_tau=30.0, random_walk=1e-8, rate_ramp=1e-10)
    log_wv = jax.jit(lambda t, mask: jnp.log(model_wv(t, mask, tau, DT)))
    closed = jax.jit(lambda t, mask: model_wv_jac(t, mask, tau, DT))
    forward = jax.jit(lambda t, mask: jax.jacfwd(log_wv)(t, mask) * mask)
    h = 1e-6
    for structure in catalogue():
        mask = jnp.asarray(structure_mask(structure))
        nu, d = closed(th, mask)
        got = np.asarray(d / nu[:, None])
        np.testing.assert_allclose(got, np.asarray(forward(th, mask)), rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(np.asarray(nu), np.asarray(model_wv(th, mask, tau, DT)), rtol=1e-13)
        fd = np.stack([(np.asarray(log_wv(th.at[i].add(h), mask))
                        - np.asarray(log_wv(th.at[i].add(-h), mask))) / (2 * h) for i in range(8)],
                      axis=1)
        np.testing.assert_allclose(got, fd, rtol=1e-6, atol=1e-8)


#: A small version of the benchmark: truth per structure (SI units), two seeds each.
TRUTHS = {
    "white + random_walk": dict(arw=1e-3, rrw=2e-4),
    "white + gauss_markov": dict(arw=1e-3, gm=((1e-3, 10.0),)),
    "white + gauss_markov×2": dict(arw=1e-3, gm=((4e-3, 0.5), (3e-3, 5.0))),
    "white + gauss_markov + random_walk": dict(arw=1e-3, gm=((3e-3, 0.5),), rrw=5.5e-4),
    "white + quantization": dict(arw=1e-3, q=2e-4),
    "white + random_walk + rate_ramp": dict(arw=1e-3, rrw=1e-3, ramp=2e-4),
}


def _simulate(truths, seed):
    ys = []
    for i, kw in enumerate(truths):
        f = jax.jit(jax.vmap(lambda k, kw=kw: simulate_noise(k, N, DT_ID, **kw)))
        ys.append(f(jax.random.split(jax.random.PRNGKey(seed + i), 2)))
    return jnp.concatenate(ys)  # (12, N)


@pytest.fixture(scope="module")
def identified():
    y = _simulate(list(TRUTHS.values()), 500)
    return y, identify(y, DT_ID)


@pytest.fixture(scope="module")
def identified_slow(identified):
    """Four of the series, their slow part chosen again by the block means' likelihood
    (``noise --slow-part``)."""
    y, _ = identified
    return identify(y[:4], DT_ID, slow_penalty=SLOW_PENALTY)


def _flat(components):
    out, gm = {}, 0
    for c in components:
        for k, p in c["params"].items():
            if c["kind"] == "gauss_markov":
                out[f"gm{gm + 1}_{k}"] = p
            else:
                out[k] = p
        gm += c["kind"] == "gauss_markov"
    return out


def _benchmark():
    """benchmarks/noise_identification.py, of which the identification tests are a small
    version (its truth parameters are read the same way here)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / "noise_identification.py"
    spec = importlib.util.spec_from_file_location("noise_identification", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_identify_chooses_the_structure_and_its_intervals_hold_the_truth(identified):
    _, res = identified
    truth_params = _benchmark().truth_params
    right = covered = total = 0
    for i, (name, kw) in enumerate(TRUTHS.items()):
        for s in range(2):
            j = 2 * i + s
            if label(res.structure(j)) != name:
                continue
            right += 1
            got = _flat(res.components(j))
            for k, v in truth_params(kw).items():
                p = got[k]
                assert p["ci"][0] <= p["value"] <= p["ci"][1]
                total += 1
                covered += p["ci"][0] <= v <= p["ci"][1]
                # the estimate is near the truth: white noise to a few per cent, the rest within
                # a factor that the record length allows
                assert abs(math.log(p["value"] / v)) < (0.03 if k == "arw" else 0.7), (name, k)
    assert right >= 10  # of 12
    assert covered >= 0.85 * total


@pytest.mark.parametrize("slow_part", [False, True])
def test_rejected_alternatives_are_scored_and_sorted(identified, identified_slow, slow_part):
    res = identified_slow if slow_part else identified[1]
    rej = res.rejected(0)
    assert len(rej) == len(res.structures) - 1
    # the slow part's alternatives first, sorted by the block-mean likelihood's criterion;
    # then the other resolvable ones by the wavelet-variance criterion; then those the record
    # cannot resolve (a Gauss–Markov time beyond its share), whatever their criterion
    alt = [r for r in rej if "likelihood_delta" in r]
    ok = [r for r in rej[len(alt):] if r.get("resolvable", True)]
    assert rej[:len(alt)] == alt and rej[len(alt):len(alt) + len(ok)] == ok
    assert all("why" in r for r in rej[len(alt) + len(ok):])
    ldeltas = [r["likelihood_delta"] for r in alt]
    assert all(d >= 0 for d in ldeltas) and ldeltas == sorted(ldeltas)
    assert bool(alt) == slow_part  # (the wavelet criterion alone scores no slow alternative)
    deltas = [r["delta"] for r in ok]
    assert deltas == sorted(deltas) and (slow_part or all(d >= 0 for d in deltas))
    assert {r["structure"] for r in rej} | {label(res.structure(0))} == {
        label(s) for s in res.structures}


def test_asymptotic_intervals_agree_with_a_parametric_bootstrap(identified):
    """The sandwich's standard errors of log σ and log τ of a white + Gauss–Markov fit against the
    spread of 12 refits of recordings simulated from the fitted model."""
    _, res = identified
    j = 2  # white + gauss_markov, seed 0
    assert label(res.structure(j)) == "white + gauss_markov"
    got = _flat(res.components(j))
    kw = dict(arw=got["arw"]["value"], gm=((got["gm1_sigma"]["value"], got["gm1_tau"]["value"]),))
    sim = jax.jit(jax.vmap(lambda k: simulate_noise(k, N, DT_ID, **kw)))
    boot = identify(sim(jax.random.split(jax.random.PRNGKey(900), 12)), DT_ID)
    logs = {k: [] for k in ("arw", "gm1_sigma", "gm1_tau")}
    for b in range(12):
        if label(boot.structure(b)) == "white + gauss_markov":
            fb = _flat(boot.components(b))
            for k in logs:
                logs[k].append(math.log(fb[k]["value"]))
    assert len(logs["arw"]) >= 9
    for k, vals in logs.items():
        lo, hi = got[k]["ci"]
        se = (math.log(hi) - math.log(lo)) / (2 * 1.959964)
        ratio = float(np.std(vals, ddof=1)) / se
        assert 0.5 < ratio < 1.8, (k, ratio)


def test_noise_command_json_contract_text_and_report(tmp_path, capsys, identified):
    import pandas as pd

    from diffgyro.cli import main

    y, _ = identified
    y = np.asarray(y)
    frames = []
    for d in range(4):  # 4 devices × 3 axes: the 12 series of the fixture
        frames.append(pd.DataFrame({"device": f"imu{d}", "t": np.arange(N) * DT_ID,
                                    "gx": y[3 * d], "gy": y[3 * d + 1], "gz": y[3 * d + 2]}))
    frames.append(pd.DataFrame({"device": "short", "t": np.arange(20) * DT_ID, "gx": y[0, :20],
                                "gy": y[1, :20], "gz": y[2, :20]}))
    path = tmp_path / "static.csv"
    pd.concat(frames).to_csv(path, index=False)
    assert main(["noise", str(path), "--json", "--report", str(tmp_path / "rep")]) == 0
    doc = json.loads(capsys.readouterr().out)
    devs = {d["device"]: d for d in doc["devices"]}
    assert devs["short"]["status"] == "too_short" and devs["short"]["axes"] is None
    assert "64" in devs["short"]["status_detail"]
    units = {"arw": "rad/s/√Hz", "q": "rad", "sigma": "rad/s", "tau": "s", "rrw": "rad/s²/√Hz",
             "r": "rad/s²"}
    d0 = devs["imu0"]
    assert d0["status"] == "ok" and set(d0["axes"]) == {"x", "y", "z"}
    for ax in d0["axes"].values():
        assert ax["rejected"] and all("criterion" in r for r in ax["rejected"])
        for c in ax["components"]:
            assert c["kind"] in ("white", "quantization", "gauss_markov", "random_walk", "rate_ramp")
            for name, p in c["params"].items():
                assert p["unit"] == units[name]
                assert p["ci"][0] <= p["value"] <= p["ci"][1]
    # imu0's x axis is the first series of white + random walk: ARW and RRW near the truth
    x = _flat(d0["axes"]["x"]["components"])
    assert x["arw"]["value"] == pytest.approx(1e-3, rel=0.03)
    rep = tmp_path / "rep"
    assert (rep / "index.html").read_text().count("<img") == 4
    assert len(list(rep.glob("*.png"))) == 4
    # text: display units
    from diffgyro.cli.noise import _print_text

    _print_text(doc, None)
    text = capsys.readouterr().out
    assert "°/√h" in text and "too_short" in text and "next best" in text
    # filter parameters from the JSON
    (tmp_path / "noise.json").write_text(json.dumps({"devices": [devs["imu0"]]}))
    assert main(["export", str(tmp_path / "noise.json"), "--format", "px4-ekf"]) == 0
    out = capsys.readouterr().out
    assert "EKF2_GYR_NOISE" in out and "EKF2_GYR_B_NOISE" in out


def test_filter_parameters_by_hand(tmp_path, capsys):
    """PX4 EKF2 and ArduPilot EKF3 add (Δt·noise)² per step: parameter = density/√Δt; a
    Gauss–Markov bias enters as the random walk √(2σ²/T); Kalibr takes the densities."""
    from diffgyro.cli import main
    from diffgyro.export import ekf_noise

    p = ekf_noise.px4_parameters(1e-3, 2e-5)
    assert p["EKF2_GYR_NOISE"] == pytest.approx(1e-3 / math.sqrt(0.01))
    assert p["EKF2_GYR_B_NOISE"] == pytest.approx(2e-4)
    a = ekf_noise.ardupilot_parameters(1e-3, 2e-5)
    assert a["EK3_GYRO_P_NSE"] == pytest.approx(1e-3 / math.sqrt(0.012))
    assert a["EK3_GBIAS_P_NSE"] == pytest.approx(2e-5 / math.sqrt(0.012))

    def param(v):
        return {"value": v, "ci": [v / 2, v * 2], "unit": "-"}

    axis = {"components": [{"kind": "white", "params": {"arw": param(1e-3)}},
                           {"kind": "gauss_markov", "params": {"sigma": param(1e-3), "tau": param(200.0)}},
                           {"kind": "random_walk", "params": {"rrw": param(1e-4)}}], "rejected": []}
    small = {"components": [{"kind": "white", "params": {"arw": param(5e-4)}}], "rejected": []}
    doc = {"devices": [{"device": "imu", "status": "ok", "status_detail": "ok", "sample_interval": 0.005,
                        "axes": {"x": axis, "y": small, "z": small}}]}
    name, n, k, report = ekf_noise.device_densities(doc, None)
    assert (name, n) == ("imu", 1e-3)
    assert k == pytest.approx(math.sqrt(1e-8 + 2e-6 / 200.0))
    assert any("Gauss–Markov" in r for r in report)
    path = tmp_path / "noise.json"
    path.write_text(json.dumps(doc))
    assert main(["export", str(path), "--format", "ardupilot-ekf", "--ekf-dt", "0.0025"]) == 0
    out = capsys.readouterr().out
    assert f"EK3_GYRO_P_NSE,{1e-3 / math.sqrt(0.0025):.6g}"[:18] in out
    assert main(["export", str(path), "--format", "kalibr", "--accel-noise-density", "1e-3",
                 "--accel-random-walk", "1e-4"]) == 0
    yaml = capsys.readouterr().out
    assert "gyroscope_noise_density: 1.000000e-03" in yaml
    assert f"gyroscope_random_walk: {k:.6e}" in yaml
    assert "update_rate: 200" in yaml


def test_bias_filter_with_the_identified_model_is_calibrated():
    """A filter carrying white + Gauss–Markov + random walk: standardised innovations white with
    unit variance, and the bias error the size the filter states; a random-walk-only filter
    (the Gauss–Markov process as its equivalent walk) tracks it worse."""
    from diffgyro.stochastic import bias_filter, state_space

    n, dt = 40_000, 0.01
    k1, k2 = jax.random.split(jax.random.PRNGKey(11))
    bias, white = jax.jit(lambda k1, k2: (simulate_noise(k1, n, dt, gm=((2e-3, 2.0),), rrw=2e-4),
                                          simulate_noise(k2, n, dt, arw=1e-3)))(k1, k2)
    y = bias + white

    def comp(kind, **params):
        return {"kind": kind, "params": {k: {"value": v} for k, v in params.items()}}

    model = [comp("white", arw=1e-3), comp("gauss_markov", sigma=2e-3, tau=2.0),
             comp("random_walk", rrw=2e-4)]
    b, pb, e, f = bias_filter(y, *state_space(model, dt, p0_walk=1e-6))
    z = np.asarray(e / jnp.sqrt(f))[100:]
    assert np.var(z) == pytest.approx(1.0, abs=0.05)
    assert abs(np.corrcoef(z[:-1], z[1:])[0, 1]) < 0.03
    err = np.asarray(b - bias)[100:]
    assert np.mean(err**2 / np.asarray(pb)[100:]) == pytest.approx(1.0, abs=0.15)
    walk = [comp("white", arw=1e-3), comp("random_walk", rrw=math.sqrt(2e-4**2 + 2 * 2e-3**2 / 2.0))]
    b_rw, *_ = bias_filter(y, *state_space(walk, dt, p0_walk=1e-6))
    assert np.sqrt(np.mean(err**2)) < 0.98 * np.sqrt(np.mean(np.asarray(b_rw - bias)[100:] ** 2))


def test_a_moving_device_is_not_identified(tmp_path, capsys):
    """The motion check takes a device that turned out: status in_motion, no axes, and the
    detail says how it moved; the device at rest beside it is identified."""
    import pandas as pd

    from diffgyro.cli import main

    rng = np.random.default_rng(4)
    n, dt = 8192, 0.01  # the length the other identification tests compile for
    rest = 1e-3 * rng.standard_normal((n, 3))
    turned = rest.copy()
    turned[2000:2300, 2] += 1.0  # a 3 s turn at 1 rad/s, then back
    turned[5000:5300, 2] -= 1.0
    frames = [pd.DataFrame({"device": name, "t": np.arange(n) * dt, "gx": g[:, 0],
                            "gy": g[:, 1], "gz": g[:, 2]})
              for name, g in (("moved", turned), ("rest", rest))]
    pd.concat(frames).to_csv(tmp_path / "two.csv", index=False)
    assert main(["noise", str(tmp_path / "two.csv"), "--json", "--gyro-unit", "rad/s"]) == 0
    moved, still = json.loads(capsys.readouterr().out)["devices"]
    assert moved["status"] == "in_motion" and moved["axes"] is None
    assert moved["status_detail"].startswith("in_motion: ") and "record at rest" in \
        moved["status_detail"]
    assert still["status"] == "ok" and still["axes"] is not None


def test_the_block_likelihood_finds_a_ramp_beside_a_gauss_markov_bias():
    """A ramp beside a Gauss–Markov bias raises the longest wavelet variances as a walk
    would; fitted out as a trend of the block means, its slope stands about ten standard
    errors from zero here (R = 1e-5 rad/s² over 655 s against a zero-frequency density
    N² + 2σ²T = 2.1e-5 rad²/s). Eight records: the structure holds the ramp on all but
    one at most, and the ramp's 95 % interval covers it on all of those but one at most."""
    kw = dict(arw=1e-3, gm=((1e-3, 10.0),), ramp=1e-5)
    f = jax.jit(jax.vmap(lambda k: simulate_noise(k, N, DT_ID, **kw)))
    y = f(jax.random.split(jax.random.PRNGKey(77), 8))
    res = identify(y, DT_ID, slow_penalty=SLOW_PENALTY)
    right = [label(res.reported_structure(i)) == "white + gauss_markov + rate_ramp" for i in range(8)]
    assert sum(right) >= 7, [label(res.reported_structure(i)) for i in range(8)]
    ci = [_flat(res.components(int(i)))["r"]["ci"] for i in np.flatnonzero(right)]
    assert sum(lo <= 1e-5 <= hi for lo, hi in ci) >= len(ci) - 1, ci


def test_structures_the_record_hardly_tells_apart_are_stated(identified_slow):
    """``resolution.close``: the slow alternatives within 2 of the chosen structure on the block
    likelihood's criterion, each with a sentence in the notes, as ``rejected`` scores them;
    an alternative moved to 1.0 from the chosen one joins them, one at 3.0 does not."""
    res = identified_slow
    for i in range(4):
        r = res.resolution(i)
        alt = {x["structure"]: x["likelihood_delta"] for x in res.rejected(i) if "likelihood_delta" in x}
        assert {c["structure"] for c in r["close"]} == {s for s, d in alt.items() if d < 2.0}
    i = next(i for i in range(4) if np.sum(np.isfinite(res.slow_criterion[i])) >= 3)
    slow = res.slow_criterion.copy()
    best = int(res.choice[i])
    near, far = [int(k) for k in np.flatnonzero(np.isfinite(slow[i])) if k != best][:2]
    slow[i, near], slow[i, far] = slow[i, best] + 1.0, slow[i, best] + 3.0
    r = dataclasses.replace(res, slow_criterion=slow).resolution(i)
    assert [c["structure"] for c in r["close"]] == [label(res.structures[near])]
    assert r["close"][0]["likelihood_delta"] == pytest.approx(1.0)
    assert any(label(res.structures[near]) in n and "hardly tells" in n for n in r["notes"])


class _Called(Exception):
    """Raised by the spy below once it has seen the program's arguments."""


def _signature(args) -> list:
    """Shapes, dtypes, weak types and whether placed on a device (a committed JAX array
    compiles a program of its own) of array arguments; other arguments as they are."""
    return [(a.shape, np.dtype(a.dtype), bool(getattr(a, "weak_type", False)),
             bool(getattr(a, "committed", False)))
            if hasattr(a, "shape") else a for a in args]


@pytest.mark.parametrize("series,n,max_gm", [(3, 12000, 2), (11, 700, 1)])
def test_the_programs_loaded_ahead_are_the_ones_identify_calls(monkeypatch, series, n, max_gm):
    """``noise`` loads the identification's two programs (the fits, the choice) on threads
    while it checks the devices for motion (:func:`diffgyro.stochastic.identify_ahead`): the
    arguments it loads them for have the shapes, dtypes and weak types of those
    :func:`identify` then calls them with (else it would load second programs), for a chunk
    under the batch and one over it."""
    from diffgyro.stochastic import _identify, catalogue

    seen, ahead = [], []

    class Done:
        def join(self):
            pass

    def spy(name, result=None):
        def call(*args):
            seen.append((name, _signature(args)))
            if result is None:
                raise _Called
            # (placed on the device, as a compiled program's results are)
            return tuple(jax.device_put(np.zeros(s.shape, s.dtype), jax.devices()[0])
                         for s in result)

        def compile_ahead(*args):
            ahead.append((name, _signature(args)))
            return Done()

        call.compile_ahead = compile_ahead
        return call

    fits_args, choice_args = _identify.program_specs(series, n, catalogue(max_gm))
    monkeypatch.setattr(_identify, "_programs", lambda samples: (
        spy("fits", choice_args[-3:]), spy("choice")))
    y = np.random.default_rng(1).standard_normal((series, n)) * 1e-3
    with pytest.raises(_Called):
        identify(y, 0.1, structures=catalogue(max_gm))
    assert seen == [("fits", _signature(fits_args)), ("choice", _signature(choice_args))]
    assert fits_args[-1] == len(dyadic_m(n))
    assert ahead == seen  # identify's own compilation ahead is of those programs too


@pytest.mark.parametrize("devices,n", [(1, 12000), (3, 700)])
def test_the_wavelet_variances_program_loaded_ahead_is_the_one_identify_calls(monkeypatch, devices,
                                                                              n):
    """``noise`` also starts the wavelet variances' program ahead (:func:`~diffgyro.stochastic.
    identify_ahead`): for the shapes, dtypes and weak types that :func:`identify` then calls
    it with for devices × 3 axes (else a second program would compile)."""
    from diffgyro.stochastic import _identify, _wavelet_variance

    started, called = [], []

    def signature(*args):
        return [(a.shape, np.dtype(a.dtype), bool(getattr(a, "weak_type", False)))
                if hasattr(a, "shape") else a for a in args]

    class Done:
        def join(self):
            pass

    def spy(*a):
        called.append(signature(*a))
        raise _Called

    def ahead(*a):
        started.append(signature(*a))
        return Done()

    spy.compile_ahead = ahead
    monkeypatch.setattr(_wavelet_variance, "oadev", spy)
    monkeypatch.setattr(_identify, "_programs", lambda samples: (spy, spy))
    _identify.load_ahead(3 * devices, n, catalogue(2), lead=(devices, 3))
    y = np.random.default_rng(2).standard_normal((devices, 3, n)) * 1e-3
    with pytest.raises(_Called):
        identify(y, np.full((devices, 3), 0.1), structures=catalogue(2))
    # load_ahead's three programs, then identify's own start of the first two (the same
    # signatures: compile_ahead returns the threads load_ahead started)
    assert len(started) == 5 and started[:2] == started[3:] and started[2:3] == called
