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
# # Bias dynamics: Allan deviation, a learned random walk, and static-kalman compared
#
# Gyro bias wanders. The static-kalman patent tracks the z-axis offset with a scalar
# Kalman filter whose process noise `Q = 1e-4` is set by hand. diffgyro
# models the bias as a deterministic error model plus a random walk whose
# variance `q` and white-noise variance `r` are *learned* by maximum
# likelihood (Kalman filter, GLS-profiled coefficients, BFGS).
#
# 1. A static run: the Allan deviation's read-outs (ARW, RRW) and the learned
#    `q`, `r` measure the same noise.
# 2. Hour-long runs with motion and short pauses: heading drift with no
#    compensation, with static-kalman, with the learned filter and with the smoother.
#
# With the environment variable `DIFFGYRO_NOTEBOOK_QUICK` set (the test suite
# sets it) the static run is half an hour and there are four hour-long runs
# instead of eight; every step is the same.

# %%
import math
import os

import matplotlib.pyplot as plt
import numpy as np

import diffgyro
from diffgyro.allan import allan, plot_allan
from diffgyro.data import Batch, Recording
from diffgyro.kalman import fit_random_walk
from diffgyro.recipes import heading_errors

diffgyro.enable_x64()
diffgyro.enable_compilation_cache()
QUICK = bool(os.environ.get("DIFFGYRO_NOTEBOOK_QUICK"))

# %% [markdown]
# ## 1. One static run: Allan read-outs and learned noise agree
#
# Two hours at 5 Hz (half an hour in quick mode); white noise of angle random walk `N` and a bias random
# walk of rate random walk `K`. The Allan read-outs are `N` (σ at τ = 1 s on
# the −½ line) and `K` (σ at τ = 3 s on the +½ line); the Kalman model gives
# `√(r·dt)` and `√q` for the same two numbers.

# %%
rng = np.random.default_rng(4)
fs, hours = 5.0, (0.5 if QUICK else 2.0)
dt = 1.0 / fs
n = int(hours * 3600 * fs)
arw_true, rrw_true = 5e-4, 2e-5  # rad/s/√Hz, rad/s²/√Hz
t = np.arange(n) * dt
gyro = (0.003 + np.cumsum(rrw_true * math.sqrt(dt) * rng.standard_normal((n, 3)), 0)
        + arw_true / math.sqrt(dt) * rng.standard_normal((n, 3)))

curves = allan(gyro.T[None], dt)  # leading axes: (devices, axes)
fit_static = fit_random_walk("bias_poly(0)+random_walk",
                             Batch.from_recordings([Recording(t=t, gyro=gyro, device="static")]))
for a, name in enumerate("xyz"):
    print(f"g{name}: ARW Allan {float(curves.readouts.arw[0, a]):.3e}, "
          f"Kalman √(r·dt) {math.sqrt(float(fit_static.r[0, a]) * dt):.3e}, truth {arw_true:.1e} | "
          f"RRW Allan {float(curves.readouts.rrw[0, a]):.3e}, Kalman √q {math.sqrt(float(fit_static.q[0, a])):.3e}, "
          f"truth {rrw_true:.1e}")

# %%
fig = plot_allan(curves, device=0, title="static run: Allan deviation with the −½ / +½ lines")
plt.show()

# %% [markdown]
# ## 2. Hour-long runs with pauses: heading drift
#
# Each run: 60 s at rest, then 100 s of yaw motion and a 20 s pause,
# repeated for just over an hour at 2 Hz. Every axis has a constant bias
# plus a random walk. Both static-kalman and the learned model see the same (true)
# static samples; static-kalman reads them in 2-s windows. The noise levels `q`, `r`
# are learned from each run's static samples alone.

# %%
def simulate_pause_run(seed, hours=1.05, fs=2.0, arw=1.5e-3, rrw=3e-5, first=60.0, move=100.0,
                       pause=20.0):
    rng = np.random.default_rng(seed)
    n = int(hours * 3600 * fs)
    dt = 1.0 / fs
    t = np.arange(n) * dt
    cyc = (t - first) % (move + pause)
    static = (t < first) | (cyc >= move)
    f, a, ph = rng.uniform(0.02, 0.2, 4), rng.uniform(0.1, 0.5, 4), rng.uniform(0, 2 * np.pi, 4)
    yaw = (a[:, None] * np.sin(2 * np.pi * f[:, None] * t + ph[:, None])).sum(0)
    rate = np.zeros((n, 3))
    rate[:, 2] = np.where(static, 0.0, yaw * np.sin(np.pi * np.clip(cyc / move, 0, 1)) ** 2)
    bias = rng.normal(0, 0.01, 3) + np.cumsum(rrw * math.sqrt(dt) * rng.standard_normal((n, 3)), 0)
    gyro = rate + bias + arw / math.sqrt(dt) * rng.standard_normal((n, 3))
    return t, gyro, rate, bias, static


fs2, n_dev = 2.0, (4 if QUICK else 8)
runs = [simulate_pause_run(s, fs=fs2) for s in range(n_dev)]
batch = Batch.from_recordings([Recording(t=r[0], gyro=r[1], device=f"run{i}") for i, r in enumerate(runs)])
static = np.zeros(batch.mask.shape, bool)
for i, r in enumerate(runs):
    static[i, :r[4].size] = r[4]
fit_runs = fit_random_walk("bias_poly(0)+random_walk", batch, static=static)
print("learned RRW √q (z) / truth:", np.round(np.sqrt(np.asarray(fit_runs.q[:, 2])) / 3e-5, 2))

# %%
at = int(3600 * fs2)
methods = ("none", "fixed", "static_kalman", "learned", "smoothed")
drift = {k: [] for k in methods}
tracks = None
for i, (t2, g2, rate2, _, st2) in enumerate(runs):
    h = heading_errors(t2, g2[:, 2], rate2[:, 2], st2, float(fit_runs.q[i, 2]), float(fit_runs.r[i, 2]),
                       window=4, init=100)
    if i == 0:
        tracks = {k: np.degrees(np.asarray(v)) for k, v in h.items()}
    for k in methods:
        drift[k].append(float(h[k][at]))
rms = {k: math.degrees(math.sqrt(np.mean(np.square(v)))) for k, v in drift.items()}
labels = {"none": "no compensation", "fixed": "factory offset E(0) only", "static_kalman": "static-kalman (Q = 1e-4)",
          "learned": "learned q, r (causal filter)", "smoothed": "learned q, r (smoother, offline)"}
for k in methods:
    print(f"{labels[k]:36s} heading error after 1 h, RMS over {n_dev} runs: {rms[k]:8.1f} deg")
print(f"learned / static-kalman = {rms['learned'] / rms['static_kalman']:.2f}")

# %%
fig, ax = plt.subplots(figsize=(8, 4))
tt = runs[0][0] / 60.0
for k in ("static_kalman", "learned", "smoothed", "fixed"):
    ax.plot(tt, tracks[k], label=labels[k])
ax.set_xlabel("time (min)")
ax.set_ylabel("heading error (deg)")
ax.set_ylim(-3 * max(abs(tracks["static_kalman"]).max(), 1), 3 * max(abs(tracks["static_kalman"]).max(), 1))
ax.legend(fontsize=8)
ax.set_title("run 0: heading error with each bias treatment")
plt.show()

# %% [markdown]
# ## What static-kalman's Q would have to be
#
# static-kalman's result depends on its hand-set `Q`. Sweeping it shows the learned
# model lands where the best hand-tuned `Q` would — without the sweep,
# and without knowing the truth.

# %%
sweep = [1e-4, 1e-5, 1e-6, 1e-7, 1e-8]
static_rms = []
for q_static in sweep:
    v = [float(heading_errors(r[0], r[1][:, 2], r[2][:, 2], r[4], float(fit_runs.q[i, 2]),
                              float(fit_runs.r[i, 2]), window=4, init=100, q_static=q_static)["static_kalman"][at])
         for i, r in enumerate(runs)]
    static_rms.append(math.degrees(math.sqrt(np.mean(np.square(v)))))
fig, ax = plt.subplots(figsize=(6, 3.5))
ax.semilogx(sweep, static_rms, "o-", label="static-kalman with fixed Q")
ax.axhline(rms["learned"], color="tab:green", label="learned q, r (causal)")
ax.axhline(rms["smoothed"], color="tab:red", ls="--", label="learned q, r (smoother)")
ax.set_xlabel("static-kalman's Q ((rad/s)² per window)")
ax.set_ylabel("RMS heading error at 1 h (deg)")
ax.legend(fontsize=8)
plt.show()
for q_static, v in zip(sweep, static_rms):
    print(f"Q = {q_static:.0e}: {v:.1f} deg")
