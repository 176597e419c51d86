"""A fleet's fit streamed from host memory: how close it comes to the transfer and memory limits.

The batch (``--devices`` × ``--samples``, bias_poly(3) with temperature, float64) is
held in host memory; ``diffgyro.fit`` takes it ``--chunk`` devices per call, and each
call moves its groups of devices to the accelerator and fits them. Measured in the same
process:

* the host-to-device limit: ``jax.device_put`` of a 2 GB host array (pageable memory,
  what ``fit`` sends), and where PyTorch with CUDA is installed, a copy from pinned
  memory (the link's own limit);
* the device-memory limit: an XLA sum over a 4 GB array on the device;
* the fit over every chunk, timed after a first (compiling) call on one chunk, for
  the sums path alone (``check_motion=False, noise_floor=False``) and for ``fit`` with
  its defaults (the motion check and the noise floor, both read on the host's threads).

A row's ``fraction_of_h2d`` is the time the bytes it reads (gyro, temperature and mask)
take at the host-to-device rate, over the fit's time; ``fraction_of_hbm`` the same at the
device-memory rate. The binding limit is the slower of the two. ``--group-samples``
sweeps the samples per compiled group (``diffgyro._fit_sums.groups``; each value
compiles its own program).

    python benchmarks/stream.py --devices 100000 --samples 10000 --json result.json
    python benchmarks/stream.py --devices 2000 --samples 10000      # a small CPU check
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import statistics
import sys
import time

import numpy as np

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # the shared timing, also when loaded by path
from _timing import median_time  # noqa: E402


def limits(h2d_gb: float = 2.0, hbm_gb: float = 4.0, repeats: int = 5) -> dict:
    """Host-to-device and device-memory read rates, bytes/s."""
    import jax
    import jax.numpy as jnp

    dev = jax.devices()[0]
    host = np.ones(int(h2d_gb * 1e9) // 8)
    h2d = None if dev.platform == "cpu" else host.nbytes / median_time(
        lambda: jax.device_put(host, dev).block_until_ready(), repeats)
    threaded = {}
    if h2d is not None:  # the same bytes sent by k host threads at once, 1/k each
        from concurrent.futures import ThreadPoolExecutor

        def send_all(pool, parts):
            for a in list(pool.map(lambda p: jax.device_put(p, dev), parts)):
                a.block_until_ready()

        for k in (2, 4, 8):
            with ThreadPoolExecutor(k) as pool:
                parts = np.array_split(host, k)
                threaded[k] = host.nbytes / median_time(
                    functools.partial(send_all, pool, parts), repeats)
    held = [jax.device_put(np.ones(int(hbm_gb * 1e9) // 8), dev)]
    total = jax.jit(jnp.sum)
    hbm = held[0].nbytes / median_time(lambda: total(held[0]).block_until_ready(), repeats)
    held.clear()
    out = {"h2d_pageable_Bps": h2d, "device_read_Bps": hbm, "h2d_pinned_Bps": None,
           **{f"h2d_pageable_{k}_threads_Bps": v for k, v in threaded.items()}}
    try:  # the link's own limit, from pinned memory (where PyTorch with CUDA is installed)
        import torch

        if dev.platform == "gpu" and torch.cuda.is_available():
            src = torch.ones(host.nbytes // 8, dtype=torch.float64).pin_memory()
            dst = torch.empty_like(src, device="cuda")

            def copy():
                dst.copy_(src, non_blocking=True)
                torch.cuda.synchronize()

            out["h2d_pinned_Bps"] = src.numel() * 8 / median_time(copy, repeats)
            del src, dst
            torch.cuda.empty_cache()
    except ImportError:
        pass
    return out


def fleet(devices: int, samples: int, chunk: int, seed: int = 0):
    """The fleet in host memory (t, gyro, temp; chamber-like temperatures, a cubic bias in
    temperature and white noise), made on the default JAX device chunk by chunk, and the
    true coefficients (devices, 3, 4) against the normalised temperature."""
    import jax
    import jax.numpy as jnp

    @jax.jit
    def make(key):
        k = jax.random.split(key, 6)
        s = jnp.arange(samples, dtype=jnp.float64)
        period = jax.random.uniform(k[0], (chunk, 1), minval=0.2, maxval=0.6) * samples
        phase = jax.random.uniform(k[1], (chunk, 1), maxval=2 * jnp.pi)
        mid = jax.random.uniform(k[2], (chunk, 1), minval=10.0, maxval=30.0)
        temp = mid + 35.0 * jnp.sin(2 * jnp.pi * s / period + phase)
        temp += 0.02 * jax.random.normal(k[3], temp.shape)
        lo, hi = temp.min(axis=1, keepdims=True), temp.max(axis=1, keepdims=True)
        ts = (temp - 0.5 * (lo + hi)) / jnp.maximum(0.5 * (hi - lo), 0.5)
        coef = jax.random.normal(k[4], (chunk, 3, 4)) * jnp.array([1e-2, 3e-3, 1e-3, 3e-4])
        pw = ts[..., None] ** jnp.arange(4)
        gyro = jnp.einsum("bnj,bij->bni", pw, coef) + 1e-4 * jax.random.normal(k[5], (chunk, samples, 3))
        return temp, gyro, coef

    temp = np.empty((devices, samples))
    gyro = np.empty((devices, samples, 3))
    coef = np.empty((devices, 3, 4))
    key = jax.random.PRNGKey(seed)
    for i in range(0, devices, chunk):
        key, sub = jax.random.split(key)
        tp, g, c = make(sub)
        m = min(chunk, devices - i)
        temp[i:i + m], gyro[i:i + m], coef[i:i + m] = (np.asarray(x)[:m] for x in (tp, g, c))
    t = np.broadcast_to(np.arange(samples, dtype=np.float64), (devices, samples))
    return np.ascontiguousarray(t), gyro, temp, coef


def lstsq(temp, gyro):
    """numpy's least squares of bias_poly(3) on each device's own temperature range."""
    lo, hi = temp.min(axis=1), temp.max(axis=1)
    centre, scale = 0.5 * (lo + hi), np.maximum(0.5 * (hi - lo), 0.5)
    out = np.empty((len(temp), 3, 4))
    for i in range(len(temp)):
        x = (temp[i] - centre[i]) / scale[i]
        out[i] = np.linalg.lstsq(np.vander(x, 4, increasing=True), gyro[i], rcond=None)[0].T
    return out


def batches(t, gyro, temp, chunk: int) -> list:
    """The fleet as ``diffgyro.Batch`` views of ``chunk`` devices each (no copies)."""
    from diffgyro import Batch

    d, n = temp.shape
    mask = np.ones((d, n), bool)
    out = []
    for i in range(0, d, chunk):
        s = slice(i, min(i + chunk, d))
        m = s.stop - s.start
        out.append(Batch(t=t[s], gyro=gyro[s], mask=mask[s], n_valid=np.full(m, n), temp=temp[s],
                         devices=tuple(f"d{j}" for j in range(s.start, s.stop))))
    return out


def fit_pass(parts: list, defaults: bool) -> dict:
    """One compiling call on the first chunk, then every chunk in turn: wall and CPU time,
    and the first chunk's coefficients."""
    from diffgyro.fit import fit

    kw = {} if defaults else {"check_motion": False, "noise_floor": False}
    t0 = time.perf_counter()
    first = fit("bias_poly(3)", parts[0], **kw)
    beta = np.asarray(first.params.beta)
    first_s = time.perf_counter() - t0
    per = []
    c0, t0 = time.process_time(), time.perf_counter()
    status = []
    for b in parts:
        s0 = time.perf_counter()
        r = fit("bias_poly(3)", b, **kw)
        status.append(np.asarray(r.status))
        per.append(time.perf_counter() - s0)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    status = np.concatenate(status)
    return {"first_call_s": first_s, "s": wall, "cpu_s": cpu, "per_chunk_median_s": statistics.median(per),
            "ok": int(np.sum(status == 0)), "beta_first_chunk": beta}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--devices", type=int, default=100_000)
    ap.add_argument("--samples", type=int, default=10_000)
    ap.add_argument("--chunk", type=int, default=10_000, help="devices per fit call")
    ap.add_argument("--group-samples", default="",
                    help="comma-separated samples per compiled group to sweep (sums path); "
                         "default: the package's own choice only")
    ap.add_argument("--transfer-threads", default="",
                    help="comma-separated host threads sending groups to an accelerator to "
                         "sweep (sums path, the package's group size); default: its own only")
    ap.add_argument("--no-defaults", action="store_true", help="skip fit with its defaults")
    ap.add_argument("--limit-gb", type=float, default=4.0,
                    help="size of the device-memory read (the transfers: half of it), GB")
    ap.add_argument("--json")
    args = ap.parse_args(argv)

    import jax

    import diffgyro
    from diffgyro._fit_sums import groups, transfer

    diffgyro.enable_x64()
    dev = jax.devices()[0]
    info = {"backend": jax.default_backend(), "device": getattr(dev, "device_kind", str(dev)),
            "jax": jax.__version__, "cores": os.cpu_count(), "python": platform.python_version(),
            "devices": args.devices, "samples": args.samples, "chunk": args.chunk}
    print(f"{info['backend']} ({info['device']}), {args.devices} devices × {args.samples} samples, "
          f"{args.chunk} per call", flush=True)
    lim = limits(args.limit_gb / 2, args.limit_gb)
    info.update(lim)
    print("limits: " + ", ".join(f"{k} {v / 1e9:.1f} GB/s" for k, v in lim.items() if v), flush=True)
    t0 = time.perf_counter()
    t, gyro, temp, coef = fleet(args.devices, args.samples, min(args.chunk, args.devices))
    parts = batches(t, gyro, temp, args.chunk)
    info["make_s"] = time.perf_counter() - t0
    nbytes = gyro.nbytes + temp.nbytes + temp.size  # gyro, temperature, mask
    info["bytes"] = nbytes
    print(f"fleet in host memory: {nbytes / 1e9:.1f} GB read by the fit, made in "
          f"{info['make_s']:.1f} s", flush=True)

    platform_name = dev.platform
    attr = "GROUP_SAMPLES" if platform_name == "cpu" else "ACCELERATOR_GROUP_SAMPLES"
    own = getattr(groups, attr)
    sweep = [int(x) for x in args.group_samples.split(",") if x.strip()] or [own]
    own_threads = transfer.TRANSFER_THREADS
    threads = [int(x) for x in args.transfer_threads.split(",") if x.strip()]
    runs = [("sums", g, own_threads) for g in sweep] + [("sums", own, k) for k in threads
                                                         if (own, k) != (sweep[0], own_threads)]
    runs += [] if args.no_defaults else [("defaults", own, own_threads)]
    rows = []
    m = min(50, args.chunk, args.devices)
    ref = lstsq(temp[:m], gyro[:m])
    for mode, g, k in runs:
        setattr(groups, attr, g)
        transfer.TRANSFER_THREADS = k
        try:
            per_group = groups.devices_per_call(min(args.chunk, args.devices), args.samples,
                                                False, True, platform_name, k)
            r = fit_pass(parts, mode == "defaults")
        finally:
            setattr(groups, attr, own)
            transfer.TRANSFER_THREADS = own_threads
        beta = r.pop("beta_first_chunk")[:m]
        rel = float(np.max(np.abs(beta - ref) / np.abs(ref).max(axis=-1, keepdims=True)))
        # on a CPU the fit reads the host's arrays in place: no transfer limit
        link = None if platform_name == "cpu" else (lim["h2d_pinned_Bps"] or lim["h2d_pageable_Bps"])
        limit_h2d = nbytes / link if link else 0.0
        limit_hbm = nbytes / lim["device_read_Bps"]
        row = {"mode": mode, "group_samples": g, "devices_per_group": per_group,
               "transfer_threads": k,
               **r, "GBps": nbytes / r["s"] / 1e9,
               "fraction_of_h2d": limit_h2d / r["s"] if link else None, "fraction_of_hbm": limit_hbm / r["s"],
               "fraction_of_binding": max(limit_h2d, limit_hbm) / r["s"],
               "max_rel_diff_vs_lstsq": rel}
        rows.append(row)
        print(f"  {mode:8s} group {g:>9d} samples ({row['devices_per_group']} devices), "
              f"{k} sending threads: "
              f"{r['s']:.2f} s ({row['GBps']:.1f} GB/s, CPU {r['cpu_s']:.1f} s, first call "
              f"{r['first_call_s']:.1f} s), {row['fraction_of_binding']:.0%} of the binding limit, "
              f"ok {r['ok']}/{args.devices}, against lstsq {rel:.1e}", flush=True)
        if args.json:  # after every row: a long sweep stopped early keeps what it measured
            with open(args.json, "w") as f:
                json.dump({"machine": info, "rows": rows}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
