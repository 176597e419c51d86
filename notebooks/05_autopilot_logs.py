# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # Autopilot logs in, PX4 parameters out: the round trip
#
# A flight controller with three IMUs sits in a thermal chamber. Its log goes
# in as a PX4 ULog (and, from a ROS driver, as a ROS 2 bag); the calibration
# comes out as the `TC_G{N}_*` temperature-compensation parameters that PX4
# reads. Then the parameters are applied **with PX4's own formula, written
# here from PX4's documentation** (not by calling diffgyro) to a second,
# unseen chamber run, and the residual must be at the noise.
#
# 1. simulate a three-IMU thermal run with a cubic thermal bias, `bias_poly(3)`;
# 2. write it as a ULog through pyulog and as a ROS 2 bag through rosbags;
# 3. read both back with `diffgyro.io.load`, fit, diagnose;
# 4. `diffgyro export cal.json --format px4`;
# 5. apply `TC_G{N}_*` as PX4 does to unseen data: residual RMS within 5 % of
#    the noise the simulator added.

# %%
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import diffgyro
from diffgyro import calibration
from diffgyro.cli import main
from diffgyro.diagnose import diagnose
from diffgyro.fit import fit
from diffgyro.io import load
from diffgyro.simulate import simulate

diffgyro.enable_x64()
diffgyro.enable_compilation_cache()
work = Path(tempfile.mkdtemp(prefix="diffgyro-nb05-"))

# %% [markdown]
# ## 1. Three IMUs in a chamber
#
# One hour at 10 Hz (the ULog reader takes `sensor_gyro` from 10 samples/s
# up; PX4 logs it at 1 Hz unless `SDLOG_PROFILE` asks for more), the chamber
# cooled, heated, cooled back; each IMU lags the chamber and self-heats in
# its own way. The gyro bias is a cubic of the sensor temperature, different
# for each IMU; the noise is the MEMS preset's (white, flicker, rate random
# walk, output quantisation).

# %%
MODEL = "bias_poly(3)"
RATE = 10.0
batch, truth = simulate("thermal", 3, effects=MODEL, seed=21, sample_rate=RATE, duration=3600.0)
recs = [batch.recording(i) for i in range(batch.n_devices)]
fig, ax = plt.subplots(figsize=(8, 2.5))
for k, rec in enumerate(recs):
    ax.plot(rec.t / 60, rec.temp, label=f"IMU {k}")
ax.plot(recs[0].t / 60, recs[0].temp_ext, "k--", lw=0.8, label="chamber")
ax.set_xlabel("time (min)")
ax.set_ylabel("°C")
ax.legend(ncol=4)
plt.show()

# %% [markdown]
# ## 2. Write the flight log: PX4 ULog and ROS 2 bag
#
# **ULog.** pyulog writes a `ULog` object back to a file; it has no builder
# for new logs, so the message definitions (PX4's own `sensor_gyro` and
# `sensor_accel` formats) come from a real PX4 log, pyulog's test log
# `sample_log_small.ulg` (BSD-3-Clause, in `tests/data/px4`), and its data
# are replaced by the simulation: one `sensor_gyro` and one `sensor_accel`
# instance per IMU, time in µs since boot (`timestamp_sample`), the
# temperature in each gyro message, and the `device_id` of the real log's
# three IMUs — the id PX4 matches its `TC_G{N}_ID` parameters against.

# %%
import pyulog  # noqa: E402

px4_data = next(p for p in (Path("../tests/data/px4"), Path("tests/data/px4")) if p.is_dir())
T0_US = 20_000_000  # the run starts 20 s after boot


def microseconds(t):
    return T0_US + np.round(np.asarray(t) * 1e6).astype(np.int64)


def write_ulog(path, recs):
    ulog = pyulog.ULog(str(px4_data / "sample_log_small.ulg"), ["sensor_gyro", "sensor_accel"])
    ids = {}
    for d in ulog.data_list:
        rec = recs[d.multi_id]
        n = rec.t.size
        new = {name: np.zeros(n, dtype=v.dtype) for name, v in d.data.items()}
        new["timestamp_sample"] = microseconds(rec.t).astype(np.uint64)
        new["timestamp"] = new["timestamp_sample"] + 250  # published a little later
        new["device_id"][:] = d.data["device_id"][0]
        new["temperature"] = rec.temp.astype(np.float32)
        values = rec.gyro if d.name == "sensor_gyro" else rec.accel
        for j, axis in enumerate("xyz"):
            new[axis] = values[:, j].astype(np.float32)
        d.data = new
        ids[d.multi_id] = int(d.data["device_id"][0])
    ulog.write_ulog(str(path))
    return [ids[k] for k in range(len(recs))]


ulg = work / "chamber.ulg"
device_ids = write_ulog(ulg, recs)
print(f"{ulg.name}: {ulg.stat().st_size / 1e6:.1f} MB, sensor_gyro device_ids {device_ids}")

# %% [markdown]
# **ROS 2 bag.** A ROS driver publishes `sensor_msgs/msg/Imu` on one topic per
# IMU and the die temperature as `sensor_msgs/msg/Temperature` at a lower
# rate (here 1 Hz) on a topic of the same namespace; the reader joins it to
# the Imu stamps by linear interpolation (docs/formats.md). Written with
# rosbags' writer in MCAP storage.

# %%
from rosbags.rosbag2 import StoragePlugin, Writer  # noqa: E402
from rosbags.typesys import Stores, get_typestore  # noqa: E402


def write_bag(path, recs):
    store = get_typestore(Stores.ROS2_HUMBLE)
    ty = store.types
    Imu, Temperature = ty["sensor_msgs/msg/Imu"], ty["sensor_msgs/msg/Temperature"]
    Header, Time = ty["std_msgs/msg/Header"], ty["builtin_interfaces/msg/Time"]
    Vector3, Quaternion = ty["geometry_msgs/msg/Vector3"], ty["geometry_msgs/msg/Quaternion"]
    unknown = np.zeros(9)
    with Writer(path, version=8, storage_plugin=StoragePlugin.MCAP) as writer:
        for k, rec in enumerate(recs):
            imu = writer.add_connection(f"/imu{k}/data", Imu.__msgtype__, typestore=store)
            temp = writer.add_connection(f"/imu{k}/temperature", Temperature.__msgtype__,
                                         typestore=store)
            for i, us in enumerate(microseconds(rec.t).tolist()):
                header = Header(stamp=Time(sec=us // 1_000_000, nanosec=us % 1_000_000 * 1000),
                                frame_id=f"imu{k}")
                w, a = rec.gyro[i], rec.accel[i]
                msg = Imu(header=header, orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                          orientation_covariance=unknown,
                          angular_velocity=Vector3(x=w[0], y=w[1], z=w[2]),
                          angular_velocity_covariance=unknown,
                          linear_acceleration=Vector3(x=a[0], y=a[1], z=a[2]),
                          linear_acceleration_covariance=unknown)
                writer.write(imu, us * 1000, store.serialize_cdr(msg, Imu.__msgtype__))
                if i % int(RATE) == 0:
                    msg = Temperature(header=header, temperature=float(rec.temp[i]), variance=0.0)
                    writer.write(temp, us * 1000, store.serialize_cdr(msg, Temperature.__msgtype__))


bag = work / "chamber_ros2"
write_bag(bag, recs)
print(f"{bag.name}/: {sorted(p.name for p in bag.iterdir())}")

# %% [markdown]
# ## 3. Read both back, fit, diagnose
#
# `diffgyro.io.load` picks the reader by extension (a rosbag2 folder by its
# `metadata.yaml`) and checks the first bytes; every log comes back as the
# same validated recordings as a CSV would. The ULog holds float32 values
# (as PX4 logs them), the bag float64, so the two agree to float32 rounding.

# %%
from_ulog, from_bag = load(ulg), load(bag)
for a, b in zip(from_ulog, from_bag, strict=True):
    dtemp = float(np.sqrt(np.mean((a.temp - b.temp) ** 2)))
    print(f"{a.device:14s} {a.t.size} samples, {a.temp.min():6.2f} … {a.temp.max():5.2f} °C  |  "
          f"{b.device:24s} {b.t.size} samples, temperature differs by {dtemp:.3f} °C RMS")
    assert a.t.size == b.t.size == RATE * 3600
    assert np.allclose(a.t, b.t, rtol=0, atol=1e-9) and np.allclose(a.gyro, b.gyro, atol=1e-8)
    assert dtemp < 0.03  # the 0.01 °C read-out noise: per sample in the ULog, 1 Hz in the bag

# %% [markdown]
# Fit the cubic on the ULog; the bag gives the same calibration to far below
# the noise (the largest difference of the two fitted bias curves over the
# calibrated range, against the noise floor).

# %%
res_ulog = fit(MODEL, from_ulog)
res_bag = fit(MODEL, from_bag)
cal = calibration.from_fit(res_ulog, batch=None)
cal_bag = calibration.from_fit(res_bag, batch=None)


def bias_curve(dev, temp):
    """b(T) of a bias_poly calibration (docs/export.md), T clamped to the calibrated range."""
    ts = (np.clip(temp, *dev.temp_range) - dev.temp_centre) / dev.temp_scale
    return np.stack([np.polyval(np.asarray(dev.beta[i])[::-1], ts) for i in range(3)], -1)


for d_u, d_b in zip(cal.devices, cal_bag.devices, strict=True):
    grid = np.linspace(*d_u.temp_range, 200)
    diff = np.max(np.abs(bias_curve(d_u, grid) - bias_curve(d_b, grid)))
    floor = d_u.quality["noise_floor"]
    print(f"{d_u.device}: status {d_u.status}, held-out RMS {d_u.quality['heldout_rms']:.3g} rad/s, "
          f"noise floor {floor:.3g};  ULog vs bag fit differ by ≤ {diff:.2g} rad/s "
          f"({diff / floor:.1%} of the floor)")
    assert diff < 0.05 * floor

# %% [markdown]
# The diagnosis checks the model before anything is exported: no registered
# effect, tried on held-out time blocks, improves on the cubic by a material
# amount against the noise floor.

# %%
dg = diagnose(MODEL, from_ulog, base_fit=res_ulog)
for d in dg.devices:
    print(d.explanation)
assert all(d.verdict == "adequate" for d in dg.devices)

# %% [markdown]
# ## 4. Export the PX4 parameters
#
# The calibration file, then the command line's exporter. `--device-id` gives
# each IMU's `sensor_gyro.device_id` (PX4 applies slot N only to the sensor
# whose id equals `TC_G{N}_ID`). The report line states the error that
# PX4's float32 parameters add, against the noise floor.

# %%
cal_path = work / "cal.json"
calibration.save(cal, cal_path)
params_path = work / "tc_gyro.params"
code = main(["export", str(cal_path), "--format", "px4", "--device-id",
             ",".join(map(str, device_ids)), "--out", str(params_path)])
assert code == 0
print(params_path.read_text())

# %% [markdown]
# From the command line the same is
#
# ```
# diffgyro fit chamber.ulg --model 'bias_poly(3)' --out cal.json
# diffgyro diagnose chamber.ulg --model 'bias_poly(3)'
# diffgyro export cal.json --format px4 --device-id 2424842,3670050,2621474 --out tc_gyro.params
# ```
#
# and QGroundControl loads `tc_gyro.params` (Parameters → Tools → Load from file).

# %% [markdown]
# ## 5. Apply them as PX4 does, on unseen data
#
# PX4's thermal calibration guide (en/advanced_config/sensor_thermal_calibration.md)
# and `TemperatureCompensation::calc_thermal_offsets_3D`
# (src/modules/temperature_compensation/TemperatureCompensation.cpp):
#
#     delta = clamp(T, TC_Gn_TMIN, TC_Gn_TMAX) − TC_Gn_TREF
#     offset = TC_Gn_X0 + TC_Gn_X1·delta + TC_Gn_X2·delta² + TC_Gn_X3·delta³   (per axis, float)
#     corrected = raw − offset
#
# where `n` is the slot whose `TC_Gn_ID` is the sensor's `device_id`. Written
# here from that description, reading the parameter file as QGroundControl
# does (vehicle, component, name, value, type; `#` comments).

# %%
def read_qgc_params(text):
    out = {}
    for line in text.splitlines():
        if line.strip() and not line.startswith("#"):
            _vehicle, _component, name, value, typ = line.split("\t")
            out[name] = int(value) if typ == "6" else np.float32(value)
    return out


def px4_correct(p, device_id, gyro, temp):
    """PX4's gyro temperature compensation of raw rates (n, 3) at temperatures (n,)."""
    slot = next(n for n in range(4) if p.get(f"TC_G{n}_ID") == device_id)
    f = np.float32
    t = np.clip(temp.astype(f), p[f"TC_G{slot}_TMIN"], p[f"TC_G{slot}_TMAX"])
    delta = t - p[f"TC_G{slot}_TREF"]
    offset = np.stack([p[f"TC_G{slot}_X0_{i}"] + p[f"TC_G{slot}_X1_{i}"] * delta
                       + p[f"TC_G{slot}_X2_{i}"] * delta**2 + p[f"TC_G{slot}_X3_{i}"] * delta**3
                       for i in range(3)], axis=-1)
    return gyro.astype(f) - offset


params = read_qgc_params(params_path.read_text())
assert params["TC_G_ENABLE"] == 1

# %% [markdown]
# The unseen run: the same three IMUs (the true coefficients and noise
# levels of the first run), another day — other ramps, another thermal
# response of the mounting, another noise realisation — kept inside the
# calibrated range of every IMU. The simulator keeps the
# true rate (zero: the board is still) and every noise component, so the
# noise actually added is known sample by sample.

# %%
unseen, unseen_truth = simulate(
    "thermal", 3, effects=MODEL, seed=22, params=truth.params, temp_norm=truth.norm,
    noise=truth.noise, keep_components=True, sample_rate=RATE, duration=3600.0,
    start_temp=25.0, profile=((42.0, 1.0, 8.0), (10.0, 1.0, 8.0), (30.0, 0.5, 0.0)))


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


rows = []
fig, axs = plt.subplots(1, 3, figsize=(12, 3.2), sharey=True)
for k, dev_id in enumerate(device_ids):
    n = int(unseen.n_valid[k])
    raw = np.asarray(unseen.gyro[k, :n], float)
    temp = np.asarray(unseen.temp[k, :n], float)
    rate = unseen_truth.env["rate"][k]
    noise = raw - rate - unseen_truth.env["error"][k]
    slot = next(s for s in range(4) if params[f"TC_G{s}_ID"] == dev_id)
    assert params[f"TC_G{slot}_TMIN"] < temp.min() and temp.max() < params[f"TC_G{slot}_TMAX"]
    before = raw - rate
    after = px4_correct(params, dev_id, raw, temp) - rate
    rows.append((k, dev_id, rms(before), rms(after), rms(noise)))
    ax = axs[k]
    ax.plot(temp[::5], before[::5, 2], ".", ms=1.5, alpha=0.5, label="raw − true rate (z)")
    ax.plot(temp[::5], after[::5, 2], ".", ms=1.5, alpha=0.5, label="PX4-corrected (z)")
    ax.axhspan(-rms(noise), rms(noise), color="k", alpha=0.15, label="± noise RMS")
    ax.set_title(f"IMU {k} (TC_G{slot}, id {dev_id})")
    ax.set_xlabel("temperature (°C)")
axs[0].set_ylabel("rad/s")
axs[0].legend(markerscale=6, fontsize=8)
plt.show()

print("IMU  device_id  raw RMS     corrected RMS  noise RMS   corrected/noise")
for k, dev_id, b, a, s in rows:
    print(f"{k:3d}  {dev_id:9d}  {b:.3e}   {a:.3e}      {s:.3e}   {a / s:.4f}")

# %% [markdown]
# The residual after PX4's correction is the noise the simulator added —
# white, flicker, random walk and quantisation — to within 5 %; the thermal
# bias it removed was many times larger.

# %%
for k, _, before_rms, after_rms, noise_rms in rows:
    assert abs(after_rms / noise_rms - 1.0) <= 0.05, (k, after_rms, noise_rms)
    assert before_rms > 5 * noise_rms, (k, before_rms, noise_rms)

# %% [markdown]
# The residual over time for one IMU, and its Allan deviation against the
# noise alone: what is left after the correction is the noise (the +½
# random-walk slope at long τ is the simulated bias walk, which no
# temperature model removes).

# %%
from diffgyro.allan import allan  # noqa: E402

k = 0
n = int(unseen.n_valid[k])
raw = np.asarray(unseen.gyro[k, :n], float)
temp = np.asarray(unseen.temp[k, :n], float)
rate = unseen_truth.env["rate"][k]
after = px4_correct(params, device_ids[k], raw, temp) - rate
noise = raw - rate - unseen_truth.env["error"][k]
curves = allan(np.stack([after.T, noise.T]), 1.0 / RATE)
fig, axs = plt.subplots(1, 2, figsize=(11, 3))
t_min = np.arange(n) / RATE / 60
axs[0].plot(t_min, raw[:, 2] - rate[:, 2], lw=0.5, label="raw − true rate (z)")
axs[0].plot(t_min, after[:, 2], lw=0.5, label="PX4-corrected (z)")
axs[0].set_xlabel("time (min)")
axs[0].set_ylabel("rad/s")
axs[0].legend()
tau = np.asarray(curves.tau)
axs[1].loglog(tau[0, 2], np.asarray(curves.adev)[0, 2], label="PX4-corrected (z)")
axs[1].loglog(tau[1, 2], np.asarray(curves.adev)[1, 2], "--", label="noise added (z)")
axs[1].set_xlabel("τ (s)")
axs[1].set_ylabel("Allan deviation (rad/s)")
axs[1].legend()
plt.show()

# %% [markdown]
# The log files, calibration and parameter file were written to a temporary
# folder; remove it.

# %%
import shutil  # noqa: E402

shutil.rmtree(work)
