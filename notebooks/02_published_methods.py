# ---
# jupyter:
#   jupytext:
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#   kernelspec:
#     display_name: Python 3
#     language: python
#     name: python3
# ---

# %% [markdown]
# # The published methods, run as published — and what a richer model adds
#
# diffgyro starts from five published gyro-compensation methods (patents; the
# docs' *Published methods* page describes them)
# and two classic calibrations. Each is a *recipe*: the procedure step by
# step, with the published choices (bin width, thresholds, Kalman `Q`, the
# six regression columns, the up/down face sets, the Ferraris algebra). On
# the command line they are `diffgyro recipe NAME DATA`.
#
# For each recipe this notebook
#
# 1. runs it on data whose truth is known (simulated) or on a public recording,
# 2. feeds the *same* data to a toolkit model with the effect the recipe
#    leaves out (curvature, a gradient, cross-axis coupling, drift) and shows
#    by how much the error falls.
#
# All rates are in rad/s unless said otherwise.

# %%
import time

import jax.numpy as jnp
import numpy as np

import diffgyro
from diffgyro.data import Recording
from diffgyro.model import Params
from diffgyro.recipes import (
    attitude_reference,
    binned_thermal,
    cube_bias,
    fog_one_run,
    multi_position,
    single_axis,
    six_position,
    static_kalman,
    toolkit_compensate,
)
from diffgyro.signals import TempNorm
from diffgyro.simulate import simulate

diffgyro.enable_x64()
diffgyro.enable_compilation_cache()  # as the command line does: compiled fits are reused
DEG = np.pi / 180
started, cpu_started = time.perf_counter(), time.process_time()
summary = []   # (recipe, what it leaves out, error measure, recipe error, toolkit model, toolkit error)

# %% [markdown]
# ## binned-thermal: bias vs temperature by binning and a straight line
#
# A static gyro warms from cold (self-heating, then a lamp). The recipe sorts
# by temperature, cuts 0.1 °C bins, sub-samples every bin to the same count,
# averages, fits `bias = a + b·T` per axis and accepts it if |r| > 0.999.
# The simulated bias is slightly curved and follows dT/dt too.

# %%
rng = np.random.default_rng(0)
t = np.arange(0.0, 7200.0, 0.2)
temp = 15 + 14 * (1 - np.exp(-t / 900)) + np.where(
    t > 3960, 12 * (1 - np.exp(-(t - 3960) / 600)), 0.0)
dtemp = np.gradient(temp, t)
bias_true = (np.array([-0.2426, 0.0873, -0.031]) + temp[:, None] * [2.1e-3, -1.4e-3, 0.9e-3]
             + 2e-5 * (temp[:, None] - 25) ** 2 * [1, -0.7, 0.5]
             + 0.05 * dtemp[:, None] * [1, 0.6, -0.8])
gyro = bias_true + 1e-3 * rng.normal(size=bias_true.shape)

s0 = binned_thermal(gyro, temp)
print("slope per °C:", s0.slope, " |r|:", np.abs(s0.r).round(4), " accepted:", s0.accepted)
print(f"{len(s0.bin_temp)} bins of 0.1 °C, {s0.per_bin} samples each after even sub-sampling")
e_recipe = np.sqrt(np.mean((s0.bias(temp) - bias_true) ** 2))
fit0, _, err0 = toolkit_compensate("bias_poly(2)+gradient", Recording(t=t, gyro=gyro, temp=temp))
e_toolkit = np.sqrt(np.mean((err0 - bias_true) ** 2))
print(f"bias error: recipe {e_recipe:.2e} rad/s, bias_poly(2)+gradient {e_toolkit:.2e} rad/s")
summary.append(("binned-thermal", "curvature, dT/dt", "bias RMS, rad/s", e_recipe, "bias_poly(2)+gradient", e_toolkit))

# %% [markdown]
# ## static-kalman: tracking the offset in static windows
#
# A level vehicle rests and turns. Thresholds `M·(max − min)` come from the
# first 1000 samples; each static window updates a scalar Kalman filter of
# the offset (`Q = 1e−4 (°/s)²`, `R = window variance`), on all three axes.
# The sensor warms during the run and its bias follows the temperature, so
# the offset frozen through each turn goes stale. A toolkit `bias_poly(1)`
# fitted on the same static windows predicts the bias through the turns.

# %%
fs = 200.0
t = np.arange(0.0, 480.0, 1 / fs)
moving = np.zeros(t.size, bool)
for start in np.arange(15.0, 410.0, 70.0):
    moving |= (t >= start) & (t < start + 60.0)
rate = np.zeros((t.size, 3))
for a, b in zip(np.flatnonzero(np.diff(moving.astype(int)) == 1) + 1,
                np.flatnonzero(np.diff(moving.astype(int)) == -1) + 1):
    rate[a:b, 2] = rng.uniform(-40, 40) * DEG * np.sin(np.linspace(0, np.pi, b - a)) ** 2
temp = 20 + 25 * (1 - np.exp(-t / 400))
bias_true = (np.array([0.4, -0.3, 0.25]) + np.outer(temp - 20, [0.02, 0.015, -0.03])) * DEG
gyro = rate + bias_true + 0.05 * DEG * rng.normal(size=rate.shape)
accel = np.tile([0, 0, 9.81], (t.size, 1)) + (0.01 + 0.5 * moving[:, None]) * rng.normal(size=rate.shape)

s1 = static_kalman(gyro, accel, t)
yaw_true = np.concatenate([[0], np.cumsum(rate[:-1, 2] / fs)])
static = np.zeros(t.size, bool)
for s, ok in zip(s1.window_start, s1.static):
    static[s:s + s1.window] = ok
static[:1000] = True
_, _, bias1 = toolkit_compensate("bias_poly(1)", Recording(t=t[static], gyro=gyro[static], temp=temp[static]),
                                 Recording(t=t, gyro=gyro, temp=temp))
yaw_toolkit = np.concatenate([[0], np.cumsum((gyro - bias1)[:-1, 2] / fs)])
for name, yaw in (("raw", s1.yaw_raw), ("factory offset", s1.yaw_fixed),
                  ("static-kalman tracked offset", s1.yaw_tracked), ("toolkit bias(T)", yaw_toolkit)):
    print(f"worst heading error, {name:18s}: {np.abs(yaw - yaw_true).max() / DEG:8.2f}°")
summary.append(("static-kalman", "drift during motion", "worst heading, rad", np.abs(s1.yaw_tracked - yaw_true).max(),
                "bias_poly(1) on the static windows", np.abs(yaw_toolkit - yaw_true).max()))

# %% [markdown]
# ## fog-one-run: one chamber run, scale factor and bias together
#
# The simulator's fog-one-run profile (−40 … 70 °C in 10 °C steps, ±10 °/s at every
# soak). The recipe regresses `K0·Ω` on `[D, T·D, T²·D, T, T − T_out, dT]`
# after dropping ±m samples around every change of the table's direction.
# The device has a constant bias and a curved one — fog-one-run has no constant
# column and a bias linear in T.

# %%
spec2 = "bias_poly(2)+scale_poly(2)+temp_diff+gradient"
beta = np.tile([3e-5, 2e-5, 2.5e-5, 2e-4, 1e-4, -5e-5, 1e-6, 2e-3], (3, 1))
batch, truth = simulate("s2", 1, seed=3, effects=spec2, params=Params(beta=jnp.asarray(beta), theta=jnp.zeros(0)),
                        temp_norm=TempNorm(centre=15.0, scale=60.0))
rec = batch.recording(0)
s2 = fog_one_run(rec.gyro, rec.temp, rec.temp_ext, rec.rate, m=3)
print("A = [a0, a1, a2, b1, b2, b3] =", s2.coefficients)
om = rec.rate[:, 2]
e2_recipe = s2.compensate(rec.gyro[:, 2], rec.temp, rec.temp_ext) - om
_, comp2, _ = toolkit_compensate(spec2, single_axis(rec, 2))
e2_toolkit = comp2[:, 0] - om


def systematic(e, keep):
    """RMS of 64-sample block means: the error that is not white noise."""
    e = e[keep][: keep.sum() // 64 * 64].reshape(-1, 64).mean(1)
    return np.sqrt(np.mean(e**2))


print(f"systematic rate error: fog-one-run {systematic(e2_recipe, s2.kept):.2e}, "
      f"toolkit {systematic(e2_toolkit, s2.kept):.2e} rad/s")
summary.append(("fog-one-run", "constant and curved bias", "systematic rate, rad/s", systematic(e2_recipe, s2.kept),
                spec2, systematic(e2_toolkit, s2.kept)))

# %% [markdown]
# ## attitude-reference: scale and bias against accelerometer + magnetometer
#
# Pitch and roll from the accelerometer, heading from the tilt-compensated
# magnetometer (NWU frame, ZYX angles), a quaternion per sample, an |a| gate,
# reference rates from consecutive quaternions, scale and bias updated
# alternately, complementary fusion — and beside it the same per-axis affine
# model solved jointly. The simulated gyro also has 1–2 % cross-axis
# coupling, which a per-axis model cannot hold.

# %%
mis = np.array([[0.02, -0.01], [0.015, 0.012], [-0.018, 0.01]])
beta3 = np.concatenate([np.array([[0.01, 0.02], [-0.02, -0.015], [0.015, 0.01]]), mis], axis=1)
spec3 = "bias_poly(0)+scale_poly(0)+misalignment"
batch, _ = simulate("attitude", 1, seed=1, effects=spec3, accel_share=0.0,
                    params=Params(beta=jnp.asarray(beta3), theta=jnp.zeros(0)))
rec = batch.recording(0)
s3 = attitude_reference(rec.gyro, rec.accel, rec.mag, rec.t, interval=50)
print("recursive s, b:", s3.scale.round(4), s3.bias.round(4))
print("joint     s, b:", s3.joint_scale.round(4), s3.joint_bias.round(4))
pairs = np.flatnonzero(s3.pairs)
_, comp3, _ = toolkit_compensate(spec3, Recording(t=rec.t[pairs], gyro=s3.measured_rate[pairs],
                                                  rate=s3.reference_rate[pairs]),
                                 Recording(t=rec.t, gyro=rec.gyro))
moving = np.linalg.norm(rec.rate, axis=1) > 0.2
e3_recipe = np.sqrt(np.mean((s3.compensate(rec.gyro, joint=True) - rec.rate)[moving] ** 2))
e3_toolkit = np.sqrt(np.mean((comp3 - rec.rate)[moving] ** 2))
print(f"rate error while moving: attitude-reference {e3_recipe:.2e}, toolkit {e3_toolkit:.2e} rad/s")
summary.append(("attitude-reference", "cross-axis coupling", "rate RMS moving, rad/s", e3_recipe, spec3, e3_toolkit))

# %% [markdown]
# ## cube-bias: biases without a level table
#
# Z up and down, Y up and down, four headings 90° apart each, on a table
# tilted by 2° at 45° latitude. Averaging the headings cancels the tilt and
# the horizontal Earth rate; up/down cancels gravity and the vertical Earth
# rate seen through misalignment and g-sensitivity. One heading alone would
# be off by a good part of the Earth rate.

# %%
batch, truth = simulate("six_face", 1, seed=4, noise="none", tilt=2.0, latitude=45.0, turns=False)
rec = batch.recording(0)
sets = {f"{s['face'][1]}_{'up' if s['face'][0] == '+' else 'down'}_{s['index'] + 1}": (s["start"], s["end"])
        for s in truth.segments if s["label"] == "face"}
s4 = cube_bias(rec.gyro, rec.accel, {k: v for k, v in sets.items() if k[0] in "zy"})
true_bias = np.asarray(truth.params.beta)[0, :, 0]
one = rec.gyro[slice(*sets["z_up_1"])].mean(0)
print("gyro bias error, 16 sets:     ", np.abs(s4.gyro_bias - true_bias).max(), "rad/s")
print("gyro bias error, one heading: ", np.abs(one - true_bias)[:2].max(), "rad/s (Earth rate 7.3e-5)")
print("accelerometer bias error:     ", np.abs(s4.accel_bias - truth.accel["bias"][0]).max(), "m/s²")

# %% [markdown]
# ## six-position — Ferraris, as imucal does it, solved with the toolkit's terms
#
# imucal's example session (102.4 Hz, deg/s and m/s²). The static faces give
# `bias_poly(0)+g_sens` by least squares; the three −360° turns give
# `scale_poly(0)+misalignment` on the integrated rate. The JSON contract:
# `ω = gyro_matrix·(ω_raw − gyro_bias − g_sens·a)`, `a = accel_matrix·(a_raw − accel_bias)`.
# On the command line:
#
# ```
# diffgyro recipe six-position example_ferraris_session.csv --columns gx=gyr_x,gy=gyr_y,gz=gyr_z,ax=acc_x,ay=acc_y,az=acc_z \
#     --gyro-unit deg/s --sampling-rate 102.4 --json
# ```

# %%
import pandas as pd  # noqa: E402

from diffgyro.recipes import read_sections  # noqa: E402

data = "../tests/data/imucal/"
df = pd.read_csv(data + "example_ferraris_session.csv", header=0, index_col=0)
sp = six_position(df[["gyr_x", "gyr_y", "gyr_z"]].to_numpy(), df[["acc_x", "acc_y", "acc_z"]].to_numpy(),
                  read_sections(data + "example_ferraris_session_list.json"), sampling_rate=102.4)
print("gyro bias (deg/s):", sp.gyro_bias.round(4))
print("gyro matrix:\n", sp.gyro_matrix.round(4))
try:
    import imucal

    sl = pd.read_json(data + "example_ferraris_session_list.json").T
    cal = imucal.FerrarisCalibration().compute(imucal.ferraris_regions_from_section_list(df, sl),
                                               102.4, "m/s^2", "deg/s")
    print("max |Δ| vs imucal: gyro bias", np.abs(sp.gyro_bias - cal.b_g).max(), "deg/s; gyro matrix",
          np.abs(sp.gyro_matrix - np.linalg.inv(cal.R_g) @ np.linalg.inv(cal.K_g)).max())
except ImportError:
    print("imucal not installed: no side-by-side")

# %% [markdown]
# ## multi-position — IMU-TK's method on its own Xsens data
#
# No turntable: a 50 s rest, then about 38 hand-placed poses. Static poses
# are found from the accelerometer variance (threshold multiplier searched
# over 2…10), the accelerometer is fitted so |a| = g at every pose, the gyro
# so that integrating between poses turns one gravity direction into the
# next. IMU-TK reports 38 poses, worst pose |‖a‖ − g| = 0.0025 m/s² and
# gyro scales near 4770 counts per rad/s.

# %%
acc = np.loadtxt("../tests/data/imu_tk/xsens_acc.mat")
gyr = np.loadtxt("../tests/data/imu_tk/xsens_gyro.mat")
mp = multi_position(acc[:, 1:], gyr[:, 1:], acc[:, 0], gravity=9.81744, pose_means=True)
print(f"{len(mp.intervals)} static poses (threshold multiplier {mp.threshold_multiplier})")
print(f"worst pose | |a| − g |: {np.abs(mp.pose_norm_error).max():.4f} m/s² "
      f"({100 * np.abs(mp.pose_norm_error).max() / 9.81744:.3f} %), "
      f"RMS over the first 100 samples {mp.pose_rms:.4f} m/s²")
print("gyro scales (counts per rad/s):", mp.gyro_scale_counts.round(1))

# %% [markdown]
# ## Side by side

# %%
table = pd.DataFrame(summary, columns=["recipe", "left out", "error measure", "recipe error",
                                       "toolkit model", "toolkit error"])
table["better by"] = (table["recipe error"] / table["toolkit error"]).round(1).astype(str) + "×"
print(table.to_string(index=False, float_format=lambda v: f"{v:.2e}"))
print(f"\nnotebook ran in {time.perf_counter() - started:.0f} s "
      f"({time.process_time() - cpu_started:.0f} s of CPU)")
