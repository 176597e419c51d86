"""The simulator against its known truth: noise levels, Earth rate, thermal lag,
profiles, determinism, the model basis, and the command line."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from diffgyro.cli import main
from diffgyro.errors import DataError, SpecError
from diffgyro.internal import DEG, EARTH_RATE, G0, first_order_hold_lag, qconj, qlog, qmul
from diffgyro.model import ErrorModel, Params
from diffgyro.signals import TempNorm, make_signals
from diffgyro.simulate import Truth, demo_batch, simulate, truth_path

QUIET = {"arw": 0.0, "rrw": 0.0, "bias_instability": 0.0, "quantum": 0.0, "temp_noise": 0.0,
         "accel_noise": 0.0}


def rel_tol(n_eff: float, k: float = 5.0) -> float:
    """k standard errors of a standard deviation estimated from ``n_eff`` samples."""
    return k / math.sqrt(2.0 * n_eff)


# --------------------------------------------------------------------------- noise


def test_white_noise_matches_arw():
    arw = 2e-4
    fs = 100.0
    batch, truth = simulate("static", 2, seed=3, noise={**QUIET, "arw": arw}, duration=100.0,
                            sample_rate=fs)
    n = int(batch.n_valid[0])
    g = batch.gyro[:, :n]
    sigma = g.std(axis=1, ddof=1)  # (devices, 3): only white noise on a constant bias
    expected = arw * math.sqrt(fs)
    tol = rel_tol(n)
    assert tol < 0.05
    np.testing.assert_allclose(sigma / expected, 1.0, atol=tol)
    np.testing.assert_allclose(truth.noise.arw, arw)


def test_white_noise_within_5_percent_with_all_preset_noise():
    """Full MEMS noise (white, random walk, flicker, quantisation): the white part,
    read from successive differences, matches each device's configured ARW within 5 %."""
    fs = 100.0
    batch, truth = simulate("static", 3, seed=11, duration=60.0, sample_rate=fs)
    n = int(batch.n_valid[0])
    dg = np.diff(batch.gyro[:, :n], axis=1)
    sigma = dg.std(axis=1, ddof=1) / math.sqrt(2.0)
    expected = truth.noise.arw * math.sqrt(fs)
    assert np.all(np.abs(sigma / expected - 1.0) < 0.05), sigma / expected


def test_rate_random_walk_increments_and_growth():
    rrw = 1e-5
    dt = 1.0
    d, dur = 400, 400.0
    batch, truth = simulate("static", d, seed=5, noise={**QUIET, "rrw": rrw}, duration=dur,
                            sample_rate=1.0 / dt)
    n = int(batch.n_valid[0])
    g = batch.gyro[:, :n] - batch.gyro[:, :1]  # remove each device's constant bias
    inc = np.diff(g, axis=1)
    var_inc = inc.var()
    assert abs(var_inc / (rrw**2 * dt) - 1.0) < 2 * rel_tol(inc.size)
    # a walk: the spread across devices grows linearly with time
    var_end = g[:, -1].var()
    assert abs(var_end / (rrw**2 * (n - 1) * dt) - 1.0) < 4 * math.sqrt(2.0 / (3 * d))
    # increments are uncorrelated
    a = inc[:, 1:].ravel()
    b = inc[:, :-1].ravel()
    assert abs(np.corrcoef(a, b)[0, 1]) < 5 / math.sqrt(a.size)


def test_bias_instability_allan_floor():
    """Flicker approximation: the Allan deviation is flat near 0.664·B over decades."""
    allan = pytest.importorskip("allantools")
    bi = 1e-4
    batch, truth = simulate("static", 1, seed=2, noise={**QUIET, "bias_instability": bi},
                            duration=20000.0, sample_rate=5.0)
    n = int(batch.n_valid[0])
    y = batch.gyro[0, :n, 0]
    taus, adev, _, _ = allan.oadev(y, rate=5.0, data_type="freq", taus=np.array([3.0, 30.0, 300.0]))
    ratio = adev / (math.sqrt(2 * math.log(2) / math.pi) * bi)
    assert np.all(np.abs(ratio - 1.0) < 0.2), ratio


def test_quantisation_steps():
    q = 1e-3
    batch, _ = simulate("static", 2, seed=1, noise={**QUIET, "arw": 3e-3, "quantum": q, "temp_noise": 0.3},
                        temp_quantum=1.0, duration=20.0, sample_rate=50.0)
    n = int(batch.n_valid[0])
    g = batch.gyro[:, :n] / q
    np.testing.assert_allclose(g, np.round(g), atol=1e-9)
    steps = np.abs(np.diff(batch.gyro[:, :n], axis=1))
    assert np.isclose(steps[steps > 0].min(), q)
    temp = batch.temp[:, :n]
    np.testing.assert_array_equal(temp, np.round(temp))
    tsteps = np.abs(np.diff(temp, axis=1))
    assert set(np.unique(tsteps)) <= {0.0, 1.0, 2.0}
    assert np.any(tsteps == 1.0)


# --------------------------------------------------------------------------- six faces (cube-bias)


@pytest.fixture(scope="module")
def six_face():
    return simulate("six_face", 1, seed=0, noise="none", effects="bias_poly(0)", accel_errors=False,
                    tilt=0.5, latitude=30.0, dwell=10.0)


def test_six_face_earth_rate_matches_latitude(six_face):
    batch, truth = six_face
    lat = 30.0 * DEG
    normal = np.array(truth.info["table_normal"])
    omega_nav = EARTH_RATE * np.array([math.cos(lat), 0.0, math.sin(lat)])
    faces = {}
    for s in truth.segments:
        if s["label"] != "face":
            continue
        r = batch.rate[0, s["start"]:s["end"]].mean(axis=0)
        f = batch.accel[0, s["start"]:s["end"]].mean(axis=0)
        assert np.isclose(np.linalg.norm(r), EARTH_RATE, rtol=1e-9)
        assert np.isclose(np.linalg.norm(f), G0, rtol=1e-12)
        faces.setdefault(s["face"], []).append((r, f))
    assert sorted(faces) == sorted(["+x", "-x", "+y", "-y", "+z", "-z"])
    for face, rows in faces.items():
        assert len(rows) == 4
        k = "xyz".index(face[1])
        sign = 1.0 if face[0] == "+" else -1.0
        r = np.array([row[0] for row in rows])
        f = np.array([row[1] for row in rows])
        # the up axis sees the component of Earth rate along the table normal: Ω·sin(lat) level
        np.testing.assert_allclose(sign * r[:, k], omega_nav @ normal, rtol=1e-9)
        assert abs(omega_nav @ normal - EARTH_RATE * math.sin(lat)) < EARTH_RATE * 0.5 * 0.5 * DEG * 2
        # averaging the four headings cancels the horizontal part and the tilt (cube-bias)
        others = [j for j in range(3) if j != k]
        np.testing.assert_allclose(r.mean(axis=0)[others], 0.0, atol=1e-12 * EARTH_RATE + 1e-18)
        np.testing.assert_allclose(f.mean(axis=0)[others], 0.0, atol=1e-9)
        np.testing.assert_allclose(sign * f[:, k], G0 * normal[2], rtol=1e-12)


def test_six_face_rate_can_be_omitted_but_gyro_still_sees_earth():
    batch, truth = simulate("six_face", 1, seed=0, noise="none", effects="bias_poly(0)",
                            include_rate=False, dwell=5.0, faces="+z,-z", turns=False)
    assert batch.rate is None and "rate" not in truth.outputs
    lat = 45.0 * DEG
    up = EARTH_RATE * np.array([math.cos(lat), 0.0, math.sin(lat)]) @ truth.info["table_normal"]
    bias = truth.params.beta[0, :, 0]
    for s in truth.segments:
        if s["label"] == "face":
            g = batch.gyro[0, s["start"]:s["end"]].mean(axis=0) - bias
            sign = 1.0 if s["face"] == "+z" else -1.0
            assert np.isclose(sign * g[2], up, rtol=1e-9)
            assert np.isclose(np.linalg.norm(g), EARTH_RATE, rtol=1e-9)


def test_six_face_imucal_sections(six_face):
    _, truth = six_face
    sec = truth.info["sections"]
    assert set(sec) == {"x_p", "x_a", "y_p", "y_a", "z_p", "z_a", "x_rot", "y_rot", "z_rot"}
    batch = six_face[0]
    for ax in "xyz":
        s = sec[f"{ax}_rot"]
        k = "xyz".index(ax)
        angle = np.sum(batch.rate[0, s["start"]:s["end"], k]) / 10.0  # 10 Hz, rectangle rule
        assert abs(angle + 2 * math.pi) < 2e-3  # one clockwise turn


# --------------------------------------------------------------------------- thermal


def test_sensor_lag_recovers_time_constant():
    """A chamber step (10 °C in 1 s) with self-heating off: the sensor approaches
    the chamber exponentially with its own τ."""
    batch, truth = simulate(
        "thermal", 2, seed=4, noise="none", sample_rate=1.0, start_temp=20.0, initial_soak=2.0,
        profile=((30.0, 600.0, 60.0),), power_steps=((0.0, 0.0),))
    n = int(batch.n_valid[0])
    t = batch.t[0, :n]
    step_end = 121.0
    sel = (t > step_end + 60.0) & (t < step_end + 1800.0)
    for i in range(2):
        gap = 30.0 - batch.temp[i, :n][sel]
        slope = np.polyfit(t[sel], np.log(gap), 1)[0]
        tau = -1.0 / slope
        assert abs(tau / truth.thermal["tau_sensor"][i] - 1.0) < 0.01
    # the reported outside temperature is the chamber
    np.testing.assert_allclose(batch.temp_ext[0, :n][sel], 30.0)


@pytest.fixture(scope="module")
def thermal_quiet():
    return simulate("thermal", 2, seed=7, noise="none",
                    effects="bias_poly(2)+gradient+temp_diff+hysteresis", duration=5400.0,
                    sample_rate=1.0, keep_components=True)


def test_true_dtemp_is_the_derivative(thermal_quiet):
    _, truth = thermal_quiet
    t, temp, dtemp = truth.env["t"], truth.env["temp"], truth.env["dtemp"]
    fd = np.gradient(temp, t, axis=1)
    scale = np.abs(dtemp).max()
    assert np.max(np.abs(fd - dtemp)[:, 5:-5]) < 0.02 * scale
    # self-heating: the sensor ends warmer than a pure lag of the chamber
    lagged = first_order_hold_lag(np.broadcast_to(truth.env["chamber"], temp.shape),
                                  truth.thermal["tau_sensor"], t[1] - t[0])
    assert np.all(temp[:, -1] - lagged[:, -1] > 0.5 * truth.thermal["self_heating"])


def test_thermal_profile_rates_and_power_step(thermal_quiet):
    _, truth = thermal_quiet
    ramps = [s for s in truth.segments if s["label"] == "ramp"]
    rates = sorted({round(abs(s["ramp_rate"]) * 5400.0 / (60.0 * 235.0), 6) for s in ramps})
    assert rates == [0.5, 1.0, 2.0]
    signs = {np.sign(s["ramp_rate"]) for s in ramps}
    assert signs == {-1.0, 1.0}
    # inside–outside difference = H·P − τ·dT/dt: the power-on rise and the power
    # steps leave a part that no combination of dT/dt and temp explains
    diff = truth.env["temp"][0] - truth.env["chamber"]
    x = np.stack([np.ones_like(diff), truth.env["dtemp"][0], truth.env["temp"][0]], axis=1)
    resid = diff - x @ np.linalg.lstsq(x, diff, rcond=None)[0]
    assert resid.std() > 0.1 * truth.thermal["self_heating"][0]
    power = np.array(truth.info["power_steps"])
    assert power[:, 1].tolist() == [1.0, 1.6, 1.0]


def test_thermal_on_a_fixture_holds_every_face_at_every_soak():
    """``faces``: each soak is shared among the faces (turned between them), the ramps keep
    the last one, and the temperature path is that of the static plan; a ``term(...)`` truth
    is drawn from the population."""
    kw = dict(seed=2, noise="none", sample_rate=0.2, duration=5400.0)
    batch, truth = simulate("thermal", 1, effects="bias_poly(1)+term(temp*az)",
                            faces="+z,+x,-y", **kw)
    still, _ = simulate("thermal", 1, effects="bias_poly(1)", **kw)
    np.testing.assert_allclose(batch.temp_ext[0], still.temp_ext[0])
    up = {"+z": [0, 0, 1], "+x": [1, 0, 0], "-y": [0, -1, 0]}
    soaks = [s for s in truth.segments if s["label"] == "soak"]
    assert len(soaks) == 3 * (1 + len(truth.options["profile"]))
    for k in range(0, len(soaks), 3):
        assert sorted(s["face"] for s in soaks[k:k + 3]) == sorted(up)
        assert len({s["temp"] for s in soaks[k:k + 3]}) == 1
    for s in soaks:
        f = batch.accel[0, s["start"]:s["end"]] / 9.80665
        np.testing.assert_allclose(f, np.broadcast_to(up[s["face"]], f.shape), atol=1e-9)
    assert np.all(np.asarray(truth.params.beta)[0, :, -1] != 0)


def test_truth_is_in_the_model_basis(thermal_quiet):
    """Least squares on the model's own design (true signals, truth's norm) gives
    back the true coefficients exactly: the simulator speaks the model's language."""
    batch, truth = thermal_quiet
    model = truth.model
    for i in range(batch.n_devices):
        n = int(batch.n_valid[i])
        sig = make_signals(batch.t[i, :n], batch.gyro[i, :n], np.ones(n, bool), rate=batch.rate[i, :n],
                           temp=truth.env["temp"][i], temp_ext=truth.env["chamber"],
                           norm=truth.norm)
        from diffgyro.signals import HEATING_THRESHOLD, latched_heating

        dtemp = truth.env["dtemp"][i]
        heating = latched_heating(dtemp, np.ones(n, bool), HEATING_THRESHOLD)
        import equinox as eqx

        sig = eqx.tree_at(lambda s: (s.dtemp, s.heating), sig, (dtemp, heating))
        x = np.asarray(model.design(sig, np.zeros(0)))
        y = batch.gyro[i, :n] - batch.rate[i, :n]
        for ax in range(3):
            beta = np.linalg.lstsq(x[:, ax], y[:, ax], rcond=None)[0]
            np.testing.assert_allclose(beta, truth.params.beta[i, ax], rtol=1e-7, atol=1e-12)
        np.testing.assert_allclose(y, truth.env["error"][i], atol=1e-15)


def test_rebase_keeps_the_physics():
    model = ErrorModel.from_spec("bias_poly(3)+scale_poly(2)+thermal_lag(2)+gradient")
    rng = np.random.default_rng(0)
    params = Params(beta=rng.standard_normal((2, 3, model.n_params)), theta=np.log([[100.0], [200.0]]))
    old = TempNorm(centre=np.float64(25.0), scale=np.float64(50.0))
    new = TempNorm(centre=np.array([10.0, 31.0]), scale=np.array([30.0, 45.0]))
    from diffgyro.simulate import rebase

    moved = rebase(model, params, old, new)
    temps = np.linspace(-20, 70, 7)
    lag = temps[::-1]
    for i in range(2):
        for norm, p in ((old, params.beta[i]), (TempNorm(new.centre[i], new.scale[i]), moved.beta[i])):
            ts = (temps - norm.centre) / norm.scale
            ls = (lag - norm.centre) / norm.scale
            bias = np.stack([ts**j for j in range(4)], -1) @ p[0, :4]
            sf = np.stack([ts**j for j in range(3)], -1) @ p[0, 4:7]
            lagterm = np.stack([ls**j - ts**j for j in (1, 2)], -1) @ p[0, 7:9]
            if norm is old:
                ref = (bias, sf, lagterm, p[0, 9])
            else:
                np.testing.assert_allclose(bias, ref[0], rtol=1e-10, atol=1e-12)
                np.testing.assert_allclose(sf, ref[1], rtol=1e-10, atol=1e-12)
                np.testing.assert_allclose(lagterm, ref[2], rtol=1e-10, atol=1e-12)
                assert p[0, 9] == ref[3]


# --------------------------------------------------------------------------- rate tables


def test_s2_profile_is_the_published_one():
    batch, truth = simulate("s2", 1, seed=0, noise="none", settle=5.0, sample_rate=1.0)
    assert truth.preset == "fog"
    soaks = [s for s in truth.segments if s["label"] == "soak"]
    assert [s["temp"] for s in soaks] == list(np.arange(-40.0, 71.0, 10.0))
    turns = [s for s in truth.segments if s["label"] == "turn"]
    assert len(turns) == 2 * len(soaks)
    chamber = truth.env["chamber"]
    assert chamber[0] == 20.0 and chamber.min() == -40.0 and chamber.max() == 70.0
    # cools first (room temperature down to −40 °C), at 1.5 °C/min
    first = [s for s in truth.segments if s["label"] == "ramp"][0]
    assert np.isclose((first["t1"] - first["t0"]) / 60.0, 60.0 / 1.5)
    for k, s in enumerate(turns):
        assert np.isclose(s["t1"] - s["t0"], 60.0)
        assert s["temp"] == soaks[k // 2]["temp"]
        r = batch.rate[0, s["start"]:s["end"]]
        assert np.isclose(np.abs(r[:, 2]).max(), 10.0 * DEG)
        assert np.sign(r[len(r) // 2, 2]) == (1.0 if k % 2 == 0 else -1.0)
        np.testing.assert_array_equal(r[:, :2], 0.0)
        np.testing.assert_allclose(chamber[s["start"]:s["end"]], s["temp"])
    assert batch.temp_ext is not None


def test_rate_table_spins_every_axis_both_signs():
    batch, truth = simulate("rate_table", 1, seed=0, noise="none", temps=(20.0, 40.0), settle=1.0,
                            rates=(10.0, 200.0), hold=4.0, pause=2.0, sample_rate=10.0)
    spins = [s for s in truth.segments if s["label"] == "spin"]
    assert len(spins) == 2 * 3 * 2 * 2
    for s in spins:
        k = "xyz".index(s["about"])
        r = batch.rate[0, s["start"]:s["end"]]
        peak = r[np.argmax(np.abs(r[:, k])), k]
        assert np.isclose(peak, s["rate"])
        np.testing.assert_allclose(np.delete(r, k, axis=1), 0.0, atol=1e-12)
        f = batch.accel[0, s["start"]:s["end"]]
        np.testing.assert_allclose(f[:, k], G0, rtol=1e-12)
    seen = {(s["about"], np.sign(s["rate"]), round(abs(s["rate"]) / DEG)) for s in spins}
    assert len(seen) == 12


def test_attitude_quaternions_follow_the_rate():
    batch, truth = simulate("attitude", 2, seed=3, noise="none", duration=30.0, sample_rate=100.0)
    n = int(batch.n_valid[0])
    q, r = batch.quat[:, :n], batch.rate[:, :n]
    step = qlog(qmul(qconj(q[:, :-1]), q[:, 1:])) / 0.01
    np.testing.assert_allclose(step, 0.5 * (r[:, 1:] + r[:, :-1]), atol=1e-9)
    assert np.abs(r).max() > 20 * DEG
    np.testing.assert_allclose(np.linalg.norm(batch.mag[:, :n], axis=-1), 50.0, rtol=1e-12)
    quiet = ~np.any([(np.arange(n) >= s["start"]) & (np.arange(n) < s["end"])
                     for s in truth.segments if s["device"] == 0 and s["linear_accel"]], axis=0)
    np.testing.assert_allclose(np.linalg.norm(batch.accel[0, :n][quiet], axis=-1), G0, rtol=1e-9)


def test_warmup_transient_present():
    batch, truth = simulate("warmup", 2, seed=1, noise="none", effects="warmup", duration=1800.0)
    n = int(batch.n_valid[0])
    tau = np.exp(truth.params.theta[:, 0])
    w = truth.params.beta[:, :, 0]
    expected = w[:, None, :] * np.exp(-batch.t[:, :n, None] / tau[:, None, None])
    np.testing.assert_allclose(batch.gyro[:, :n] - batch.rate[:, :n], expected, atol=1e-15)
    assert np.all(truth.env["temp"][:, -1] > truth.env["temp"][:, 0] + 1.0)  # self-heating


# --------------------------------------------------------------------------- determinism, truth file, CLI


def test_same_seed_same_output_and_stable_streams():
    a, ta = simulate("thermal", 2, seed=9, duration=900.0)
    b, tb = simulate("thermal", 2, seed=9, duration=900.0)
    for name in ("t", "gyro", "temp", "temp_ext", "accel", "rate"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(ta.params.beta, tb.params.beta)
    c, _ = simulate("thermal", 2, seed=10, duration=900.0)
    assert not np.array_equal(a.gyro, c.gyro)
    # adding an effect keeps the other coefficients (streams keyed by term)
    _, td = simulate("thermal", 2, seed=9, duration=900.0, effects="bias_poly(2)+gradient")
    np.testing.assert_array_equal(td.params.beta[..., :3], ta.params.beta)


def test_truth_json_round_trip(tmp_path):
    _, truth = simulate("thermal", 2, seed=1, duration=600.0,
                        effects="bias_poly(1)+thermal_lag+warmup")
    path = tmp_path / "x.truth.json"
    truth.to_json(path)
    back = Truth.load(path)
    np.testing.assert_array_equal(back.params.beta, truth.params.beta)
    np.testing.assert_array_equal(back.params.theta, truth.params.theta)
    np.testing.assert_array_equal(back.noise.arw, truth.noise.arw)
    assert back.spec == truth.spec and back.devices == truth.devices
    assert float(back.norm.scale) == float(truth.norm.scale)
    # thermal_lag follows the bias polynomial (the bias sees the lagged temperature)
    labels = truth.model.param_labels()[0]
    assert truth.coefficients(0)["x"]["thermal_lag.l1"] == truth.coefficients(0)["x"]["bias_poly(1).c1"]
    assert "warmup.tau" in truth.coefficients(0)["shared"]
    assert len(labels) == truth.params.beta.shape[-1]
    assert truth_path("dir/x.csv").name == "x.truth.json"


def test_cli_writes_standard_csv_that_loads_back_identical(tmp_path, capsys):
    out = tmp_path / "x.csv"
    rc = main(["simulate", "--plan", "thermal", "--devices", "3", "--duration", "600",
               "--seed", "4", "--out", str(out)])
    assert rc == 0
    frame = pd.read_csv(out)
    assert list(frame["device"].unique()) == ["dev000", "dev001", "dev002"]
    assert {"t", "gx", "gy", "gz", "temp", "temp_ext", "ax", "ay", "az", "rx", "ry", "rz"} <= set(frame)
    batch, truth = simulate("thermal", 3, seed=4, duration=600.0)
    expected = batch.to_frame()
    for col in expected.columns:
        if col != "device":
            np.testing.assert_array_equal(frame[col].to_numpy(), expected[col].to_numpy())
    from diffgyro.io import load

    recs = load(out)
    for i, r in enumerate(recs):
        np.testing.assert_array_equal(r.gyro, batch.recording(i).gyro)
        np.testing.assert_array_equal(r.temp, batch.recording(i).temp)
    saved = json.loads((tmp_path / "x.truth.json").read_text())
    assert saved["spec"] == "bias_poly(2)"
    np.testing.assert_array_equal(np.array([d["beta"] for d in saved["devices"]]), truth.params.beta)


def test_cli_bad_input_one_line_errors(tmp_path, capsys):
    for argv in (["simulate", "--plan", "nope", "--out", str(tmp_path / "a.csv")],
                 ["simulate", "--plan", "thermal", "--effects", "bias_poly(2)+nope"],
                 ["simulate", "--plan", "six_face", "--set", "wobble=1"],
                 ["simulate", "--plan", "static", "--noise", "arw"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("diffgyro: error:") and "\n" not in err
    with pytest.raises(DataError):
        simulate("thermal", 0)
    with pytest.raises(SpecError):
        simulate("static", 1, preset="quartz")


def test_demo_batch_has_a_visible_hidden_effect():
    batch, truth = demo_batch(n_devices=2)
    assert truth.spec == "bias_poly(2)+gradient" and batch.n_devices == 2
    g = truth.params.beta[:, :, 3]  # gradient coefficient per axis
    peak = np.abs(g[:, :, None] * truth.env["dtemp"][:, None, :]).max(axis=-1)
    white = truth.noise.arw * math.sqrt(1.0)
    assert np.all(peak.max(axis=1) > 3 * white.max(axis=1))


def test_six_face_feeds_the_six_position_recipe_exactly():
    """At the pole Earth rate is vertical: the Ferraris recipe on noise-free six-face data
    returns the true accelerometer and gyro calibration, and g-sensitivity off by exactly
    (I + S + M)·Ω/g (Earth rate flips with the face, like gravity)."""
    from diffgyro.recipes import six_position

    batch, truth = simulate("six_face", 1, seed=0, latitude=90.0, tilt=0.0, noise="none", dwell=10.0)
    rec = batch.recording(0)
    res = six_position(rec.gyro, rec.accel, truth.info["sections"], t=rec.t,
                       rotation_angle=-2 * math.pi, gravity=G0).to_dict()
    beta = truth.params.beta[0]  # bias_poly(0), g_sens (3), scale_poly(0), misalignment (2)
    sm = np.diag(beta[:, 4])
    for i, others in enumerate(((1, 2), (0, 2), (0, 1))):
        sm[i, others[0]], sm[i, others[1]] = beta[i, 5], beta[i, 6]
    np.testing.assert_allclose(res["accel_bias"], truth.accel["bias"][0], atol=1e-12)
    np.testing.assert_allclose(res["accel_matrix"], truth.accel["matrix"][0], atol=1e-12)
    np.testing.assert_allclose(res["gyro_bias"], beta[:, 0], atol=1e-14)
    np.testing.assert_allclose(res["gyro_matrix"], np.linalg.inv(np.eye(3) + sm), atol=1e-12)
    # the measured Earth rate goes through scale factor and misalignment too
    np.testing.assert_allclose(res["g_sens"], beta[:, 1:4] + (np.eye(3) + sm) * EARTH_RATE / G0,
                               atol=1e-14)


def test_population_spreads_match_the_presets():
    """Coefficients are drawn in the model basis with the stated physical spreads:
    bias 0.5 °/s and slope 0.01 °/s/°C (MEMS), 1 °/h and 0.02 °/h/°C (FOG), whatever
    the normalisation's half-range."""
    from diffgyro.internal import FOG, MEMS, draw_params

    model = ErrorModel.from_spec("bias_poly(1)+misalignment+g_sens+thermal_lag+warmup")
    d = 2000
    for preset, c0, slope in ((MEMS, 0.5 * DEG, 0.01 * DEG), (FOG, DEG / 3600, 0.02 * DEG / 3600)):
        for scale in (50.0, 30.0):
            p = draw_params(model, preset, d, seed=1, temp_scale=scale)
            tol = rel_tol(3 * d)
            assert abs(p.beta[..., 0].std() / c0 - 1) < tol
            assert abs((p.beta[..., 1] / scale).std() / slope - 1) < tol
            assert abs(p.beta[..., 2:4].std() / preset.misalignment - 1) < tol
            assert abs(p.beta[..., 4:7].std() / preset.g_sens - 1) < tol
            # the bias polynomial sees the lagged temperature: l1 = c1
            np.testing.assert_array_equal(p.beta[..., 7], p.beta[..., 1])
            taus = np.exp(p.theta)
            assert taus[:, 0].min() >= preset.lag_tau[0] and taus[:, 0].max() <= preset.lag_tau[1]
            assert taus[:, 1].min() >= preset.warmup_tau[0] and taus[:, 1].max() <= preset.warmup_tau[1]
    assert FOG.arw < MEMS.arw / 100 and FOG.bias_instability < MEMS.bias_instability / 100
