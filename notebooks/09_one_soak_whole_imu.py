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
# # One soak, the whole IMU
#
# A flight controller with three IMUs goes through one thermal soak. Its gyros **and**
# its accelerometers drift with temperature, and both autopilots hold a correction for
# each. Here the soak's log goes in as a PX4 ULog and as an ArduPilot DataFlash log; both
# sensors of every IMU are calibrated from it, exported together, and applied **with each
# autopilot's own formula, written here from its source** (not by calling diffgyro) to a
# second, unseen soak.
#
# 1. simulate three IMUs: a cubic thermal offset on every gyro and accelerometer, and a
#    dT/dt term on IMU 2's accelerometer;
# 2. write the soak as a ULog (accelerometer instances in another order than the gyros',
#    each sensor with its own `device_id`) and as a DataFlash log;
# 3. read both back, fit the gyros and the accelerometers, diagnose the accelerometers;
# 4. `diffgyro export gyro.json --accel accel.json`, PX4 and ArduPilot;
# 5. apply the parameters to the unseen soak: each channel's residual before and after.
#
# With `DIFFGYRO_NOTEBOOK_QUICK` set (the test suite sets it) the soak is shorter.

# %%
import os
import struct
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pyulog

import diffgyro
from diffgyro.cli import main
from diffgyro.diagnose import diagnose
from diffgyro.io import LoadReport, load_batch
from diffgyro.model import Params
from diffgyro.simulate import simulate

diffgyro.enable_x64()
diffgyro.enable_compilation_cache()
work = Path(tempfile.mkdtemp(prefix="diffgyro-nb09-"))
QUICK = bool(os.environ.get("DIFFGYRO_NOTEBOOK_QUICK"))
RUN = {"sample_rate": 10.0, "duration": 1200.0 if QUICK else 3600.0}

# %% [markdown]
# ## 1. Three IMUs through a soak
#
# The accelerometers' thermal offsets in m/s² per unit of the scaled temperature
# `T_s = (T − centre) / scale` (about ±1 over the run), and IMU 2's dT/dt coefficient in
# m/s² per °C/s. The gyros' cubic is drawn by the simulator's MEMS preset.

# %%
MODEL, ACCEL = "bias_poly(3)", "bias_poly(3)+gradient"
beta = np.array([
    [[0.02, 0.09, 0.03, -0.02, 0.0], [-0.01, -0.05, 0.02, 0.015, 0.0], [0.03, 0.12, -0.04, 0.01, 0.0]],
    [[-0.03, 0.06, -0.02, 0.01, 0.0], [0.02, 0.08, 0.01, -0.02, 0.0], [-0.02, -0.10, 0.03, 0.02, 0.0]],
    [[0.01, -0.07, 0.02, 0.01, 0.6], [0.02, 0.05, -0.03, 0.0, -0.5], [-0.01, 0.09, 0.02, -0.01, 0.7]],
])
acc_params = Params(beta=beta, theta=np.zeros((3, 0)))
batch, truth = simulate("thermal", 3, effects=MODEL, seed=41, accel_effects=ACCEL,
                        accel_params=acc_params, **RUN)
unseen_plan = {"start_temp": 20.0, "profile": ((45.0, 1.5, 15.0), (0.0, 1.0, 15.0), (30.0, 0.5, 10.0))}
unseen, ut = simulate("thermal", 3, effects=MODEL, seed=42, params=truth.params,
                      temp_norm=truth.norm, accel_effects=ACCEL, accel_params=acc_params,
                      keep_components=True, **RUN, **unseen_plan)
fig, ax = plt.subplots(figsize=(8, 2.5))
for k in range(3):
    ax.plot(batch.t[k, :batch.n_valid[k]] / 60, batch.temp[k, :batch.n_valid[k]], label=f"IMU {k}")
ax.set_xlabel("time (min)")
ax.set_ylabel("°C")
ax.legend()
plt.show()

# %% [markdown]
# ## 2. The logs
#
# **ULog.** pyulog writes a `ULog` object back to a file; the message definitions (PX4's
# own `sensor_gyro` and `sensor_accel`) come from pyulog's real test log in
# `tests/data/px4`, whose data are replaced. Accelerometer instance k is IMU 2 − k's:
# on a real board the instance numbers of the two sensors need not agree, and a table
# matched by number instead of by `device_id` corrects one accelerometer with another's
# curve.

# %%
px4_data = next(p for p in (Path("../tests/data/px4"), Path("tests/data/px4")) if p.is_dir())
GYRO_IDS, ACCEL_IDS, ACCEL_IMU = [0x240012, 0x380022, 0x280032], [0x24A012, 0x38A022, 0x28A032], [2, 1, 0]


def microseconds(t):
    return 1_000_000 + np.round(np.asarray(t) * 1e6).astype(np.int64)


def write_ulog(path, b):
    ulog = pyulog.ULog(str(px4_data / "sample_log_small.ulg"), ["sensor_gyro", "sensor_accel"])
    for d in ulog.data_list:
        imu = d.multi_id if d.name == "sensor_gyro" else ACCEL_IMU[d.multi_id]
        n = int(b.n_valid[imu])
        new = {name: np.zeros(n, dtype=v.dtype) for name, v in d.data.items()}
        new["timestamp_sample"] = microseconds(b.t[imu, :n]).astype(np.uint64)
        new["timestamp"] = new["timestamp_sample"] + 250
        new["device_id"][:] = GYRO_IDS[imu] if d.name == "sensor_gyro" else ACCEL_IDS[d.multi_id]
        new["temperature"] = np.asarray(b.temp[imu, :n], np.float32)
        values = b.gyro if d.name == "sensor_gyro" else b.accel
        for j, axis in enumerate("xyz"):
            new[axis] = np.asarray(values[imu, :n, j], np.float32)
        d.data = new
    ulog.write_ulog(str(path))


ulg = work / "soak.ulg"
write_ulog(ulg, batch)

# %% [markdown]
# **DataFlash.** pymavlink reads DataFlash but does not write it, so the `IMU` messages
# are packed from the format's definition: `FMT` messages first, then each sample as
# `A3 95 type` and its fields (`TimeUS, I, GyrX..Z, AccX..Z, EG, EA, T`). IMU k's gyro
# and accelerometer share one message, instance `I` = k.

# %%
IMU_FMT = ("QBffffffIIf", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T")


def write_dataflash(path, b):
    out = bytearray()
    for typ, name, fmt, cols in ((128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"),
                                 (129, "IMU", *IMU_FMT)):
        length = 3 + struct.calcsize("<" + fmt.replace("n", "4s").replace("N", "16s")
                                     .replace("Z", "64s"))
        out += b"\xa3\x95\x80" + struct.pack("<BB4s16s64s", typ, length, name.encode(),
                                             fmt.encode(), cols.encode())
    events = sorted((int(us), k, i) for k in range(b.n_devices)
                    for i, us in enumerate(microseconds(b.t[k, :b.n_valid[k]])))
    g, a, temp = np.asarray(b.gyro), np.asarray(b.accel), np.asarray(b.temp)
    for us, k, i in events:
        out += b"\xa3\x95\x81" + struct.pack("<QB6fIIf", us, k, *g[k, i], *a[k, i], 0, 0, temp[k, i])
    path.write_bytes(bytes(out))


binlog = work / "soak.bin"
write_dataflash(binlog, batch)
print(f"{ulg.name}: {ulg.stat().st_size / 1e6:.1f} MB, {binlog.name}: {binlog.stat().st_size / 1e6:.1f} MB")

# %% [markdown]
# ## 3. Read back, fit, diagnose
#
# Read for the accelerometer channel, the ULog gives one device per `sensor_accel`
# instance with its own temperature and `device_id`; the gyro rides along to judge rest.

# %%
report = LoadReport()
acc_batch = load_batch([ulg], report=report, channel="accel")
print({dev: hex(i) for dev, i in report.device_ids.items()})
assert list(report.device_ids.values()) == ACCEL_IDS

cal_g, cal_a = work / "gyro.json", work / "accel.json"
assert main(["fit", str(ulg), "-m", MODEL, "--out", str(cal_g)]) == 0
assert main(["fit", str(ulg), "-m", f"accel: {MODEL}", "--out", str(cal_a)]) == 0

# %% [markdown]
# The discovery loop on the accelerometers: the cubic is enough for two of them; the
# third (accelerometer instance 0, IMU 2) misses a term that follows dT/dt. No autopilot
# parameter holds dT/dt, so its export carries a warning; the held-out numbers say how
# much a cubic leaves.

# %%
diag = diagnose(MODEL, acc_batch, ["gradient", "temp_diff"], channel="accel",
                greedy=False, synthesis=False, noise=False)
for d in diag.devices:
    best = "" if d.best is None else f" -> add {d.best.effect}"
    print(f"{d.device}: {d.verdict}{best} (held-out {d.heldout_rms:.2e}, floor {d.noise_floor:.2e} m/s²)")
assert diag.devices[0].verdict == "missing_effect" and diag.devices[0].best.effect == "gradient"

# %% [markdown]
# ## 4. Export both channels
#
# PX4: `TC_G{n}_*` and `TC_A{n}_*`, each slot with its sensor's `device_id`. ArduPilot:
# `INS_TCAL{n}_GYR*` and `INS_TCAL{n}_ACC*`, IMU by IMU, from the DataFlash log.

# %%
params_px4 = work / "thermal.params"
assert main(["export", str(cal_g), "--accel", str(cal_a), "--format", "px4",
             "--out", str(params_px4)]) == 0

cal_g2, cal_a2, params_ap = work / "gyro_df.json", work / "accel_df.json", work / "thermal.param"
assert main(["fit", str(binlog), "-m", MODEL, "--out", str(cal_g2)]) == 0
assert main(["fit", str(binlog), "-m", MODEL, "--channel", "accel", "--out", str(cal_a2)]) == 0
assert main(["export", str(cal_g2), "--accel", str(cal_a2), "--format", "ardupilot",
             "--out", str(params_ap)]) == 0

# %% [markdown]
# ## 5. Applied by the autopilots' formulas to the unseen soak
#
# **PX4** (TemperatureCompensation.cpp, `calc_thermal_offsets_3D`; the offset is
# subtracted from the raw reading): `dT = clamp(T, TMIN, TMAX) − TREF`,
# `offset = X0 + X1·dT + X2·dT² + X3·dT³`, in float32; slot found by `ID`.
# **ArduPilot** (AP_InertialSensor_tempcal.cpp, `TCal::correct_sensor`):
# `v −= P(T' − 35); v += P(Tcal' − 35); v −= offset`, `P(d) = (c1 + (c2 + c3·d)·d)·d·1e-6`.
# The accelerometer's constant is its offset calibration's (six positions or level), so
# its residual is judged less its mean.

# %%
def px4_values(path):
    out = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            _, _, name, value, typ = line.split("\t")
            out[name] = int(value) if typ == "6" else float(np.float32(value))
    return out


def px4_offset(p, letter, device_id, temp):
    n = next(n for n in range(4) if p.get(f"TC_{letter}{n}_ID") == device_id)
    q, f = f"TC_{letter}{n}_", np.float32
    d = np.clip(temp.astype(f), f(p[q + "TMIN"]), f(p[q + "TMAX"])) - f(p[q + "TREF"])
    return np.stack([sum(f(p[f"{q}X{k}_{i}"]) * d**k for k in range(4)) for i in range(3)], -1)


def ardupilot_correct(p, n, raw, temp, letters, cal_temp, offs):
    lo, hi = p[f"INS_TCAL{n}_TMIN"], p[f"INS_TCAL{n}_TMAX"]
    t, tc = np.clip(temp, lo, hi), np.clip(cal_temp, lo, hi)
    out = np.array(raw, float)
    for i, ax in enumerate("XYZ"):
        c = [p[f"INS_TCAL{n}_{letters}{k}_{ax}"] for k in (1, 2, 3)]

        def poly(d, c=c):
            return (c[0] + (c[1] + c[2] * d) * d) * d * 1e-6

        out[:, i] = out[:, i] - poly(t - 35.0) + poly(tc - 35.0) - offs[i]
    return out


def rms(x):
    return float(np.sqrt(np.mean(np.square(x - x.mean(0)))))


px4 = {name: float(v) for name, v in px4_values(params_px4).items()}
ap = {}
for line in params_ap.read_text().splitlines():
    if line.strip() and not line.startswith("#"):
        name, value = line.split(",")
        ap[name] = float(np.float32(value))

rows = []
for k in range(3):
    n = int(unseen.n_valid[k])
    g, a, temp = (np.asarray(x[k, :n]) for x in (unseen.gyro, unseen.accel, unseen.temp))
    rate = ut.env["rate"][k]
    clean = ((np.eye(3) + ut.accel["error_matrix"][k]) @ ut.env["specific_force"][k].T).T
    a_noise = a - clean - ut.accel["bias"][k] - ut.env["accel_thermal"][k]
    g_noise = g - rate - ut.env["error"][k]
    acc_id = ACCEL_IDS[ACCEL_IMU.index(k)]
    stem = "INS_GYROFFS" if k == 0 else f"INS_GYR{k + 1}OFFS"
    rows.append({
        "gyro": (rms(g - rate), rms(g - px4_offset(px4, "G", GYRO_IDS[k], temp) - rate),
                 rms(ardupilot_correct(ap, k + 1, g, temp, "GYR", ap[f"INS_GYR{k + 1}_CALTEMP"],
                                       [ap[f"{stem}_{ax}"] for ax in "XYZ"]) - rate),
                 rms(g_noise)),
        "accel": (rms(a), rms(a - px4_offset(px4, "A", acc_id, temp)),
                  rms(ardupilot_correct(ap, k + 1, a, temp, "ACC", 25.0, [0.0] * 3)),
                  rms(a_noise)),
    })
for k, r in enumerate(rows):
    for ch, (raw, p4, apc, noise) in r.items():
        print(f"IMU {k} {ch:5s}: raw {raw / noise:5.2f}x, PX4 {p4 / noise:5.3f}x, "
              f"ArduPilot {apc / noise:5.3f}x the noise added")

# %%
fig, axes = plt.subplots(1, 2, figsize=(9, 3), sharey=True)
for ax, ch in zip(axes, ("gyro", "accel")):
    x = np.arange(3)
    noise = np.array([r[ch][3] for r in rows])
    for j, (label, w) in enumerate((("raw", -0.27), ("PX4", -0.09), ("ArduPilot", 0.09))):
        ax.bar(x + w, [r[ch][j] for r in rows] / noise, 0.18, label=label)
    ax.axhline(1.0, color="k", lw=0.8, ls="--")
    ax.set_xticks(x, [f"IMU {k}" for k in range(3)])
    ax.set_title(f"{ch}: residual RMS on the unseen soak")
axes[0].set_ylabel("× noise added")
axes[0].legend()
plt.show()

# %% [markdown]
# The gyros and the cubic accelerometers end at the noise with either autopilot's
# formula. IMU 2's accelerometer keeps what its dT/dt term puts in: the autopilots'
# tables are functions of temperature alone. diagnose named the term; the export said
# the residual stands above the noise floor.

# %%
for k, r in enumerate(rows):
    assert r["gyro"][1] <= 1.05 * r["gyro"][3] and r["gyro"][2] <= 1.05 * r["gyro"][3], k
    if k < 2:
        assert r["accel"][1] <= 1.05 * r["accel"][3] and r["accel"][2] <= 1.05 * r["accel"][3], k
assert rows[2]["accel"][1] > 1.5 * rows[2]["accel"][3]
