"""diagnose names the noise the residual holds: a Gauss–Markov bias under a correct thermal
model reads as Gauss–Markov with its correlation time, not as a random walk or a missing
effect; its ``noise`` object has the ``noise --json`` form."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from diffgyro.data import Recording
from diffgyro.diagnose import diagnose
from diffgyro.stochastic import simulate_noise

N, DT = 8192, 0.1
SIGMA, TAU, ARW = 3e-3, 20.0, 3e-4  # rad/s, s, rad/s/√Hz


#: The three axes' white + Gauss–Markov noise, one compiled program for every correlation time.
_gyro_noise = jax.jit(jax.vmap(lambda k, tau: simulate_noise(k, N, DT, arw=ARW, gm=((SIGMA, tau),)),
                               in_axes=(0, None)))


def _recording(seed: int, tau: float = TAU, quad: float = 0.0) -> Recording:
    """A thermal run whose bias is linear in temperature (plus ``quad``·ΔT², an effect the
    base model lacks), plus white + GM noise of correlation time ``tau``."""
    t = np.arange(N) * DT
    temp = 20.0 + 15.0 * np.sin(2 * np.pi * t / (N * DT))
    g = np.asarray(_gyro_noise(jax.random.split(jax.random.PRNGKey(seed), 3), tau)).T
    g = g + 1e-3 + 2e-4 * (temp - 20.0)[:, None] + quad * ((temp - 20.0) ** 2)[:, None]
    return Recording(t=t, gyro=g, temp=temp, device=f"gm{seed}")


@pytest.fixture(scope="module")
def diag():
    return diagnose("bias_poly(1)", [_recording(11)])


def test_gauss_markov_named_not_a_walk(diag):
    d = diag.devices[0]
    assert d.noise_process == "gauss_markov", d.noise
    assert d.verdict == "adequate" and d.best is None, d.explanation
    assert not any(c.significant for c in d.candidates)  # no deterministic effect proposed
    assert d.random_walk is None or not d.random_walk.significant
    assert "Gauss–Markov" in d.explanation
    for axis in d.noise["axes"].values():
        gm = [c for c in axis["components"] if c["kind"] == "gauss_markov"]
        lo, hi = gm[-1]["params"]["tau"]["ci"]
        assert lo <= TAU <= hi, gm


def test_noise_object_in_json(diag):
    rec = json.loads(json.dumps(diag.to_json(), allow_nan=False))["devices"][0]
    noise = rec["noise"]
    assert noise["device"] == rec["device"] == "gm11"
    assert noise["status"] == "ok" and set(noise["axes"]) == {"x", "y", "z"}
    for axis in noise["axes"].values():
        kinds = [c["kind"] for c in axis["components"]]
        assert kinds[0] == "white" and "gauss_markov" in kinds
        arw = axis["components"][0]["params"]["arw"]
        assert arw["unit"] == "rad/s/√Hz" and arw["ci"][0] <= ARW * 1.05 and arw["ci"][1] >= ARW * 0.95
    assert rec["noise_process"] == "gauss_markov"


def test_white_residual_not_identified():
    """An ordinary run (white residual, model right) does not pay for the identification."""
    t = np.arange(N) * DT  # the length of the fixture's: the same compiled programs
    temp = 20.0 + 15.0 * np.sin(2 * np.pi * t / (N * DT))
    g = np.random.default_rng(3).normal(0.0, ARW / np.sqrt(DT), (N, 3)) + 2e-4 * (temp - 20.0)[:, None]
    d = diagnose("bias_poly(1)", [Recording(t=t, gyro=g, temp=temp, device="w")]).devices[0]
    assert d.verdict == "adequate"
    assert d.noise["status"] == "not_identified" and d.noise["axes"] is None
    assert d.noise_process is None


def test_kalman_bias_uses_the_identified_model(diag):
    """kalman.identified_bias runs the identified model; a random walk alone is exactly
    kalman's own walk filter, and a Gauss–Markov bias's variance stays below its σ²."""
    import jax.numpy as jnp

    from diffgyro.kalman import identified_bias, rw_filter

    y = np.asarray(diag.residuals[0, :N])
    axes = diag.devices[0].noise["axes"]
    b, pb = identified_bias(y, axes, DT)
    for k, ax in enumerate("xyz"):
        gm = [c for c in axes[ax]["components"] if c["kind"] == "gauss_markov"]
        sig2 = sum(c["params"]["sigma"]["value"] ** 2 for c in gm)
        assert np.all(np.asarray(pb[:, k]) <= sig2 * (1 + 1e-9))
    arw, rrw = 3e-4, 1e-5
    walk = {ax: {"components": [{"kind": "white", "params": {"arw": {"value": arw}}},
                                {"kind": "random_walk", "params": {"rrw": {"value": rrw}}}]}
            for ax in "xyz"}
    b, pb = identified_bias(y, walk, DT, p0_walk=1e-4)
    t = jnp.arange(N) * DT
    fp = rw_filter(jnp.asarray(y[:, 0]), jnp.zeros((N, 0)), jnp.ones(N, bool), t,
                   jnp.asarray(rrw**2), jnp.asarray(arw**2 / DT), jnp.asarray(1e-4))
    np.testing.assert_allclose(np.asarray(b[:, 0]), np.asarray(fp.a_y), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(np.asarray(pb[:, 0]), np.asarray(fp.p), rtol=1e-9)


def test_missing_effect_under_the_bias_is_named():
    """Scored against the identified noise (white + Gauss–Markov), a missing ΔT² term whose
    variance is about a third of the bias' is named; against the white floor alone it closes
    about a quarter of the gap the bias opens, too little to count, and nothing is named.
    The ΔT² term is named as the built-in ``bias_poly(2)`` or as the synthesised
    ``term(dtemp^2)``, the same column: which of the two depends on the noise the residual
    is identified with (white + Gauss–Markov, the truth, since the block-mean likelihood
    chooses the slow part: the raised floor then leaves the synthesised term to name it)."""
    d = diagnose("bias_poly(1)", [_recording(0, tau=5.0, quad=2.2e-5)]).devices[0]
    assert d.verdict == "missing_effect", d.explanation
    assert d.best is not None and d.best.term in ("bias_poly(2)", "term(dtemp^2)"), d.best
    assert "identified noise" in d.explanation
    assert d.noise_process is not None and "gauss_markov" in d.noise_process


# ------------------------------------------------------------------ a right-model thermal run

GM_SIGMA, GM_TAU, FS = 1.5e-4, 400.0, 0.5  # rad/s, s, Hz: the bias noise as large as the white


@pytest.fixture(scope="module")
def thermal_gm():
    """A simulated thermal run (the default chamber profile stretched to N samples at 0.5 Hz,
    4.6 h, the length of the runs above) whose model is right (bias_poly(2)), with white noise
    of 1.5e-4 rad/s per sample and a Gauss–Markov bias of the same σ and τ = 400 s on every
    axis; and its diagnosis with the default options."""
    import dataclasses

    import diffgyro
    from diffgyro.simulate import simulate

    diffgyro.enable_x64()
    batch, _ = simulate("thermal", 1, effects="bias_poly(2)", seed=3, sample_rate=FS,
                        duration=N / FS, noise={"arw": GM_SIGMA / np.sqrt(FS), "rrw": 0.0,
                                                "bias_instability": 0.0, "quantum": 0.0})
    rec = batch.recording(0)
    keys = jax.random.split(jax.random.PRNGKey(5), 3)
    gm = np.stack([np.asarray(simulate_noise(k, rec.n, 1 / FS, gm=((GM_SIGMA, GM_TAU),)))
                   for k in keys], axis=1)
    rec = dataclasses.replace(rec, gyro=rec.gyro + gm)
    return rec, diagnose("bias_poly(2)", [rec])


def test_gauss_markov_bias_named_on_a_right_model_thermal_run(thermal_gm):
    """The model is right and nothing is missing, yet the held-out error is ~35 % above the
    white level: the noise is identified without being asked, σ and τ of the bias cover the
    truth on every axis, the verdict stays adequate and the explanation gives σ and τ."""
    _, diag = thermal_gm
    d = diag.devices[0]
    assert d.verdict == "adequate" and d.best is None, d.explanation
    assert d.excess > 0.15
    assert d.noise["status"] == "ok" and d.noise_process == "gauss_markov", d.noise
    for axis in d.noise["axes"].values():
        (gm,) = [c for c in axis["components"] if c["kind"] == "gauss_markov"]
        s, t = gm["params"]["sigma"], gm["params"]["tau"]
        assert s["ci"][0] <= GM_SIGMA <= s["ci"][1], s
        assert t["ci"][0] <= GM_TAU <= t["ci"][1], t
        assert f"σ {s['value']:.3g} [{s['ci'][0]:.3g}, {s['ci'][1]:.3g}] rad/s" in d.explanation
        assert f"τ {t['value']:.3g} [{t['ci'][0]:.3g}, {t['ci'][1]:.3g}] s" in d.explanation


def test_text_json_and_report_agree(thermal_gm, tmp_path, capsys):
    """`diagnose --noise --json --report`: the JSON's noise object, the text table and
    explanation and the report page give the same σ and τ."""
    from diffgyro import io
    from diffgyro.cli import main
    from diffgyro.cli.diagnose import print_diagnosis, wide_console

    rec, diag = thermal_gm
    path = tmp_path / "run.csv"
    io.save(rec, path)
    assert main(["diagnose", str(path), "--model", "bias_poly(2)", "--noise", "--json",
                 "--report", str(tmp_path / "rep")]) == 0
    (out,) = json.loads(capsys.readouterr().out)["devices"]
    assert out["noise_process"] == "gauss_markov" and out["noise"]["interval_level"] == 0.95
    page = next((tmp_path / "rep").glob("*.html"), None)
    pages = "".join(p.read_text() for p in (tmp_path / "rep").glob("*.html"))
    assert page is not None and "Noise model of the residual" in pages
    print_diagnosis(diag, wide_console())
    text = capsys.readouterr().out
    assert " GM " in text
    for axis in out["noise"]["axes"].values():
        (gm,) = [c for c in axis["components"] if c["kind"] == "gauss_markov"]
        s, t = gm["params"]["sigma"], gm["params"]["tau"]
        words = f"σ {s['value']:.3g} [{s['ci'][0]:.3g}, {s['ci'][1]:.3g}] rad/s"
        assert words in out["explanation"] and words in " ".join(text.split())
        assert f"<td>{t['value']:.3g}</td><td>[{t['ci'][0]:.3g}, {t['ci'][1]:.3g}]</td>" in pages
