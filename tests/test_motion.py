"""Motion awareness: simulated devices with known truth (at rest with thermal drift or
engine vibration: not flagged; turning: flagged; --static-only recovers the true bias), and
real public logs (a flight, a board turned by hand, hand rotations, six- and multi-position sessions flagged; logs of
vehicles on the ground not flagged), the fit's bias checked against pyulog's mean of the
static samples."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.io

from diffgyro import calibration
from diffgyro.cli import main
from diffgyro.data import Batch, Recording
from diffgyro.fit import fit
from diffgyro.internal import check_windows, window_stats
from diffgyro.motion import (
    MAX_RESOLUTION,
    MAX_WINDOWS,
    QUANTILE_WINDOWS,
    motion_check,
    noise_quantiles,
    window_sizes,
)
from diffgyro.status import STATUS_NAMES

DATA = Path(__file__).parent / "data"
FLIGHT = DATA / "px4" / "sample.ulg"
GROUND = [DATA / "px4" / "sample_log_small.ulg", DATA / "px4" / "sample_appended_multiple.ulg"]
BIAS = np.array([0.004, -0.0025, 0.0011])


def _device(name, *, turns=False, vibration=False, fs=100.0, duration=900.0, seed=0):
    """A gyro at rest whose bias drifts with a warm-up of 25 °C (0.002 rad/s/°C on x: slow
    thermal drift, 0.05 rad/s over the run), optionally turned (0.6 rad/s turns of 4 s about
    z, then back) or shaken by an engine (0.05 rad/s at 37 Hz)."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(fs * duration)) / fs
    temp = 20.0 + 25.0 * (1.0 - np.exp(-t / 300.0))
    gyro = BIAS + rng.normal(0.0, 0.003, (t.size, 3))
    gyro[:, 0] += 0.002 * (temp - temp[0])
    acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 0.02, (t.size, 3))
    if turns:
        for k, start in enumerate(np.arange(60.0, duration - 60.0, 60.0)):
            on = (t >= start) & (t < start + 4.0)
            gyro[on, 2] += 0.6 if k % 2 == 0 else -0.6
    if vibration:
        gyro += 0.05 * np.sin(2 * np.pi * 37.0 * t)[:, None] * np.array([1.0, 0.6, 0.3])
    return Recording(t=t, gyro=gyro, temp=temp, accel=acc, device=name)


@pytest.fixture(scope="module")
def simulated():
    return Batch.from_recordings([_device("drift"), _device("turns", turns=True, seed=1),
                                  _device("engine", vibration=True, fs=200.0, seed=2)])


def test_status_name_is_appended():
    assert STATUS_NAMES[-2:] == ("in_motion", "rest_unverified")
    assert STATUS_NAMES.index("failed") == 5


def test_simulated_rest_drift_and_vibration_are_not_motion_turns_are(simulated):
    m = motion_check(simulated)
    frac = np.asarray(m.moving_fraction)
    # 14 turns of 4 s in 900 s: 6.2 % of the samples
    assert frac[0] == 0.0 and frac[2] == 0.0
    assert 0.055 < frac[1] < 0.08
    assert 0.5 < float(m.rate_peak[1]) < 0.7
    assert float(m.rest_noise[0]) == pytest.approx(0.003, rel=0.15)
    res = fit("bias_poly(2)", simulated)
    assert [res.status_name(i) for i in range(3)] == ["ok", "in_motion", "ok"]
    rec = res.records()[1]
    assert rec["status_detail"].startswith("in_motion: 6 % of the recording moved")
    assert "--static-only" in rec["status_detail"]
    assert set(rec["motion"]) == {"moving_fraction", "rate_peak", "rate_rms", "turn_peak",
                                  "tilt_peak", "rest_rate", "rest_noise", "threshold", "resolution", "n_windows",
                                  "window_s", "verdict", "reason"}
    assert rec["motion"]["verdict"] == "in_motion" and rec["motion"]["turn_peak"] > 0.5


def test_static_only_recovers_the_true_bias(simulated):
    one = simulated.select([1])
    plain = fit("bias_poly(2)", one)
    static = fit("bias_poly(2)", one, static_only=True)
    assert static.status_name(0) == "ok"
    rec = static.records()[0]
    assert rec["static_only"] is True and rec["n_recorded"] == one.n_valid[0]
    assert rec["n_samples"] < 0.94 * rec["n_recorded"]
    # z carries the turns: the plain fit reads their mean, the static fit the bias
    truth = BIAS[2]
    se = 0.003 / np.sqrt(rec["n_samples"])
    z_plain = float(plain.params.beta[0, 2, 0])
    z_static = float(static.params.beta[0, 2, 0])
    assert abs(z_static - truth) < 6 * se * 3
    assert abs(z_plain - truth) > 20 * abs(z_static - truth)


def test_a_rate_reference_is_not_flagged():
    rec = _device("table", turns=True, duration=300.0)
    rate = np.zeros_like(rec.gyro)
    rate[:, 2] = rec.gyro[:, 2] - BIAS[2]
    rec = Recording(t=rec.t, gyro=rec.gyro, rate=np.round(rate, 1), device="table")
    assert motion_check(Batch.from_recordings([Recording(t=rec.t, gyro=rec.gyro)])).moved(0)
    for spec in ("bias_poly(0)+scale_poly(0)", "bias_poly(0)"):  # the fit subtracts the rate
        res = fit(spec, rec)
        assert res.records()[0]["motion"]["moving_fraction"] == 0.0
        # (a scale factor on x and y, which the table does not turn, is not supported)
        assert res.status_name(0) == ("ok" if spec == "bias_poly(0)" else "insufficient_range")


def test_a_device_is_judged_the_same_in_any_batch():
    """A device's check does not depend on the batch around it: checked alone and unpadded
    (the compiled check called on its own samples), and beside a longer device (its samples
    padded, its baseline extrapolated past its end as unpadded), the numbers agree to
    float32 rounding and the static masks are equal."""
    rec = _device("turns", duration=443.0, seed=3)
    w, b = window_sizes(0.01)  # 41 s blocks: the recording ends in the second half of one
    gyro = rec.gyro.copy()
    gyro[:, 0] += 1e-4 * rec.t  # a steady drift, and a slow turn in that last half block
    gyro[(rec.t >= 431.0) & (rec.t < 435.0), 2] += 0.03
    rec = Recording(t=rec.t, gyro=gyro, accel=rec.accel, temp=rec.temp, device="turns")
    n = rec.t.size
    alone = check_windows(*(window_stats(x[None], np.ones((1, n), bool), w, np.arange(1),
                                         -(-n // w), noise_quantiles(), QUANTILE_WINDOWS)
                            for x in (rec.gyro, rec.accel)), w, b)
    mixed = motion_check(Batch.from_recordings([rec, _device("long", duration=700.0)]))
    assert mixed.window[0] == w  # it moved: judged in the windows of its rate
    for k in ("moving_fraction", "rate_peak", "rate_rms", "rest_noise", "threshold"):
        np.testing.assert_allclose(float(getattr(mixed, k)[0]), float(alone[k][0]), rtol=1e-5,
                                   err_msg=k)
    assert abs(float(mixed.rate_peak[0]) / 0.03 - 1.0) < 0.1  # the turn, against the drift's line
    near = np.repeat(np.asarray(alone["window_near"][0]), w)[:n]
    np.testing.assert_array_equal(np.asarray(mixed.static[0, :n]), ~near)


def test_a_fast_thermal_transient_the_model_follows_is_not_motion():
    """A quiet gyro at 1 Hz whose bias follows a fast temperature step (time constant 20 s,
    0.002 rad/s per °C over 10 °C): window means leave any slow baseline, yet the model
    bias_poly(1) follows them, so its residual holds no motion and the fit is ok."""
    rng = np.random.default_rng(3)
    t = np.arange(1800.0)
    temp = 25.0 + 10.0 * (1.0 - np.exp(-np.clip(t - 600.0, 0.0, None) / 20.0))
    gyro = 0.001 + 0.002 * (temp - 25.0)[:, None] * np.ones(3) + rng.normal(0, 1e-4, (t.size, 3))
    rec = Recording(t=t, gyro=gyro, temp=temp, device="step")
    assert motion_check(Batch.from_recordings([rec])).moved(0)
    res = fit("bias_poly(1)", rec)
    assert res.status_name(0) == "ok"
    assert res.records()[0]["motion"]["moving_fraction"] == 0.0


# --------------------------------------------------------------------------- real logs


def _run(capsys, args):
    code = main(args)
    out = capsys.readouterr()
    return code, out.out + out.err


def _json(capsys, args):
    code = main(args)
    out = capsys.readouterr()
    assert code == 0, out.err
    return json.loads(out.out)


@pytest.fixture(scope="module")
def broad():
    d = scipy.io.loadmat(DATA / "broad" / "05_undisturbed_slow_rotation_with_breaks_B.mat")
    fs = float(d["sampling_rate"][0, 0])
    n = len(d["imu_gyr"])
    rec = Recording(t=np.arange(n) / fs, gyro=d["imu_gyr"], accel=d["imu_acc"], device="broad")
    return Batch.from_recordings([rec]), d["movement"].ravel() == 0


def test_broad_hand_rotations_flagged_and_static_matches_the_labels(broad):
    """BROAD trial 05: 49 % of the samples labelled moving; the check finds 49 %, and what it
    calls static is labelled rest (precision > 0.99)."""
    batch, rest = broad
    m = motion_check(batch)
    n = rest.size
    assert float(m.moving_fraction[0]) == pytest.approx(1.0 - rest.mean(), abs=0.03)
    static = np.asarray(m.static[0])[:n]
    assert (static & rest).sum() / static.sum() > 0.99
    assert (static & rest).sum() / rest.sum() > 0.9
    assert fit("bias_poly(0)", batch).status_name(0) == "in_motion"


def test_six_and_multi_position_sessions_are_flagged():
    import pandas as pd

    df = pd.read_csv(DATA / "imucal" / "example_ferraris_session.csv")
    six = Recording(t=df.n_samples.to_numpy() / 102.4,
                    gyro=np.deg2rad(df[["gyr_x", "gyr_y", "gyr_z"]].to_numpy()),
                    accel=df[["acc_x", "acc_y", "acc_z"]].to_numpy(), device="imucal")
    g = np.loadtxt(DATA / "imu_tk" / "xsens_gyro.mat")
    a = np.loadtxt(DATA / "imu_tk" / "xsens_acc.mat")
    multi = Recording(t=g[:, 0] - g[0, 0], gyro=g[:, 1:4] * 2.09e-4, accel=a[:, 1:4] * 2.41e-3,
                      device="imu_tk")
    res = fit("bias_poly(0)", [six, multi])
    assert [res.status_name(i) for i in range(2)] == ["in_motion", "in_motion"]
    frac = [r["motion"]["moving_fraction"] for r in res.records()]
    assert 0.1 < frac[0] < 0.3 and 0.15 < frac[1] < 0.45


def _pyulog_gyro(path):
    from pyulog import ULog

    d = ULog(str(path), ["sensor_combined"]).get_dataset("sensor_combined").data
    return np.column_stack([d[f"gyro_rad[{k}]"] for k in range(3)]).astype(np.float64)


def test_px4_log_turned_by_hand_is_flagged_and_static_only_fits_the_static_mean(tmp_path, capsys):
    doc = _json(capsys, ["fit", str(FLIGHT), "--model", "bias_poly(0)", "--json"])
    dev = doc["devices"][0]
    assert dev["status"] == "in_motion"
    assert dev["motion"]["rate_peak"] > 1.0
    cal = tmp_path / "cal.json"
    doc = _json(capsys, ["fit", str(FLIGHT), "--model", "bias_poly(0)", "--json", "--static-only",
                 "--out", str(cal)])
    dev = doc["devices"][0]
    assert dev["status"] == "ok" and dev["static_only"] is True
    # the reference reader's samples, masked with the detected static intervals
    from diffgyro.io import load

    batch = Batch.from_recordings(load([FLIGHT]))
    static = np.asarray(motion_check(batch).static[0])[:int(batch.n_valid[0])]
    ref = _pyulog_gyro(FLIGHT)[static].mean(axis=0)
    got = [dev["params"][ax]["bias_poly(0).c0"] for ax in "xyz"]
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)
    assert dev["n_samples"] == static.sum()
    saved = calibration.load(cal).devices[0]
    assert saved.static_only and saved.motion == dev["motion"]


@pytest.mark.parametrize("path", GROUND, ids=lambda p: p.name)
def test_px4_logs_on_the_ground_are_not_flagged(path, capsys):
    """Vehicles on the ground (land detector: landed; one armed with motors running):
    nothing moved, status ok, and the bias is pyulog's mean of the samples."""
    dev = _json(capsys, ["fit", str(path), "--model", "bias_poly(0)", "--json"])["devices"][0]
    assert dev["status"] == "ok", dev["status_detail"]
    assert dev["motion"]["moving_fraction"] < 0.02 and dev["motion"]["verdict"] == "at_rest"
    ref = _pyulog_gyro(path).mean(axis=0)
    got = [dev["params"][ax]["bias_poly(0).c0"] for ax in "xyz"]
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


def test_export_refuses_a_device_in_motion_unless_forced(tmp_path, capsys):
    cal = tmp_path / "cal.json"
    _json(capsys, ["fit", str(FLIGHT), "--model", "bias_poly(0)", "--json", "--out", str(cal)])
    assert calibration.load(cal).devices[0].motion["moving_fraction"] > 0.02
    for fmt in ("px4", "ardupilot", "c-header"):
        code, output = _run(capsys, ["export", str(cal), "--format", fmt])
        assert code == 2
        assert "sample/sensor_combined" in output and "in_motion" in output
        assert "--force" in output
        code, output = _run(capsys, ["export", str(cal), "--format", fmt, "--force", "-o",
                                  str(tmp_path / f"x.{fmt}")])
        assert code == 0, output
        text = (tmp_path / f"x.{fmt}").read_text()
        assert "written with --force" in text and "in_motion" in text


def test_allan_on_a_moving_recording_says_so(capsys):
    doc = _json(capsys, ["allan", str(FLIGHT), "--json", "--taus", "0.1,1"])
    dev = doc["devices"][0]
    assert dev["status"] == "in_motion" and "not the sensor's noise" in dev["status_detail"]
    code, output = _run(capsys, ["allan", str(FLIGHT), "--taus", "0.1,1"])
    assert "not the sensor's noise" in output
    doc = _json(capsys, ["allan", str(FLIGHT), "--json", "--taus", "0.1,1", "--static-only"])
    dev = doc["devices"][0]
    assert dev["status"] == "ok" and dev["static_only"] is True
    t0, t1 = dev["segment"]
    assert dev["n_samples"] < dev["n_recorded"] and t1 > t0
    code, output = _run(capsys, ["export", str(FLIGHT), "--format", "kalibr"])
    assert code == 2 and "in_motion" in output


def test_diagnose_gives_no_verdict_on_motion(capsys):
    dev = _json(capsys, ["diagnose", str(FLIGHT), "--model", "bias_poly(0)", "--json"])["devices"][0]
    assert dev["status"].startswith("in_motion")
    assert dev["motion"]["moving_fraction"] > 0.02
    assert dev["best"] is None and "no effect is named" in dev["explanation"]


def test_a_recipe_that_assumes_rest_says_it_moved_and_runs_on_the_static_part(tmp_path, capsys):
    """binned-thermal on a warm-up with turns about z: a warning and status in_motion; with
    --static-only the z offset is the true bias again (the x line is the thermal drift)."""
    path = tmp_path / "turns.csv"
    _device("d", turns=True).to_frame().to_csv(path, index=False)
    code, output = _run(capsys, ["recipe", "binned-thermal", str(path)])
    assert code == 0 and "in_motion" in output and "--static-only" in output
    plain = _json(capsys, ["recipe", "binned-thermal", str(path), "--json"])
    assert plain["status"] == "in_motion"
    static = _json(capsys, ["recipe", "binned-thermal", str(path), "--json", "--static-only"])
    assert static["status"] == "ok" and static["static_only"] is True
    def z_at_32(r):  # the z bias line read inside the run (its offset is at 0 °C)
        return r["offset"][2] + 32.0 * r["slope"][2]

    assert abs(z_at_32(static) - BIAS[2]) < 1e-4
    assert abs(z_at_32(plain) - BIAS[2]) > 2e-3
    assert static["slope"][0] == pytest.approx(0.002, rel=0.02)
    code, output = _run(capsys, ["recipe", "static-kalman", str(path), "--static-only"])
    assert code == 2 and "does not apply" in output


def test_a_random_walk_does_not_absorb_the_turns():
    """The state-space path: its smoothed bias could follow a turn, so the status reads the
    recording; --static-only fits the rest and finds the true z bias."""
    rec = _device("walk", turns=True, duration=240.0, fs=50.0)
    res = fit("bias_poly(0)+random_walk", rec)
    assert res.status_name(0) == "in_motion"
    static = fit("bias_poly(0)+random_walk", rec, static_only=True).records()[0]
    assert static["status"] == "ok" and static["static_only"] is True
    assert abs(static["params"]["z"]["bias_poly(0).c0"] - BIAS[2]) < 1e-4


ARDUPILOT = DATA / "ardupilot"


def _pymavlink_gyro(path: Path) -> dict[int, np.ndarray]:
    """Gyro samples of every IMU instance as pymavlink reads them (``I``, else IMU/IMU2)."""
    from pymavlink import DFReader

    reader = DFReader.DFReader_text if path.suffix.lower() == ".log" else DFReader.DFReader_binary
    log = reader(str(path), zero_time_base=False)
    out: dict[int, list] = {}
    while (m := log.recv_match(type=["IMU", "IMU2"])) is not None:
        k = int(m.I) if "I" in m.get_fieldnames() else (1 if m.get_type() == "IMU2" else 0)
        out.setdefault(k, []).append([m.GyrX, m.GyrY, m.GyrZ])
    return {k: np.asarray(v, float) for k, v in out.items()}


def test_ardupilot_flight_is_flagged_and_bench_log_is_not(capsys):
    """DataFlash logs from other projects: an ArduCopter 3.1 flight (both IMUs turned) is
    in_motion; 80 KiB of a 4.6 board on the bench holds 0.4 s of each IMU and 0.3 s of a
    2 kHz gyro batch, too short to show rest: every device rest_unverified with the
    reason, its biases still pymavlink's means of the samples."""
    flight = _json(capsys, ["fit", str(ARDUPILOT / "nan.log"), "--model", "bias_poly(0)",
                            "--json"])["devices"]
    assert [d["status"] for d in flight] == ["in_motion", "in_motion"]
    assert all(d["motion"]["moving_fraction"] > 0.3 for d in flight)
    bench = ARDUPILOT / "backend_log_80k.bin"
    devices = _json(capsys, ["fit", str(bench), "--model", "bias_poly(0)", "--json"])["devices"]
    assert all(d["status"] == "rest_unverified" for d in devices), [d["status"] for d in devices]
    assert all("too short to judge" in d["status_detail"] for d in devices)
    assert {d["motion"]["verdict"] for d in devices} == {"unverified"}
    ref = _pymavlink_gyro(bench)
    for d in devices:
        if "/imu" in d["device"]:
            k = int(d["device"].rsplit("imu", 1)[1])
            got = [d["params"][ax]["bias_poly(0).c0"] for ax in "xyz"]
            np.testing.assert_allclose(got, ref[k].mean(axis=0), rtol=0, atol=1e-9)


# --------------------------------------------------------------------------- the verdict


def _quiet(n, fs, seed=0, accel=True):
    """A gyro at rest (white noise 3e-3 rad/s, the module's BIAS) with gravity on z."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    acc = np.array([0.0, 0.0, 9.81]) + rng.normal(0.0, 0.02, (n, 3)) if accel else None
    return t, BIAS + rng.normal(0.0, 0.003, (n, 3)), acc


def test_too_short_to_judge_is_rest_unverified_and_export_refuses(tmp_path, capsys):
    """Three seconds at 100 Hz hold 9 windows: not enough to know the rest noise, so the
    device is rest_unverified (never "moving 0 %"), with the reason, and not exported."""
    t, g, a = _quiet(300, 100.0)
    rec = Recording(t=t, gyro=g, accel=a, device="short")
    res = fit("bias_poly(0)", rec)
    r = res.records()[0]
    assert r["status"] == "rest_unverified" and r["motion"]["verdict"] == "unverified"
    assert "too short to judge" in r["status_detail"] and "16 windows" in r["status_detail"]
    path = tmp_path / "short.csv"
    rec.to_frame().to_csv(path, index=False)
    cal = tmp_path / "cal.json"
    _json(capsys, ["fit", str(path), "--model", "bias_poly(0)", "--json", "--out", str(cal)])
    code, output = _run(capsys, ["export", str(cal), "--format", "px4"])
    assert code == 2 and "rest_unverified" in output


def test_a_slow_log_with_no_quiet_part_is_not_at_rest():
    """A flight logged at 8 Hz: turns all along (0.3 to 2 rad/s), no still window. Its
    'quietest' windows set a threshold of tenths of a rad/s, too coarse to show a turn of
    a degree: not ok, whatever its moving fraction."""
    fs, n = 8.0, 960
    t = np.arange(n) / fs
    rng = np.random.default_rng(5)
    turn = sum(a * np.sin(2 * np.pi * f * t[:, None] + p) for a, f, p in
               zip(rng.uniform(0.3, 2.0, (6, 3)), rng.uniform(0.05, 1.5, (6, 1)),
                   rng.uniform(0, 6, (6, 3))))
    rec = Recording(t=t, gyro=BIAS + turn + rng.normal(0, 0.003, (n, 3)), device="flight")
    m = motion_check(Batch.from_recordings([rec]))
    assert m.status(0) in ("in_motion", "rest_unverified"), m.record(0)
    assert fit("bias_poly(0)", rec).status_name(0) != "ok"


def test_steady_spin_after_rest_keeps_only_the_rest():
    """A minute at rest, then a steady 0.9 rad/s roll about the vertical (gravity does not
    move) for the rest of the record: the plain fit is in_motion; --static-only keeps the
    first minute only, lists it, and its bias is the true one."""
    fs = 50.0
    t, g, a = _quiet(int(150 * fs), fs, seed=2)
    spin = np.clip(t - 60.0, 0.0, 1.0) * 0.9  # spun up over a second
    g = g.copy()
    g[:, 2] += spin
    rec = Recording(t=t, gyro=g, accel=a, device="rocket")
    assert fit("bias_poly(0)", rec).status_name(0) == "in_motion"
    r = fit("bias_poly(0)", rec, static_only=True).records()[0]
    assert r["status"] == "ok", r["status_detail"]
    spans = r["motion"]["rest_intervals"]
    assert spans and all(end <= 60.0 for _, end, _ in spans)
    assert r["motion"]["rest_kept_s"] > 50.0
    got = [r["params"][ax]["bias_poly(0).c0"] for ax in "xyz"]
    np.testing.assert_allclose(got, BIAS, atol=5 * 0.003 / np.sqrt(50 * fs))


def test_a_slow_tilt_is_motion_by_gravity():
    """A turn of 5° about x over 20 s, held, and back: too slow for the gyro's windows to
    reach ten thresholds, but gravity turns with it: in_motion, with the tilt reported."""
    fs = 20.0
    t, g, a = _quiet(int(240 * fs), fs, seed=3)
    u = t - 60.0
    w = np.radians(5.0) / 20.0
    rate = np.where((u >= 0) & (u < 20), w, 0.0) - np.where((u >= 40) & (u < 60), w, 0.0)
    ang = np.cumsum(rate) / fs
    g = g.copy()
    g[:, 0] += rate
    a = a.copy()
    a[:, 1], a[:, 2] = np.cos(ang) * a[:, 1] + np.sin(ang) * a[:, 2], -np.sin(ang) * a[:, 1] + np.cos(ang) * a[:, 2]
    m = motion_check(Batch.from_recordings([Recording(t=t, gyro=g, accel=a, device="tilt")]))
    rec = m.record(0)
    assert rec["verdict"] == "in_motion" and rec["tilt_peak"] >= np.radians(0.5), rec
    assert "gravity tilted" in rec["reason"]


def test_devices_at_other_rates_are_judged_in_windows_of_their_own():
    """A 1 kHz gyro batch of 0.3 s beside a 25 Hz IMU of a minute, in one batch: the short
    fast one is too short to judge (not at rest in windows of the slow one's length)."""
    t1, g1, a1 = _quiet(300, 1000.0, seed=4)
    t2, g2, a2 = _quiet(1500, 25.0, seed=5)
    m = motion_check(Batch.from_recordings([Recording(t=t1, gyro=g1, accel=a1, device="fast"),
                                            Recording(t=t2, gyro=g2, accel=a2, device="slow")]))
    assert [m.record(i)["verdict"] for i in range(2)] == ["unverified", "at_rest"]
    assert m.window_s[0] < 0.5 and m.window_s[1] > 0.1 and m.window[0] != m.window[1]


def test_export_warns_of_a_model_limit_and_refuses_an_unexplained_residual(tmp_path, capsys):
    """The residual rule: a cubic on a run whose bias also follows dT/dt stands a few times
    over its floor (written, with a warning naming the factor and diagnose); a constant on
    a steep thermal bias stands far over it (refused unless --force, which says so)."""
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 1, effects="bias_poly(2)+gradient", seed=0, sample_rate=2.0,
                        duration=3600.0)
    from diffgyro.io import save

    path = save(batch, tmp_path / "x.csv")
    # a bias of 2 mrad/s per °C over 40 °C against 3e-4 rad/s of noise, at rest
    t, g, a = _quiet(7200, 2.0, seed=6)
    temp = 20.0 + 40.0 * t / t[-1]
    steep = save(Recording(t=t, gyro=BIAS + 0.1 * (g - BIAS) + 2e-3 * (temp - 40.0)[:, None],
                           temp=temp, accel=a, device="steep"), tmp_path / "steep.csv")
    for model, expect in (("bias_poly(3)", "warn"), ("bias_poly(0)", "refuse")):
        path = steep if expect == "refuse" else path
        cal = tmp_path / f"{expect}.json"
        dev = _json(capsys, ["fit", str(path), "--model", model, "--json", "--out", str(cal)])["devices"][0]
        ratio = dev["residual_ratio"]
        code, output = _run(capsys, ["export", str(cal), "--format", "px4", "-o", str(tmp_path / f"{expect}.params")])
        if expect == "warn":
            assert 3.0 < ratio <= 10.0 and code == 0, (ratio, output)
            assert f"{ratio:.3g}x its noise floor" in output and "diagnose" in output
            assert "diagnose" in (tmp_path / f"{expect}.params").read_text()
        else:
            assert ratio > 10.0 and code == 2 and "--force" in output, (ratio, output)
            code, output = _run(capsys, ["export", str(cal), "--format", "px4", "--force", "-o",
                                         str(tmp_path / "forced.params")])
            assert code == 0 and "written with --force" in (tmp_path / "forced.params").read_text()


def test_a_long_recording_at_rest_is_shown_in_long_windows_and_a_knock_in_its_rates():
    """A long recording of a quiet gyro (an hour at 10 Hz, 3e-4 rad/s) is first judged
    in long windows, which show a turn of a degree: at rest it stays there; knocked once
    (turned by 1 rad/s for 0.3 s), it is judged again in its rate's windows, which place
    the knock within a few seconds. So is one tapped and turned back (a long window
    then holds no angle, but is loud), and a noisy gyro, whose long windows cannot show a
    degree."""
    t, g, a = _quiet(36_000, 10.0, seed=7)
    noisy = g
    g = BIAS + 0.1 * (g - BIAS)
    knocked = g.copy()
    on = (t >= 3000.0) & (t < 3000.3)
    knocked[on, 0] += 1.0
    tapped = g.copy()  # and back: no angle left in a long window, but a loud one
    tapped[(t >= 2000.0) & (t < 2000.2), 1] += 1.0
    tapped[(t >= 2000.2) & (t < 2000.4), 1] -= 1.0
    m = motion_check(Batch.from_recordings([Recording(t=t, gyro=g, accel=a, device="rest"),
                                            Recording(t=t, gyro=knocked, accel=a, device="knock"),
                                            Recording(t=t, gyro=noisy, accel=a, device="noisy"),
                                            Recording(t=t, gyro=tapped, accel=a, device="tapped")]))
    own = window_sizes(0.1)[0]
    assert [m.record(i)["verdict"] for i in range(3)] == ["at_rest", "in_motion", "at_rest"]
    assert m.window[0] > own and m.n_windows[0] <= MAX_WINDOWS
    assert m.resolution[0] <= MAX_RESOLUTION
    assert m.window[1] == own and m.window[2] == own and m.window[3] == own
    moving = ~np.asarray(m.static[1, :t.size])
    assert moving[on].all() and moving.sum() <= 8 * own  # the knock, within a few seconds


def test_a_spin_for_the_whole_recording_is_not_a_bias():
    """A steady 0.9 rad/s roll from start to end: a bias term absorbs it (the fit's
    residual is white), but no gyro's bias is that large, so the fit stays in_motion and
    says why."""
    t, g, a = _quiet(int(150 * 50.0), 50.0, seed=2)
    g = g.copy()
    g[:, 2] += 0.9
    r = fit("bias_poly(0)", Recording(t=t, gyro=g, accel=a, device="spin")).records()[0]
    assert r["status"] == "in_motion"
    assert "turns steadily at 0.9 rad/s" in r["status_detail"]
