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
# # A flight log is not a calibration
#
# An autopilot log holds the gyro at a high rate, so it is tempting to fit a
# bias to it. But the mean of a gyro that turned is the mean turn rate, not a
# bias. This notebook runs diffgyro on a real public PX4 log that holds both:
# a vehicle still for 2 s, turned by up to 2 rad/s for the next 6 s, then
# left at rest for a minute (`tests/data/px4/sample.ulg`, pyulog's test log, BSD-3-Clause;
# the vehicle is disarmed: its motor outputs stay at 900 µs, so the turns are
# the vehicle handled, not flown — a flight's turns are read the same way).
#
# 1. the whole log: `fit`, `allan` and `export` say `in_motion` and refuse;
# 2. the same board at rest (the log's rest part, and two other PX4 logs of
#    vehicles on the ground): `ok`;
# 3. `--static-only`: the bias from the detected static intervals, equal to
#    the mean of those samples;
# 4. a production line's limits: pass, fail and the yield;
# 5. units that cannot pass silently: the same samples written in deg/s.

# %%
import contextlib
import io
import json
import os
import tempfile
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np

import diffgyro
from diffgyro import calibration
from diffgyro.cli import main
from diffgyro.data import Batch, Recording
from diffgyro.io import load
from diffgyro.motion import motion_check

diffgyro.enable_x64()
diffgyro.enable_compilation_cache()
os.environ.setdefault("COLUMNS", "110")  # the width of the command line's tables
work = Path(tempfile.mkdtemp(prefix="diffgyro-nb08-"))
px4 = next(p for p in (Path("../tests/data/px4"), Path("tests/data/px4")) if p.is_dir())
LOG = px4 / "sample.ulg"


def run(*args, split=False):
    """The command line, in this process: its exit code and its printed output (stdout
    and stderr apart with ``split``)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main([str(a) for a in args])
    if split:
        return code, out.getvalue(), err.getvalue()
    return code, err.getvalue() + out.getvalue()


def run_json(*args):
    """``--json``: the strict JSON object on stdout."""
    code, out, err = run(*args, "--json", split=True)
    assert code == 0, err
    return json.loads(out)


# %% [markdown]
# ## 1. The log, and where it moved
#
# The log holds `sensor_combined` (gyro and accelerometer, no temperature) at
# about 250 samples/s. `diffgyro.motion.motion_check` cuts it into windows of
# about 0.25 s and marks a window as moving when its mean leaves a slow
# baseline by more than 6 times the noise a window mean has **at rest on this
# device** (the threshold comes from the recording's own quiet windows, not a
# fixed number).

# %%
rec = load(LOG)[0]
t = rec.t - rec.t[0]
m = motion_check(Batch.from_recordings([rec]))
static = np.asarray(m.static[0])[: t.size]
print(f"{rec.device}: {t.size} samples over {t[-1]:.1f} s")
print({k: round(v, 6) if isinstance(v, float) else v for k, v in m.record(0).items()})

fig, axs = plt.subplots(2, 1, figsize=(9, 4), sharex=True)
for j, axis in enumerate("xyz"):
    axs[0].plot(t, rec.gyro[:, j], lw=0.6, label=axis)
    axs[1].plot(t, rec.accel[:, j], lw=0.6, label=axis)
for ax in axs:
    ax.fill_between(t, 0, 1, where=~static, color="r", alpha=0.12, transform=ax.get_xaxis_transform(),
                    label="moving (and a window either side)")
axs[0].set_ylabel("gyro (rad/s)")
axs[1].set_ylabel("accel (m/s²)")
axs[1].set_xlabel("time since the log's first sample (s)")
axs[0].legend(ncol=4, fontsize=8)
plt.show()

# %% [markdown]
# ## 2. What diffgyro says about the whole log
#
# `fit --model 'bias_poly(0)'`: a constant bias per axis. The device is not
# `ok`: its status is `in_motion`, and the detail says how much moved, how
# fast, against what rest noise, and what to do.

# %%
code, text = run("fit", LOG, "--model", "bias_poly(0)", "--out", work / "cal.json")
print(text)
whole = calibration.load(work / "cal.json").devices[0]
assert whole.status == "in_motion" and "--static-only" in whole.status_detail

# %% [markdown]
# The "bias" that fit would have given is the plain mean of the log — the
# mean turn rate mixed with the bias:

# %%
plain = np.array([whole.params[a]["bias_poly(0).c0"] for a in "xyz"])
np.testing.assert_allclose(plain, rec.gyro.mean(axis=0), rtol=0, atol=1e-9)
print("mean of the whole log (rad/s):", np.round(plain, 5))

# %% [markdown]
# `allan` on it: its read-outs (a "bias instability" of centiradians per
# second, a rate random walk of tenths of rad/s²/√Hz) are the turns', not the
# sensor's noise, and it says so. With `--static-only` it reads the longest
# static interval instead, and the read-outs are the sensor's.

# %%
code, text = run("allan", LOG)
print(text)
assert "not the sensor's noise" in text
code, text = run("allan", LOG, "--static-only")
print(text)
assert code == 0 and "in_motion" not in text

# %% [markdown]
# `export` refuses the calibration file's device, naming why; `--force`
# writes it anyway, and the file says so.

# %%
code, text = run("export", work / "cal.json", "--format", "px4")
print(f"exit code {code}:", text)
assert code == 2 and "in_motion" in text
code, text = run("export", work / "cal.json", "--format", "px4", "--force", "--out", work / "forced.params")
forced = (work / "forced.params").read_text()
print(next(line for line in forced.splitlines() if "--force" in line))
assert code == 0 and "written with --force" in forced

# %% [markdown]
# ## 3. The same board at rest
#
# The log's last minute, from 8 s on, is the vehicle at rest: cut out as a
# recording of its own it is `ok`. So are two other PX4 logs of vehicles on
# the ground (`sample_log_small.ulg`, armed with its motors running;
# `sample_appended_multiple.ulg`, landed throughout). At rest, the bias is
# the mean of the samples (`tests/test_motion.py` checks the ground logs'
# against pyulog's reading).

# %%
rest_part = t >= 8.0
rest = Recording(t=rec.t[rest_part], gyro=rec.gyro[rest_part], accel=rec.accel[rest_part],
                 device="sample/at-rest")
rest.to_frame().to_csv(work / "at_rest.csv", index=False)
code, text = run("fit", work / "at_rest.csv", px4 / "sample_log_small.ulg",
                 px4 / "sample_appended_multiple.ulg", "--model", "bias_poly(0)",
                 "--out", work / "rest.json")
print(text)
at_rest = calibration.load(work / "rest.json").devices
assert [d.status for d in at_rest] == ["ok"] * 3
assert all(d.motion["moving_fraction"] == 0.0 for d in at_rest)
bias_rest = np.array([at_rest[0].params[a]["bias_poly(0).c0"] for a in "xyz"])
np.testing.assert_allclose(bias_rest, rest.gyro.mean(axis=0), rtol=0, atol=1e-9)

# %% [markdown]
# ## 4. `--static-only`: the bias from the static intervals
#
# On the whole log, `--static-only` masks the moving samples (and a window
# either side) and fits the rest: status `ok`, with `static_only` and the
# number of samples used of those recorded. Its bias is the mean of the
# static samples, to the last digit; the whole log's mean is off by the turns.

# %%
so = run_json("fit", LOG, "--model", "bias_poly(0)", "--static-only")["devices"][0]
bias_static = np.array([so["params"][a]["bias_poly(0).c0"] for a in "xyz"])
mean_static = rec.gyro[static].mean(axis=0)
print(f"status {so['status']}, {so['n_samples']} of {so['n_recorded']} samples used")
print("static-only fit      ", np.round(bias_static, 6))
print("mean of static samples", np.round(mean_static, 6))
print("fit of the rest part ", np.round(bias_rest, 6))
print("whole-log mean       ", np.round(plain, 6))
print(f"whole-log mean is off by {np.abs(plain - bias_static).max():.2g} rad/s "
      f"({np.abs(plain - bias_static).max() / so['noise_floor']:.0f}× the noise floor)")
assert so["status"] == "ok" and so["static_only"] is True and so["n_samples"] == static.sum()
np.testing.assert_allclose(bias_static, mean_static, rtol=0, atol=1e-9)
assert np.abs(bias_static - bias_rest).max() < 2e-4
assert np.abs(plain - bias_static).max() > 20 * np.abs(bias_static - bias_rest).max()

# %% [markdown]
# ## 5. A production line's pass/fail
#
# `--limits FILE.toml` judges every device: the status must be `ok` (a unit
# in motion is not calibrated), the bias within 1 °/s and the noise floor
# within 5·10⁻³ rad/s. The whole log fails on its status; with
# `--static-only` it passes; the ground log `sample_appended_multiple.ulg`
# fails on its noise floor (0.011 rad/s, twenty times that of the first log
# at rest). The batch gets its yield and the list of rejected units.

# %%
limits = work / "line.toml"
limits.write_text("""\
[about]
name = "bench check"

[limits]
status = "ok"
"params.*.bias_poly(0).c0" = { abs = true, max = 1.0, unit = "deg/s" }
noise_floor = { max = 5e-3 }
""")
files = [LOG, px4 / "sample_log_small.ulg", px4 / "sample_appended_multiple.ulg"]
doc = run_json("fit", *files, "--model", "bias_poly(0)", "--limits", limits)
for d in doc["devices"]:
    print(f"{d['device']:42s} {d['status']:10s} {d['limits']['result']}",
          *(b["detail"] for b in d["limits"]["broken"]))
print(json.dumps(doc["limits"] | {"file": limits.name}))
assert [d["limits"]["result"] for d in doc["devices"]] == ["fail", "pass", "fail"]
assert doc["limits"]["rejected"] == [doc["devices"][0]["device"], doc["devices"][2]["device"]]
code, text = run("fit", LOG, "--model", "bias_poly(0)", "--limits", limits, "--static-only")
print(text)
assert code == 0 and "1 of 1 devices pass" in text

# %% [markdown]
# ## 6. Units that cannot pass silently
#
# The same samples written to a CSV in deg/s, as many loggers do, with plain
# headers (`gx, gy, gz`) and no `--gyro-unit`. Read as rad/s, the turns would
# be rates of more than 100 rad/s, over any gyro's full scale: refused, with
# the option that passes it. With the unit in the header (`gx (deg/s)`), the
# file is read in deg/s and a line says so.

# %%
frame = rec.to_frame()
for a in ("gx", "gy", "gz"):
    frame[a] = np.rad2deg(frame[a])
frame.to_csv(work / "in_degrees.csv", index=False)
code, text = run("fit", work / "in_degrees.csv", "--model", "bias_poly(0)")
print(f"exit code {code}:", text)
assert code == 2 and "--gyro-unit deg/s" in text
frame.rename(columns={a: f"{a} (deg/s)" for a in ("gx", "gy", "gz")}).to_csv(
    work / "with_header.csv", index=False)
code, text = run("fit", work / "with_header.csv", "--model", "bias_poly(0)", "--static-only")
print(text)
assert code == 0 and "deg/s" in text

# %% [markdown]
# What the numbers cannot show: the rest part alone, in deg/s without the
# option. A bias of 0.16 and a noise of 0.03 per sample are plausible in
# rad/s for a poor MEMS gyro, so the file is read as it is (the status the
# fit gives is printed, not asserted): the turns gave the unit away above,
# a still board does not. State the unit in the header or with
# `--gyro-unit`; on a line, the limits are the second net — the noise floor
# and the three biases fail `line.toml`.

# %%
frame = rest.to_frame()
for a in ("gx", "gy", "gz"):
    frame[a] = np.rad2deg(frame[a])
frame.to_csv(work / "rest_in_degrees.csv", index=False)
doc = run_json("fit", work / "rest_in_degrees.csv", "--model", "bias_poly(0)", "--limits", limits)
dev = doc["devices"][0]
print(f"status {dev['status']}, noise floor {dev['noise_floor']:.3g} 'rad/s', limits {dev['limits']['result']}:")
for broken in dev["limits"]["broken"]:
    print("  ", broken["detail"])
assert dev["limits"]["result"] == "fail"
assert any(b["limit"] == "noise_floor" for b in dev["limits"]["broken"])

# %% [markdown]
# The files were written to a temporary folder; remove it.

# %%
import shutil  # noqa: E402

shutil.rmtree(work)
