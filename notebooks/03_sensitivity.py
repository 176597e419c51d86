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
# # How good is a calibration, and what in the test plan limits it?
#
# One study end to end, on the fog-one-run thermal-chamber + rate-table procedure
# (−40…70 °C in 10 °C steps, 30 min soaks, ±10 °/s for a minute each way in
# every soak) and the model `bias_poly(3)+scale_poly(2)+gradient`:
#
# 1. **Uncertainty** — the fit's Gauss–Newton covariance assumes white
#    residuals. Gyro noise is not white; an autocorrelation-consistent
#    covariance (autoregressive-spectral HAC, Newey–West, block bootstrap)
#    keeps the intervals honest. The covariance, propagated, gives a band
#    around the compensation over the operating range.
# 2. **Sensitivity** — every fit is a JAX function, so the influence of each
#    input sample on the compensation at −40 °C, or of each plan number on
#    the predicted worst-case error, is a gradient.
# 3. **Design** — optimise the plan by gradient for the same total time, or
#    find the shortest plan that matches fog-one-run, and check the prediction by
#    Monte Carlo.
#
# The plan grid is coarse here (2048 samples, about 14 s) so the notebook
# runs in about a minute; `PlanConfig(n_samples=8192)` gives the report
# numbers. Rates are in rad/s inside, °/h in the prints. With the environment
# variable `DIFFGYRO_NOTEBOOK_QUICK` set (the test suite sets it) the Monte
# Carlo batches, bootstrap and plan optimisation run smaller; every step is the
# same.

# %%
import os
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import diffgyro
from diffgyro.fit import fit
from diffgyro.model import ErrorModel
from diffgyro.plan_design import (
    DEG,
    OperatingRange,
    PlanConfig,
    budget_for_accuracy,
    flat,
    heading_study,
    monte_carlo,
    optimise_plan,
    plan_duration,
    plan_environment,
    plan_sensitivity,
    predict_plan,
    s2_plan,
    simulate_devices,
)
from diffgyro.sensitivity import (
    block_bootstrap,
    compensation_sensitivity,
    coverage,
    hac_covariance,
    plot_uncertainty_band,
    uncertainty_band,
)

diffgyro.enable_x64()
diffgyro.enable_compilation_cache()
started = time.perf_counter()
DPH = 180 / np.pi * 3600  # rad/s -> °/h
QUICK = bool(os.environ.get("DIFFGYRO_NOTEBOOK_QUICK"))
N_DEVICES, N_BOOT, N_MC = (24, 24, 24) if QUICK else (120, 100, 250)
STEPS, BUDGET_STEPS, BUDGET_ITERATIONS = (20, 20, 2) if QUICK else (200, 150, 6)

model = ErrorModel.from_spec("bias_poly(3)+scale_poly(2)+gradient")
op = OperatingRange(temps=(-40.0, 70.0), rate=10 * DEG)   # where the calibration is used
config = PlanConfig(n_samples=2048)                      # tilted mount: every axis sees the table
arw = 1e-5                                               # rad/s/√Hz (0.034 °/√h)
s2 = s2_plan()
print(f"fog-one-run takes {float(plan_duration(s2, config)) / 3600:.2f} h")

# %%
env = plan_environment(s2, config)
fig, ax = plt.subplots(figsize=(10, 3))
ax.plot(env.t / 3600, env.chamber, label="chamber")
ax.plot(env.t / 3600, env.temp, label="sensor (lags 10 min)")
ax2 = ax.twinx()
ax2.plot(env.t / 3600, env.rate_true[:, 0] / DEG, color="C2", lw=0.6, label="x rate")
ax.set_xlabel("time (h)")
ax.set_ylabel("°C")
ax2.set_ylabel("°/s")
ax.legend(loc="upper left")
ax.set_title("the fog-one-run plan")
plt.show()

# %% [markdown]
# ## 1. Uncertainty that survives correlated noise
#
# 120 devices (24 in quick mode) through fog-one-run, with white noise plus a Gauss–Markov bias
# (σ = 0.5 °/h, τ = 2 min), each calibrated with `fit`. The truth is known,
# so we can count how often the nominal 95 % intervals hold it.

# %%
batch, truth = simulate_devices(s2, config, model, N_DEVICES, arw, op.norm, seed=1,
                                gm_sigma=0.5 / DPH, gm_tau=120.0)
result = fit(model, batch, norm=op.norm)
est = np.asarray(jax.vmap(flat)(result.params))
tru = np.asarray(jax.vmap(flat)(truth))
hac = hac_covariance(result, batch)                       # AR-spectral (default)
nw = hac_covariance(result, batch, method="kernel")       # Newey–West, prewhitened
boot = block_bootstrap(result, batch, n_boot=N_BOOT)
for name, cov in [("Gauss–Newton (plain)", result.cov), ("HAC, AR spectral", hac["cov"]),
                  ("Newey–West (Bartlett)", nw["cov"]), ("circular block bootstrap", boot["cov"])]:
    print(f"{name:26s} 95 % intervals cover the truth {100 * coverage(est, tru, cov):5.1f} %")
print(f"median Newey–West bandwidth {np.median(nw['bandwidth']):.0f} samples, "
      f"bootstrap block {np.median(boot['block']):.0f} samples")

# %%
temps = np.linspace(-40, 70, 45)
bands = [uncertainty_band(result, 0, temps, rate=op.rate, label="Gauss–Newton"),
         uncertainty_band(result, 0, temps, rate=op.rate, cov=hac["cov"][0], label="HAC")]
fig = plot_uncertainty_band(bands, unit="deg/h", title="device 0: compensation at +10 °/s")
plt.show()
ratio = np.asarray(bands[1].sigma / bands[0].sigma)
print(f"the honest band is {ratio.min():.1f}–{ratio.max():.1f}× the plain one")

# %% [markdown]
# ## 2. Which samples decide the calibration at −40 °C?
#
# Reverse mode through `solve_device`: the derivative of the compensated
# x rate at −40, 15 and 70 °C with respect to every x-gyro sample of
# device 0. Samples from the cold soak carry the −40 °C point; the
# polynomial makes far soaks pull the other way. Summed over all samples
# the influence is −1 (up to the scale factor): a constant offset added to
# the data is removed exactly.

# %%
sig = jax.tree.map(lambda a: a[0], result.signals(batch))
infl = jax.jit(lambda s: compensation_sensitivity(model, s, jnp.asarray([-40.0, 15.0, 70.0])))(sig)
fig, ax = plt.subplots(figsize=(10, 3))
for j, t_op in enumerate([-40, 15, 70]):
    ax.plot(env.t / 3600, infl[j, 0, :, 0], lw=0.8, label=f"at {t_op} °C")
ax.set_xlabel("time (h)")
ax.set_ylabel("∂ compensated / ∂ sample")
ax.legend()
plt.show()
print("sum of the influences:", np.round(np.asarray(infl[:, 0, :, 0].sum(1)), 4))

# %% [markdown]
# ## 3. What in the plan limits it?
#
# The predicted 1σ error over the operating range comes from the plan's
# Fisher information; its gradient tells what each number of the plan is
# worth (elasticity: % change of the worst-case error per % change). The
# number of table headings is an integer: it is compared by finite
# difference, in a lab that does not know the table's heading (Earth's
# horizontal rate is then not in the reference). Two headings per soak, in
# mirrored order, cancel what the soaks alias; what is left comes from the
# ramps, which run at one heading.

# %%
sens = plan_sensitivity(s2, config, model, arw, op)
el = sens["elasticity"]
print(f"fog-one-run predicted worst-case 1σ error {float(sens['worst']) * DPH:.4f} °/h")
print("elasticity to soak durations  ", np.round(np.asarray(el.soaks), 3))
print("elasticity to soak temperatures", np.round(np.asarray(el.temps), 3))
print(f"to ramp rate {float(el.ramp):+.3f}, table rate {float(el.rates[0]):+.3f}, "
      f"spin share {float(el.spin_fraction):+.3f}")
unknown = PlanConfig(n_samples=config.n_samples, earth_rate="unknown")
hs = heading_study(s2, unknown, model, arw, op, headings=(1, 2, 4))
print("Earth rate not in the reference — worst case by number of headings (°/h):",
      {h: round(v * DPH, 2) for h, v in hs.items()})

# %% [markdown]
# ## 4. A better plan for the same time, and the same accuracy in less time
#
# Two designs, both by Adam on the plan's unconstrained coordinates (the
# total time is held exactly): *thermal only* keeps fog-one-run's use of the rate
# table (10 °/s, the same share of every soak) and moves the soak
# temperatures, durations and ramp rate; *full* may also spin longer.

# %%
free_thermal = ("temps", "soaks", "ramp")
T_s2 = float(plan_duration(s2, config))
pred_s2 = predict_plan(s2, config, model, arw, op)
designs = {
    "thermal only": optimise_plan(s2, config, model, arw, op, free=free_thermal, steps=STEPS),
    "full": optimise_plan(s2, config, model, arw, op, steps=STEPS),
}
target = float(pred_s2.worst)
rows = []
for name, res in designs.items():
    free = free_thermal if name == "thermal only" else ("temps", "soaks", "ramp", "spin_fraction")
    t_eq, _ = budget_for_accuracy(target, s2, config, model, arw, op, lo=0.5 * 3600, hi=T_s2,
                                  iterations=BUDGET_ITERATIONS, free=free, steps=BUDGET_STEPS)
    rows.append((name, float(res.prediction.worst), t_eq))
    print(f"{name:13s} equal time: worst {float(res.prediction.worst) * DPH:.4f} °/h "
          f"({100 * (1 - float(res.prediction.worst) / target):.0f} % better than fog-one-run); "
          f"equal accuracy in {t_eq / 3600:.2f} h ({100 * (1 - t_eq / T_s2):.0f} % less time)")
best = designs["full"].plan
print("full design: soak temperatures", np.round(np.asarray(best.temps), 1))
print("             soak minutes     ", np.round(np.asarray(best.soaks) / 60, 1))
print(f"             ramp {float(best.ramp) * 60:.2f} °C/min, spin share {float(best.spin_fraction):.2f}")

# %%
fig, ax = plt.subplots(figsize=(10, 3))
for name, plan in [("fog-one-run", s2), ("thermal only", designs["thermal only"].plan), ("full", best)]:
    e = plan_environment(plan, config)
    ax.plot(e.t / 3600, e.temp, label=name)
ax.set_xlabel("time (h)")
ax.set_ylabel("sensor °C")
ax.legend()
plt.show()

# %% [markdown]
# ## 5. Does the prediction hold? Monte Carlo
#
# 250 simulated devices per plan (24 in quick mode) (each with its own sensor lag,
# self-heating and coefficients, white noise), calibrated with `fit`; the
# worst case over the operating range of the RMS compensation error is
# compared with the prediction.

# %%
for name, plan, pred in [("fog-one-run", s2, pred_s2), ("full", best, designs["full"].prediction)]:
    mc = monte_carlo(plan, config, model, arw, op, n_devices=N_MC, seed=7)
    print(f"{name:5s} predicted {float(pred.worst) * DPH:.4f} °/h, Monte Carlo "
          f"{float(mc.worst) * DPH:.4f} °/h ({100 * (float(mc.worst) / float(pred.worst) - 1):+.1f} %), "
          f"median device worst |error| {float(jnp.median(mc.device_worst)) * DPH:.4f} °/h")
print(f"\nnotebook ran in {time.perf_counter() - started:.0f} s")
