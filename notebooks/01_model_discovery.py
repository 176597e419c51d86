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
# # Model discovery: see where the model fails, name the missing effect, watch the error fall
#
# A MEMS gyro sits in a thermal chamber: it is cooled, soaked, heated and
# cooled back. Its bias follows a quadratic of temperature — and something
# else, which we do not tell the notebook. We fit the quadratic, compare it
# with the measurements, let `diagnose` name the missing effect with the
# evidence, add it, and watch the held-out error fall to the noise floor.
#
# Three things keep the diagnosis honest (see `diffgyro.diagnose`):
#
# * errors are measured on **held-out time blocks** (the model never saw
#   them), so adding terms cannot fake an improvement;
# * the **noise floor** comes from successive differences of the raw data, not
#   from any model;
# * an improvement counts only if it is **large against its fold-to-fold
#   spread and material against the floor** — gyro residuals are correlated
#   in time, and a textbook F-test on 10⁵ samples calls anything significant.

# %%
import matplotlib.pyplot as plt
import numpy as np

import diffgyro
from diffgyro.diagnose import diagnose, diagnose_auto
from diffgyro.fit import fit
from diffgyro.simulate import simulate

diffgyro.enable_x64()
diffgyro.enable_compilation_cache()

# %% [markdown]
# ## 1. A device with a hidden effect
#
# Two hours at 1 Hz, one device. The truth has one more term than the model
# we will start from; it is kept in `truth` and only looked at in the end.

# %%
batch, truth = simulate("thermal", 1, effects="bias_poly(2)+gradient", seed=6,
                        duration=7200.0, sample_rate=1.0)
rec = batch.recording(0)
fig, ax = plt.subplots(figsize=(8, 2.5))
ax.plot(rec.t / 60, rec.temp, label="sensor temp")
ax.plot(rec.t / 60, rec.temp_ext, label="chamber (temp_ext)")
ax.set_xlabel("time (min)")
ax.set_ylabel("°C")
ax.legend()
plt.show()

# %% [markdown]
# ## 2. Fit the thermal polynomial and look at what it leaves

# %%
base = fit("bias_poly(2)", batch)
print(base.summary(0)["status"], "held-out RMS", float(base.heldout_rms[0]), "rad/s")
resid = np.asarray(base.residuals(batch)[0, : batch.n_valid[0]])
sig = base.signals(batch)
dtemp = np.asarray(sig.dtemp[0, : batch.n_valid[0]]) * 60
heating = np.asarray(sig.heating[0, : batch.n_valid[0]])
fig, axs = plt.subplots(1, 2, figsize=(10, 3))
for k, name in enumerate("xyz"):
    axs[0].plot(rec.temp[::10], resid[::10, k], ".", ms=2, alpha=0.4, label=f"g{name}")
axs[0].set_xlabel("temperature (°C)")
axs[0].set_ylabel("residual (rad/s)")
axs[1].scatter(dtemp[::10], resid[::10].mean(1), c=heating[::10], cmap="coolwarm", s=3)
axs[1].set_xlabel("dT/dt (°C/min), colour: heating (red) / cooling (blue)")
plt.show()

# %% [markdown]
# The residual does not depend on temperature any more, but it clearly
# follows dT/dt and separates heating from cooling.

# %% [markdown]
# ## 3. Diagnose
#
# For every registered effect the data supports and the model lacks, the
# model *with that term added* is scored on the same held-out folds. The
# verdict names the best significant candidate, the close look-alikes, and
# the evidence.

# %%
dg = diagnose("bias_poly(2)", batch)
d = dg.devices[0]
print(d.verdict)
print(d.explanation)
for c in d.candidates[:6]:
    print(f"{c.effect:14s} held-out {c.heldout_rms:.3g}  closes {100 * c.closure:5.1f} % of the gap"
          f"  paired t {c.t:7.1f}  significant {c.significant}")

# %% [markdown]
# `gradient`, `thermal_lag` and `temp_diff` are look-alikes on a thermal run
# (a lagging sensor makes the inside–outside difference follow dT/dt too), so
# they are all reported with their held-out numbers; the best one is named.
# A random-walk smoother would also follow the residual — it is not allowed
# to win by default, because it explains nothing that carries over to new
# data.

# %% [markdown]
# ## 4. Add the named effect and refit: the ladder

# %%
ladder = diagnose_auto("bias_poly(2)", batch)
for added, spec, h, f, k in ladder.table_rows():
    print(f"{added:12s} {spec:28s} held-out {h:.3g} rad/s   floor {f:.3g}   adequate {k}/1")
fig, ax = plt.subplots(figsize=(5, 3))
ax.plot([s.added or "base" for s in ladder.steps], [s.heldout_rms[0] for s in ladder.steps], "o-",
        label="held-out RMS")
ax.axhline(ladder.steps[-1].noise_floor[0], color="k", ls="--", label="noise floor")
ax.set_ylabel("rad/s")
ax.legend()
plt.show()

# %% [markdown]
# ## 5. Compare with the truth
#
# The term the diagnosis named is the one the simulation hid, and the refit
# recovers its coefficients.

# %%
final = fit(ladder.spec, batch, norm=truth.norm)
got = np.asarray(final.params.beta[0])[:, -1]
want = np.asarray(truth.params.beta[0])[:, -1]
print("hidden:", truth.spec, " named:", ladder.steps[-1].added)
print("gradient coefficients (rad/s per °C/s):", got, "truth:", want)
assert ladder.steps[-1].added == "gradient"
assert np.allclose(got, want, rtol=0.1, atol=0.02 * np.max(np.abs(want)))

# %% [markdown]
# ## 6. The same from the command line
#
# ```
# diffgyro diagnose chamber.csv --model 'bias_poly(2)' --report report/ --auto
# diffgyro diagnose chamber.csv --model 'bias_poly(2)' --json
# ```
#
# `--report` writes one self-contained HTML page per device (the figures
# above, the Allan deviation of the residual against the floor, the
# candidates) and a batch summary.
