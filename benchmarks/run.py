"""diffgyro against the tools users would otherwise pick, and against the memory-bandwidth limit.

Every case times diffgyro and its baseline(s) in this one process,
interleaved (candidate, then each baseline, repeated), after a warm-up, and
reports medians. ``compile_s`` is the first call's time minus the median
(tracing + XLA compilation; the persistent compilation cache is not used).
The machine's memory read bandwidth is measured in the same run (numpy and
JAX sums over a 1 GB array, the faster one counts); a case's bandwidth limit
is the time to read its input once, and ``fraction_of_bandwidth_limit`` is
limit / diffgyro_s.

Per-device Python loops (numpy.polyfit, scipy least_squares, filterpy,
allantools) run on a subset of the devices (or of the samples, for the
per-sample filterpy loop); their time is scaled linearly to the whole case
and the subset is stated in the row (``baseline_subset``). Answers are
compared on that subset.

    python benchmarks/run.py --quick                   # < 3 minutes on 2 CPU cores
    python benchmarks/run.py --json results.json       # the issue's sizes
    python benchmarks/run.py --cases bias_poly3,allan  # a selection
    python benchmarks/run.py --host-devices 0          # one XLA CPU device per core (default: 1)

Runs unchanged on a GPU machine (the backend and device are printed).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

# On a GPU, JAX takes most of the card's memory when it starts; the child processes of the
# diagnose_native and compile cases then fail to create their solver handles. Each process
# allocates what it uses instead (set before JAX is imported here or in a child).
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # the shared timing, also when loaded by path
from _timing import cpu_name, measure, median_time  # noqa: E402

# --------------------------------------------------------------------------- sizes

#: case -> (devices, samples) for the full run (the issue's sizes) and for --quick.
FULL = {
    "bias_poly3": (10_000, 10_000),
    "s2_regression": (1_000, 10_000),
    "thermal_lag": (1_000, 10_000),
    "kalman": (1_000, 100_000),
    "allan": (100, 1_000_000),
    "diagnose": (100, 20_000),
    "diagnose_native": (1, 720_000),
    "load": (3, 1_350_000),
    "compile": (256, 2_000),
}
QUICK = {
    "bias_poly3": (1_000, 10_000),
    "s2_regression": (200, 10_000),
    "thermal_lag": (32, 4_000),
    "kalman": (200, 50_000),
    "allan": (4, 1_000_000),
    "diagnose": (8, 5_000),
    "diagnose_native": (1, 100_000),
    "load": (3, 200_000),
    "compile": (256, 2_000),
}
#: How many devices (series) the per-device Python baselines run, full / quick.
SUBSET = {
    "bias_poly3": (1000, 300),
    "s2_regression": (1000, 200),
    "thermal_lag": (24, 4),
    "kalman": (20_000, 5_000),  # samples of one series through filterpy
    "allan": (9, 3),
}
GOALS = {
    "bias_poly3": "≥5× faster, coefficients equal to 1e-9 relative, ≥25% of the bandwidth limit",
    "s2_regression": "≥2× faster than batched numpy normal equations, same answer",
    "thermal_lag": "≥10× faster than a scipy least_squares loop, same optimum to 1e-8",
    "kalman": "≥100× faster than a filterpy loop, same estimates",
    "allan": "≥3× faster than allantools oadev, same values",
    "diagnose": "report devices/s",
    "diagnose_native": "1 device × 720 000 samples: ≤ 1.5 GB peak RSS, ≤ 3× fit's time",
    "compile": "≤2 s per model spec",
    "load": "report against a bare pandas read",
}


def now() -> float:
    return time.perf_counter()


def block(x):
    import jax

    return jax.block_until_ready(x)


def row(case, devices, samples, dg_s, first_s, baseline, base_s, diff, rel, nbytes, bw, **extra):
    limit = nbytes / bw if nbytes else None
    out = {
        "case": case, "devices": devices, "samples": samples,
        "diffgyro_s": dg_s, "baseline": baseline, "baseline_s": base_s,
        "speedup": (base_s / dg_s) if (base_s and dg_s) else None,
        "max_abs_diff": diff, "max_rel_diff": rel, "bytes": nbytes,
        "fraction_of_bandwidth_limit": (limit / dg_s) if limit else None,
        "compile_s": max(first_s - dg_s, 0.0) if first_s is not None else None,
        "goal": GOALS.get(case.replace(":", "_")) or GOALS.get(case.split(":")[0]),
    }
    out.update(extra)
    return out


# --------------------------------------------------------------------------- machine


def machine_info() -> dict:
    import jax

    dev = jax.devices()[0]
    return {"cpu": cpu_name(), "cores": os.cpu_count(), "backend": jax.default_backend(),
            "device": getattr(dev, "device_kind", str(dev)), "n_devices": jax.device_count(),
            "jax": jax.__version__, "numpy": np.__version__, "python": platform.python_version()}


def bandwidth(gigabytes: float = 1.0, repeats: int = 5) -> dict:
    """Memory read bandwidth (bytes/s): numpy and XLA sums over one large array, and XLA
    with every CPU device reading its share at once (with use_cpu_cores, one device's
    sum may not reach what the machine can read)."""
    import jax
    import jax.numpy as jnp

    a = np.ones(int(gigabytes * 1e9) // 8)
    f = jax.jit(jnp.sum)

    def rate(read):  # bytes/s: median of ``repeats`` after a warm-up
        return a.nbytes / median_time(lambda: block(read()), repeats)

    bw_np = rate(a.sum)
    bw_jx = rate(functools.partial(f, jax.device_put(a)))  # the copy is freed on return
    devs = jax.local_devices()
    bw_all = bw_jx  # one device: the same measurement
    if len(devs) > 1:
        parts = [jax.device_put(p, d) for p, d in zip(np.array_split(a, len(devs)), devs)]
        bw_all = rate(lambda: [f(p) for p in parts])
        del parts
    return {"numpy_GBps": bw_np / 1e9, "jax_GBps": bw_jx / 1e9, "jax_all_devices_GBps": bw_all / 1e9,
            "bytes_per_s": max(bw_np, bw_jx, bw_all)}


# --------------------------------------------------------------------------- data


def thermal_profiles(rng, devices: int, samples: int, dt: float = 1.0):
    """Chamber-like temperatures: per device a few ramps and soaks between -20 and 60 °C."""
    t = np.arange(samples) * dt
    temp = np.empty((devices, samples))
    for i in range(devices):
        knots = np.sort(rng.uniform(0, t[-1], 6))
        levels = rng.uniform(-20, 60, 8)
        temp[i] = np.interp(t, np.concatenate([[0], knots, [t[-1]]]), levels)
    temp += 0.02 * rng.normal(size=temp.shape)
    return t, temp


def lag(x, tau, dt: float = 1.0):
    """``x`` through a first-order lag of time constant ``tau`` (scipy), starting settled."""
    from scipy.signal import lfilter

    a = -np.expm1(-dt / tau)
    y, _ = lfilter([a], [1.0, -(1.0 - a)], x[1:], zi=[(1.0 - a) * x[0]])
    return np.concatenate([x[:1], y])


def own_norm(temp):
    lo, hi = temp.min(axis=1), temp.max(axis=1)
    return 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 0.5)


def make_batch(t, gyro, **signals):
    from diffgyro import Batch

    d, n = gyro.shape[:2]
    return Batch(t=np.broadcast_to(t, (d, n)), gyro=gyro, mask=np.ones((d, n), bool),
                 n_valid=np.full(d, n), devices=tuple(f"d{i}" for i in range(d)), **signals)


def compare(a, b):
    """Largest absolute difference, and largest relative to each row's largest magnitude."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    scale = np.max(np.abs(b), axis=-1, keepdims=True)
    return float(np.max(np.abs(a - b))), float(np.max(np.abs(a - b) / np.where(scale > 0, scale, 1)))


# --------------------------------------------------------------------------- cases


def case_bias_poly3(devices, samples, subset, repeats, bw, full_fit=True):
    """bias_poly(3) per axis against numpy.polyfit and numpy.linalg.lstsq loops."""
    from diffgyro.fit import fit

    rng = np.random.default_rng(1)
    t, temp = thermal_profiles(rng, devices, samples)
    centre, scale = own_norm(temp)
    ts = (temp - centre[:, None]) / scale[:, None]
    coef = rng.normal(size=(devices, 3, 4)) * np.array([1e-2, 3e-3, 1e-3, 3e-4])
    gyro = np.empty((devices, samples, 3))
    for i in range(0, devices, 256):
        s = slice(i, i + 256)
        pw = np.stack([ts[s] ** j for j in range(4)], axis=-1)  # (b, n, 4)
        gyro[s] = np.einsum("bnj,bij->bni", pw, coef[s]) + 1e-4 * rng.normal(size=(pw.shape[0], samples, 3))
    del ts
    batch = make_batch(t, gyro, temp=temp)
    sub = min(subset, devices)

    def candidate():
        r = fit("bias_poly(3)", batch, noise_floor=False)
        return np.asarray(block(r.params.beta))

    def polyfit():
        out = np.empty((sub, 3, 4))
        for i in range(sub):
            x = (temp[i] - centre[i]) / scale[i]
            out[i] = np.polyfit(x, gyro[i], 3)[::-1].T
        return out

    def lstsq():
        out = np.empty((sub, 3, 4))
        for i in range(sub):
            x = (temp[i] - centre[i]) / scale[i]
            out[i] = np.linalg.lstsq(np.vander(x, 4, increasing=True), gyro[i], rcond=None)[0].T
        return out

    first, dg, base, (out_c, out_b) = measure(candidate, {"polyfit": polyfit, "lstsq": lstsq},
                                              repeats)
    nbytes = temp.nbytes + gyro.nbytes + batch.mask.nbytes
    rows = []
    for name, label in (("polyfit", "numpy.polyfit loop (3 axes per call)"),
                        ("lstsq", "numpy.linalg.lstsq loop")):
        diff, rel = compare(out_c[:sub], out_b[name])
        rows.append(row("bias_poly3", devices, samples, dg, first, label,
                        base[name] * devices / sub, diff, rel, nbytes, bw,
                        baseline_subset=f"{sub} devices, scaled",
                        note="fit(noise_floor=False): coefficients, held-out folds, covariance, "
                             "status"))
    if full_fit:
        # the default fit() also computes the model-free noise floor (per device and axis,
        # on the host's threads beside the fit)
        def candidate_full():
            r = fit("bias_poly(3)", batch)
            return np.asarray(block(r.params.beta))

        first_f, dg_f, _, (out_f, _) = measure(candidate_full, {}, max(3, repeats // 2))
        diff, rel = compare(out_f[:sub], out_b["lstsq"])
        rows.append(row("bias_poly3:defaults", devices, samples, dg_f, first_f,
                        "numpy.linalg.lstsq loop", base["lstsq"] * devices / sub, diff, rel,
                        nbytes, bw, baseline_subset=f"{sub} devices, scaled",
                        note="fit() with its defaults, noise floor included"))
    return rows


def local_slope_np(t, y, half):
    """numpy twin of diffgyro.signals.local_slope (all samples valid)."""
    n = t.shape[-1]
    tc = t - t.mean(axis=-1, keepdims=True)
    yc = y - y.mean(axis=-1, keepdims=True)

    def csum(x):
        return np.concatenate([np.zeros(x.shape[:-1] + (1,)), np.cumsum(x, axis=-1)], axis=-1)

    i = np.arange(n)
    lo, hi = np.clip(i - half, 0, n), np.clip(i + half + 1, 0, n)
    c = [csum(np.broadcast_to(v, y.shape)) for v in (np.ones_like(tc), tc, yc, tc * tc, tc * yc)]
    s1, st, sy, stt, sty = (x[..., hi] - x[..., lo] for x in c)
    var = stt - st * st / s1
    cov = sty - st * sy / s1
    return np.where(var > 0, cov / np.where(var > 0, var, 1.0), 0.0)


def s2_design(temp, temp_ext, rate, t, window=60.0):
    """numpy regressors of bias_poly(2)+scale_poly(2)+gradient+temp_diff, (d, n, 3, 8)."""
    centre, scale = own_norm(temp)
    ts = (temp - centre[:, None]) / scale[:, None]
    dt = float(np.median(np.diff(t)))
    half = max(1, int(round(0.5 * window / dt)))
    dtemp = local_slope_np(t[None, :], temp, half)
    d, n = temp.shape
    x = np.empty((d, n, 3, 8))
    for j in range(3):
        x[:, :, :, j] = (ts ** j)[:, :, None]
        x[:, :, :, 3 + j] = rate * (ts ** j)[:, :, None]
    x[:, :, :, 6] = dtemp[:, :, None]
    x[:, :, :, 7] = (temp - temp_ext)[:, :, None]
    return x


def case_s2(devices, samples, subset, repeats, bw):
    """fog-one-run's regression (bias_poly(2)+scale_poly(2)+gradient+temp_diff) against batched numpy
    normal equations."""
    from diffgyro.fit import fit

    spec = "bias_poly(2)+scale_poly(2)+gradient+temp_diff"
    rng = np.random.default_rng(2)
    t, temp = thermal_profiles(rng, devices, samples)
    temp_ext = 0.7 * temp + 5 + 0.5 * rng.normal(size=temp.shape)
    steps = rng.choice([-2.0, -1.0, -0.5, 0.0, 0.5, 1.0, 2.0], size=(devices, samples // 200 + 1, 3))
    rate = np.repeat(steps, 200, axis=1)[:, :samples]
    beta = rng.normal(size=(devices, 3, 8)) * np.array([1e-2, 3e-3, 1e-3, 1e-3, 3e-4, 1e-4, 0.5,
                                                          1e-4])
    gyro = np.empty((devices, samples, 3))
    for i in range(0, devices, 64):
        s = slice(i, i + 64)
        x = s2_design(temp[s], temp_ext[s], rate[s], t)
        gyro[s] = rate[s] + np.einsum("dnip,dip->dni", x, beta[s]) + 1e-4 * rng.normal(
            size=rate[s].shape)
    batch = make_batch(t, gyro, temp=temp, temp_ext=temp_ext, rate=rate)
    sub = min(subset, devices)

    def candidate():
        r = fit(spec, batch, noise_floor=False)
        return np.asarray(block(r.params.beta))

    def numpy_normal():
        out = np.empty((sub, 3, 8))
        for i in range(0, sub, 32):
            s = slice(i, min(i + 32, sub))
            x = s2_design(temp[s], temp_ext[s], rate[s], t)  # (b, n, 3, p)
            y = gyro[s] - rate[s]
            xa = np.ascontiguousarray(np.moveaxis(x, 2, 1))  # (b, 3, n, p)
            a = np.swapaxes(xa, -1, -2) @ xa  # (b, 3, p, p)
            c = np.einsum("binp,bni->bip", xa, y)
            d = np.sqrt(np.einsum("...ii->...i", a))
            z = np.linalg.solve(a / (d[..., :, None] * d[..., None, :]), (c / d)[..., None])
            out[s] = z[..., 0] / d
        return out

    first, dg, base, (out_c, out_b) = measure(candidate, {"np": numpy_normal}, repeats)
    diff, rel = compare(out_c[:sub], out_b["np"])
    nbytes = temp.nbytes + temp_ext.nbytes + gyro.nbytes + rate.nbytes + batch.mask.nbytes + t.nbytes
    return [row("s2_regression", devices, samples, dg, first,
                "batched numpy normal equations (regressors built in numpy)",
                base["np"] * devices / sub, diff, rel, nbytes, bw,
                baseline_subset=f"{sub} devices, scaled" if sub < devices else "all devices",
                note=f"{spec}; fit(noise_floor=False) with held-out folds")]


def case_thermal_lag(devices, samples, subset, repeats, bw, also_direct=True):
    """bias_poly(1)+thermal_lag (one shared time constant) against scipy least_squares per device."""
    from scipy.optimize import least_squares

    from diffgyro.fit import fit

    spec = "bias_poly(1)+thermal_lag"
    rng = np.random.default_rng(3)
    dt = 1.0
    t, temp = thermal_profiles(rng, devices, samples, dt)
    centre, scale = own_norm(temp)
    tau = rng.uniform(100.0, 600.0, devices)

    gyro = np.empty((devices, samples, 3))
    coef = rng.normal(size=(devices, 3, 2)) * np.array([1e-2, 3e-3])
    for i in range(devices):
        lag_s = (lag(temp[i], tau[i], dt) - centre[i]) / scale[i]
        gyro[i] = coef[i, :, 0] + np.outer(lag_s, coef[i, :, 1]) + 1e-4 * rng.normal(size=(samples, 3))
    batch = make_batch(t, gyro, temp=temp)
    sub = min(subset, devices)

    def candidate(path="sums"):
        r = fit(spec, batch, noise_floor=False, path=path)
        return np.asarray(block(r.params.beta)), np.exp(np.asarray(r.params.theta[:, 0]))

    def residual(i, p):
        ts = (temp[i] - centre[i]) / scale[i]
        lag_s = (lag(temp[i], np.exp(p[9]), dt) - centre[i]) / scale[i]
        x = np.stack([np.ones_like(ts), ts, lag_s - ts], axis=1)
        return (gyro[i] - x @ p[:9].reshape(3, 3).T).ravel()

    def scipy_loop():
        betas, taus = np.empty((sub, 3, 3)), np.empty(sub)
        for i in range(sub):
            ts = (temp[i] - centre[i]) / scale[i]
            y = gyro[i]

            def resid(p, i=i):
                return residual(i, p)

            tau0 = np.clip(t[-1] / 30.0, 10.0, 3600.0)  # diffgyro's nonlinear_init
            lag0 = (lag(temp[i], tau0, dt) - centre[i]) / scale[i]
            x0 = np.stack([np.ones_like(ts), ts, lag0 - ts], axis=1)
            b0 = np.linalg.lstsq(x0, y, rcond=None)[0].T
            sol = least_squares(resid, np.concatenate([b0.ravel(), [np.log(tau0)]]),
                                xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=2000)
            betas[i], taus[i] = sol.x[:9].reshape(3, 3), np.exp(sol.x[9])
        return betas, taus

    first, dg, base, (out_c, out_b) = measure(candidate, {"scipy": scipy_loop}, repeats)
    (b_c, tau_c), (b_s, tau_s) = out_c, out_b["scipy"]
    diff, rel = compare(b_c[:sub], b_s)
    tau_rel = float(np.max(np.abs(tau_c[:sub] - tau_s) / tau_s))

    def cost(b, tau_):
        return np.array([np.sum(residual(i, np.concatenate([b[i].ravel(), [np.log(tau_[i])]]))**2)
                         for i in range(sub)])

    # which optimum is lower: a τ difference alone can be a solver's stopping rule
    cost_c, cost_s = cost(b_c, tau_c), cost(b_s, tau_s)
    cost_rel = float(np.max((cost_c - cost_s) / cost_s))
    nbytes = temp.nbytes + gyro.nbytes + batch.mask.nbytes
    label = "scipy.optimize.least_squares loop (all 10 parameters, lfilter lag)"
    rows = [row("thermal_lag", devices, samples, dg, first, label, base["scipy"] * devices / sub,
                diff, max(rel, tau_rel), nbytes, bw, baseline_subset=f"{sub} devices, scaled",
                tau_max_rel_diff=tau_rel, max_cost_excess_over_scipy=cost_rel,
                note=f"{spec}; fit(path='sums'): Newton on the projected cost; also refits "
                     "the time constant on 5 held-out folds")]
    if also_direct:  # the direct path: optimistix LM on the design
        first_d, dg_d, _, ((b_d, tau_d), _) = measure(lambda: candidate("direct"), {},
                                                       max(3, repeats // 2))
        diff, rel = compare(b_d[:sub], b_s)
        tau_rel = float(np.max(np.abs(tau_d[:sub] - tau_s) / tau_s))
        rows.append(row("thermal_lag:direct", devices, samples, dg_d, first_d, label,
                        base["scipy"] * devices / sub, diff, max(rel, tau_rel), nbytes, bw,
                        baseline_subset=f"{sub} devices, scaled", tau_max_rel_diff=tau_rel,
                        note=f"{spec}; fit(path='direct'): optimistix LM over the time "
                             "constant, design formed per trial"))
    return rows


def case_kalman(devices, samples, subset, repeats, bw):
    """Random-walk bias Kalman filter of every device and axis against filterpy and a numpy loop."""
    import jax
    import jax.numpy as jnp
    from filterpy.kalman import KalmanFilter

    from diffgyro.kalman import rw_filter

    rng = np.random.default_rng(4)
    dt, q, r, p0 = 0.1, 1e-9, 1e-6, 1e-4
    series = devices * 3
    y = np.cumsum(np.sqrt(q * dt) * rng.normal(size=(series, samples)), axis=1)
    y += np.sqrt(r) * rng.normal(size=y.shape) + 1e-3
    t = np.arange(samples) * dt
    nb = min(subset, samples)

    @jax.jit
    def filt(y, t):
        obs = jnp.ones(y.shape[-1], bool)
        x0 = jnp.zeros((y.shape[-1], 0), y.dtype)
        return jax.vmap(lambda yy: rw_filter(yy, x0, obs, t, q, r, p0).a_y)(y)

    yj, tj = jax.device_put(y), jax.device_put(t)

    def candidate():
        return np.asarray(block(filt(yj, tj)))

    def numpy_loop():  # one time loop, all series as a vector (a strong numpy baseline)
        a = np.zeros(series)
        p = np.full(series, p0)
        out = np.empty_like(y)
        for k in range(samples):
            if k:
                p = p + q * dt
            f = p + r
            a = a + p / f * (y[:, k] - a)
            p = p * r / f
            out[:, k] = a
        return out

    def filterpy_loop():  # one series, nb samples (per-sample Python objects)
        kf = KalmanFilter(dim_x=1, dim_z=1)
        kf.x = np.zeros((1, 1))
        kf.F = np.eye(1)
        kf.H = np.eye(1)
        kf.R = np.eye(1) * r
        kf.Q = np.eye(1) * q * dt
        kf.P = np.eye(1) * p0
        out = np.empty(nb)
        for k in range(nb):
            if k:
                kf.predict()
            kf.update(y[0, k])
            out[k] = kf.x[0, 0]
        return out

    first, dg, base, (out_c, out_b) = measure(candidate, {"np": numpy_loop, "fp": filterpy_loop},
                                              repeats)
    nbytes = y.nbytes + t.nbytes
    diff_np, rel_np = compare(out_c, out_b["np"])
    diff_fp, rel_fp = compare(out_c[:1, :nb], out_b["fp"][None])
    return [
        row("kalman", devices, samples, dg, first, "filterpy KalmanFilter per-sample loop",
            base["fp"] * series * samples / nb, diff_fp, rel_fp, nbytes, bw,
            baseline_subset=f"1 series × {nb} samples, scaled to {series} series",
            note="filtered bias of every device and axis (lax.scan, vmapped)"),
        row("kalman", devices, samples, dg, first,
            "numpy time loop, all series vectorised", base["np"], diff_np, rel_np, nbytes, bw,
            baseline_subset="all"),
    ]


def case_allan(devices, samples, subset, repeats, bw):
    """Overlapping Allan deviation of every device and axis against allantools.oadev."""
    import allantools
    import jax
    import jax.numpy as jnp

    from diffgyro import allan

    rng = np.random.default_rng(5)
    dt = 0.01
    y = 1e-3 * rng.normal(size=(devices, 3, samples))
    y += np.cumsum(1e-6 * rng.normal(size=y.shape), axis=-1)
    m = allan.default_m(samples)
    mj = jnp.asarray(m)
    yj = jax.device_put(y)
    sub = min(subset, devices * 3)
    flat = y.reshape(-1, samples)

    def candidate():
        adev, _ = allan.oadev(yj, dt, mj)
        return np.asarray(block(adev)).reshape(-1, len(m))

    def at_loop():
        return np.stack([allantools.oadev(flat[i], rate=1.0 / dt, data_type="freq",
                                          taus=m * dt)[1] for i in range(sub)])

    first, dg, base, (out_c, out_b) = measure(candidate, {"at": at_loop}, repeats)
    diff, rel = compare(out_c[:sub], out_b["at"])
    return [row("allan", devices, samples, dg, first, "allantools.oadev loop",
                base["at"] * devices * 3 / sub, diff, rel, y.nbytes, bw,
                baseline_subset=f"{sub} series, scaled to {devices * 3}",
                note=f"{len(m)} cluster sizes, all devices × 3 axes")]


def case_diagnose(devices, samples, subset, repeats, bw):
    """diagnose() with every candidate effect: devices per second."""
    try:
        from diffgyro.diagnose import diagnose
    except ImportError:
        return [row("diagnose", devices, samples, None, None, None, None, None, None, 0, bw,
                    note="diffgyro.diagnose not available yet")]
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", devices, effects="bias_poly(2)+gradient", seed=6,
                        sample_rate=1.0, duration=float(samples))

    def candidate():
        return diagnose("bias_poly(2)", batch)

    first, dg, _, _ = measure(candidate, {}, repeats)
    nbytes = sum(getattr(batch, k).nbytes for k in batch.signals if getattr(batch, k) is not None)
    return [row("diagnose", devices, int(batch.length), dg, first, None, None, None, None,
                nbytes, bw, devices_per_s=devices / dg,
                note="diagnose('bias_poly(2)') with every candidate; thermal plan")]


NATIVE_CHILD = """
import json, resource, sys, time
import numpy as np
sys.path.insert(0, {here!r})
import diffgyro
diffgyro.enable_x64()
if {cache!r}:
    diffgyro.enable_compilation_cache({cache!r})
import jax
import run as B
z = np.load({path!r})
batch = B.make_batch(z["t"], z["gyro"], temp=z["temp"], temp_ext=z["temp_ext"])
t0 = time.perf_counter()
if {command!r} == "fit":
    from diffgyro.fit import fit
    jax.block_until_ready(fit("bias_poly(2)", batch).params.beta)
else:
    from diffgyro.diagnose import diagnose
    verdicts = [d.verdict + ":" + str(d.best.effect if d.best else None)
                for d in diagnose("bias_poly(2)", batch).devices]
seconds = time.perf_counter() - t0
# peak RSS of this process image: VmHWM (ru_maxrss keeps the parent's peak across exec)
try:
    hwm = next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM"))
except (OSError, StopIteration):
    hwm = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({{"s": seconds, "rss_GB": hwm / 1e6}}))
"""


def native_data(path, devices: int, samples: int, fs: float = 200.0, seed: int = 6):
    """A thermal run at ``fs`` Hz whose bias follows dT/dt (gradient) beyond bias_poly(2)."""
    rng = np.random.default_rng(seed)
    t, temp = thermal_profiles(rng, devices, samples, dt=1.0 / fs)
    temp_ext = 0.7 * temp + 5 + 0.05 * rng.normal(size=temp.shape)
    slope = np.gradient(np.stack([lag(temp[i], 120.0 * fs, 1.0) for i in range(devices)]), t, axis=1)
    gyro = (1e-3 * (temp - 20) / 40)[..., None] + 0.05 * slope[..., None] \
        + 2e-3 * rng.normal(size=(devices, samples, 3))
    np.savez(path, t=t, gyro=gyro, temp=temp, temp_ext=temp_ext)


def native_run(command: str, path, cache: str = "") -> dict:
    """Time and peak RSS of ``fit`` or ``diagnose`` on the saved data, in a child process."""

    code = NATIVE_CHILD.format(here=str(Path(__file__).resolve().parent), cache=cache,
                               path=str(path), command=command)
    return json.loads(run_child(code).strip().splitlines()[-1])


def run_child(code: str, timeout: float | None = None) -> str:
    """Run ``python -c code`` and return its stdout; a failed child raises with the end of
    its stderr, so the benchmark says why."""
    import subprocess

    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=timeout)
    if out.returncode != 0:
        raise RuntimeError(f"child process exited with {out.returncode}:\n"
                           + "\n".join(out.stderr.strip().splitlines()[-15:]))
    return out.stdout


COMMAND_CHILD = """
import json, os, time
t0 = time.perf_counter()
pid = os.posix_spawn({argv[0]!r}, {argv!r}, dict(os.environ, DIFFGYRO_CACHE_DIR={cache!r}),
                     file_actions=[(os.POSIX_SPAWN_OPEN, 1, os.devnull, os.O_WRONLY, 0)])
_, status, usage = os.wait4(pid, 0)  # this child's own peak RSS, not the benchmark's
print(json.dumps({{"s": time.perf_counter() - t0, "rss_GB": usage.ru_maxrss / 1e6,
                  "exit": os.waitstatus_to_exitcode(status)}}))
"""


def native_table(npz, path):
    """The saved record as a Parquet file in the standard schema (``diffgyro.io._save``)."""
    from diffgyro.io import save

    z = np.load(npz)
    save(make_batch(z["t"], z["gyro"], temp=z["temp"], temp_ext=z["temp_ext"]), path)


def command_run(command: str, path, cache: str) -> dict:
    """Wall time and peak RSS of the command a user runs on the Parquet file: ``diffgyro fit
    -m bias_poly(2) FILE --out CAL`` or ``diffgyro diagnose -m bias_poly(2) FILE``, start to
    exit (Python start-up, imports, reading the file and printing included)."""

    argv = [sys.executable, "-m", "diffgyro", command, "-m", "bias_poly(2)", str(path)]
    if command == "fit":
        argv += ["--out", str(Path(path).with_suffix(".json"))]
    code = COMMAND_CHILD.format(argv=argv, cache=cache)
    r = json.loads(run_child(code).strip().splitlines()[-1])
    if r["exit"] != 0:
        raise RuntimeError(f"{' '.join(argv[2:])} exited with {r['exit']}")
    return r


#: The record sizes (devices, samples) of the full diagnose_native case: memory from 100 000
#: to 1.35 M samples per device (200 Hz × 1 h is 720 000; a PX4 thermal log of three IMUs at
#: 250 Hz × 1.5 h is 3 × 1.35 M).
NATIVE_LADDER = {720_000: ((1, 100_000), (1, 360_000), (1, 720_000), (1, 1_350_000),
                           (3, 1_350_000))}


def case_diagnose_native(devices, samples, subset, repeats, bw, kinds=("native", "command")):
    """diagnose and fit on the same raw-rate record (200 Hz), each in a child process: time of
    the call and the process's peak RSS (compiled programs from the persistent cache, filled
    by a first process of each). Full size: every record of :data:`NATIVE_LADDER`."""
    import os
    import tempfile

    own_cache = tempfile.TemporaryDirectory()  # the children's cache when none is set
    cache = os.environ.get("DIFFGYRO_CACHE_DIR") or own_cache.name
    rows = []
    for d, n in NATIVE_LADDER.get(samples, ((devices, samples),)):
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "native.npz"
            native_data(path, d, n)
            table = Path(tmp) / "native.parquet"
            native_table(path, table)
            for kind, run_one, where in (("native", native_run, path), ("command", command_run, table)):
                if kind not in kinds:
                    continue
                pair = []
                for command in ("fit", "diagnose"):
                    run_one(command, where, cache)  # fills the compile cache
                    r = run_one(command, where, cache)
                    what = (f"{command}('bias_poly(2)') on a 200 Hz thermal run, own process"
                            if kind == "native" else
                            f"the command `diffgyro {command} -m bias_poly(2)` on the record "
                            "as Parquet, start to exit")
                    pair.append(row(f"{command}:{kind}", d, n, r["s"], None, None, None, None,
                                    None, d * n * 6 * 8, bw, peak_rss_GB=r["rss_GB"], note=what))
                    print(f"  {command}:{kind} {d} x {n}: {r['s']:.2f} s, {r['rss_GB']:.3f} GB",
                          flush=True)
                pair[1]["time_vs_fit"] = pair[1]["diffgyro_s"] / pair[0]["diffgyro_s"]
                rows += pair
    own_cache.cleanup()
    for kind in kinds:
        first = next(r for r in rows if r["case"] == f"diagnose:{kind}")
        for r in rows:
            if r["case"] == f"diagnose:{kind}":
                r["rss_vs_smallest"] = r["peak_rss_GB"] / first["peak_rss_GB"]
    return rows


def case_load(devices, samples, subset, repeats, bw):
    """``io.load_batch`` of a Parquet file in the standard schema (every cell checked, units,
    time base, padded batch) against the script a user would write: ``pandas.read_parquet``
    and a ``groupby`` per device into numpy arrays, no checks."""
    import tempfile

    import pandas as pd

    from diffgyro.io import load_batch

    with tempfile.TemporaryDirectory() as tmp:
        npz, path = Path(tmp) / "rec.npz", Path(tmp) / "rec.parquet"
        native_data(npz, devices, samples)
        native_table(npz, path)
        npz.unlink()

        def naive():
            frame = pd.read_parquet(path)
            return {dev: (g["t"].to_numpy(), g[["gx", "gy", "gz"]].to_numpy(),
                          g["temp"].to_numpy(), g["temp_ext"].to_numpy())
                    for dev, g in frame.groupby("device", sort=False)}

        first, dg, base, (batch, outs) = measure(lambda: load_batch(path), {"pandas": naive}, repeats)
        diff = max(float(np.max(np.abs(batch.gyro[i, :samples] - outs["pandas"][d][1])))
                   for i, d in enumerate(batch.devices))
        nbytes = path.stat().st_size
    return [row("load", devices, samples, dg, first, "pandas.read_parquet + groupby (no checks)",
                base["pandas"], diff, diff, nbytes, bw,
                note="load_batch of one Parquet file, the standard schema with temp_ext")]


COMPILE_SPECS = ("bias_poly(3)", "bias_poly(2)+scale_poly(2)+gradient+temp_diff",
                 "bias_poly(1)+thermal_lag")

COMPILE_WARMUP = "bias_poly(1)"  # fitted first in the "after another spec" processes

COMPILE_CHILD = """
import json, sys, time
import numpy as np
sys.path.insert(0, {here!r})
import diffgyro
diffgyro.use_cpu_cores({host_devices})
diffgyro.enable_x64()
if {cache!r}:
    diffgyro.enable_compilation_cache({cache!r})
import jax
import run as B
from diffgyro.fit import fit
rng = np.random.default_rng(5)
d, n = {devices}, {samples}
t, temp = B.thermal_profiles(rng, d, n)
temp_ext = 0.7 * temp + 5 + 0.5 * rng.normal(size=temp.shape)
rate = np.repeat(rng.choice([-1.0, 0.0, 1.0], size=(d, n // 200 + 1, 3)), 200, axis=1)[:, :n]
# the bias follows the temperature through a 300 s lag: every spec's fit is well posed
# (thermal_lag's τ identified in a few Newton steps), so a later call's time is steady
die = np.stack([B.lag(temp[i], 300.0) for i in range(d)])
gyro = rate * 1.001 + 1e-3 * (die - 20)[..., None] + 1e-4 * rng.normal(size=rate.shape)
batch = B.make_batch(t, gyro, temp=temp, temp_ext=temp_ext, rate=rate)
if {warmup!r}:  # another spec first: what this one adds is its own compile
    jax.block_until_ready(fit({warmup!r}, batch).params.beta)
times = []
for _ in range(3):
    t0 = time.perf_counter()
    jax.block_until_ready(fit({spec!r}, batch).params.beta)
    times.append(time.perf_counter() - t0)
print(json.dumps({{"first": times[0], "run": float(np.median(times[1:])),
                  "n_devices": len(jax.devices())}}))
"""


def case_compile(devices, samples, subset, repeats, bw, host_devices=1, specs=COMPILE_SPECS,
                 processes=1):
    """Compile time per model spec: the first fit() in a fresh process minus a later one,
    cold (no persistent compilation cache) and with the cache filled by an earlier
    process (``diffgyro.enable_compilation_cache``, on in the command line), and cold in a
    process that has fitted another spec (what a new spec adds: the model-discovery loop);
    the median over ``processes`` fresh processes of each kind."""
    import tempfile

    def child(spec, cache, warmup=""):
        code = COMPILE_CHILD.format(here=str(Path(__file__).parent), cache=cache, spec=spec,
                                    warmup=warmup, devices=devices, samples=samples,
                                    host_devices=host_devices if host_devices else None)
        return json.loads(run_child(code, timeout=600).strip().splitlines()[-1])

    def compile_s(r):
        return max(r["first"] - r["run"], 0.0)

    rows = []
    for spec in specs:
        colds = [child(spec, "") for _ in range(processes)]
        # the model-discovery loop's case: the process has fitted another spec already
        # (process-wide first-use costs paid: LAPACK's loading, the noise floor's program)
        afters = [child(spec, "", warmup=COMPILE_WARMUP) for _ in range(processes)]
        with tempfile.TemporaryDirectory() as cache:
            child(spec, cache)  # fills the cache
            warms = [child(spec, cache) for _ in range(processes)]
        cold = sorted(colds, key=compile_s)[len(colds) // 2]  # the median process
        warm = sorted(warms, key=compile_s)[len(warms) // 2]
        after = sorted(afters, key=compile_s)[len(afters) // 2]
        rows.append(row(f"compile:{spec}", devices, samples, cold["run"], cold["first"], None, None,
                        None, None, 0, bw, spec=spec,
                        compile_cached_s=compile_s(warm),
                        compile_after_other_spec_s=compile_s(after),
                        compile_after_other_spec_s_all=[compile_s(r) for r in afters],
                        compile_s_all=[compile_s(r) for r in colds],
                        compile_cached_s_all=[compile_s(r) for r in warms],
                        note="fit(spec) with defaults (noise floor included) in a fresh "
                             f"process on {cold['n_devices']} JAX devices; compile_s cold, "
                             "compile_cached_s with the persistent compilation cache filled, "
                             f"compile_after_other_spec_s cold after a fit of {COMPILE_WARMUP}"))
    return rows


CASES = {
    "bias_poly3": case_bias_poly3,
    "s2_regression": case_s2,
    "thermal_lag": case_thermal_lag,
    "kalman": case_kalman,
    "allan": case_allan,
    "diagnose": case_diagnose,
    "diagnose_native": case_diagnose_native,
    "load": case_load,
    "compile": case_compile,
}


# --------------------------------------------------------------------------- output


def fmt(x, spec=".3g"):
    if x is None:
        return "—"
    if isinstance(x, float):
        return format(x, spec)
    return str(x)


def table(rows) -> str:
    cols = [("case", "case", "s"), ("devices", "devices", "d"), ("samples", "samples", "d"),
            ("diffgyro_s", "diffgyro s", ".3g"), ("compile_s", "compile s", ".2g"),
            ("compile_cached_s", "from cache", ".2g"),
            ("compile_after_other_spec_s", "after another spec", ".2g"),
            ("baseline_s", "baseline s", ".3g"), ("speedup", "speedup", ".3g"),
            ("max_rel_diff", "max rel diff", ".1e"),
            ("fraction_of_bandwidth_limit", "of BW limit", ".1%"), ("baseline", "baseline", "s")]
    lines = ["| " + " | ".join(c[1] for c in cols) + " |", "|" + "---|" * len(cols)]
    for r in rows:
        lines.append("| " + " | ".join(fmt(r.get(k), s) for k, _, s in cols) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--quick", action="store_true", help="smaller sizes (under 3 minutes on 2 cores)")
    p.add_argument("--json", type=Path, help="write the rows to this file")
    p.add_argument("--cases", default=",".join(CASES), help="comma-separated: " + ",".join(CASES))
    p.add_argument("--repeats", type=int, default=5, help="timed runs per case (median)")
    p.add_argument("--direct-lag", action="store_true",
                   help="thermal_lag: also time fit(path='direct') (optimistix LM; slow at full size)")
    p.add_argument("--native-kinds", default="native,command",
                   help="diagnose_native: the call in a process (native), the command, or both")
    p.add_argument("--host-devices", type=int, default=1,
                   help="XLA CPU devices: 1 = JAX's default, 0 = one per core "
                        "(diffgyro.use_cpu_cores; fit() still runs on the first, Kalman and "
                        "Allan on one)")
    args = p.parse_args(argv)
    import diffgyro

    diffgyro.use_cpu_cores(args.host_devices or None)
    diffgyro.enable_x64()
    names = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = set(names) - set(CASES)
    if unknown:
        p.error(f"unknown case(s) {sorted(unknown)}; choose from {', '.join(CASES)}")
    info = machine_info()
    print(f"machine: {info['cpu']}, {info['cores']} cores; JAX {info['jax']} backend "
          f"{info['backend']} ({info['device']} × {info['n_devices']})", flush=True)
    bw = bandwidth()
    print(f"memory read bandwidth: numpy {bw['numpy_GBps']:.1f} GB/s, JAX {bw['jax_GBps']:.1f} GB/s, "
          f"JAX on all {info['n_devices']} devices {bw['jax_all_devices_GBps']:.1f} GB/s", flush=True)
    sizes = QUICK if args.quick else FULL
    rows = []
    t_all = now()
    for name in names:
        d, n = sizes[name]
        sub = SUBSET.get(name, (0, 0))[1 if args.quick else 0]
        t0 = now()
        kw = {"also_direct": args.direct_lag} if name == "thermal_lag" else \
            {"host_devices": args.host_devices, "processes": 1 if args.quick else 3} \
            if name == "compile" else \
            {"kinds": tuple(args.native_kinds.split(","))} if name == "diagnose_native" else {}
        new = CASES[name](d, n, sub, args.repeats, bw["bytes_per_s"], **kw)
        for r in new:
            r.update(mode="quick" if args.quick else "full", backend=info["backend"],
                     device=info["device"], n_devices=info["n_devices"], cpu=info["cpu"],
                     cores=info["cores"],
                     bandwidth_GBps=bw["bytes_per_s"] / 1e9)
        rows += new
        print(f"  {name}: {now() - t0:.1f} s", flush=True)
    print(table(rows))
    print(f"total {now() - t_all:.1f} s")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
