"""Noise identification's acceptance run: a generator of its own, many structures, rates, lengths.

Thirteen cases of twelve noise structures (white; + quantization; + random walk; +
Gauss–Markov; two Gauss–Markov processes; Gauss–Markov + random walk; random walk + ramp;
quantization + random walk; ramp; quantization + Gauss–Markov; two Gauss–Markov + random
walk; Gauss–Markov + ramp), recorded at 10 to 400 Hz for 10 minutes to 4 hours, three
axes each (amplitudes ×1, ×0.8, ×1.25 of the case's), ``--seeds`` recordings of each.

The series come from this file's own numpy generator, not from diffgyro's simulator:

* white rate noise: N/√dt per sample;
* quantization: an angle read-out error drawn afresh each sample, uniform over a step
  Δ = √12·Q (variance Δ²/12 = Q²), the rate its difference over dt: IEEE Std 952's
  quantization noise. (Rounding the integrated angle itself is that only where the angle
  moves many steps per sample; where it moves less, as at 400 Hz with steps large enough
  to show, the rounding error is correlated from sample to sample and is another process:
  the first run of this file did that, and every interval missed its Q);
* Gauss–Markov: the AR(1) recursion b_k = φ·b_(k−1) + σ·√(1−φ²)·w_k, φ = e^(−dt/T),
  started from its stationary law (``scipy.signal.lfilter``);
* random walk: the running sum of K·√dt·w_k; ramp: R·t.

Reported: how often diffgyro's reported structure (after what the record cannot resolve
is merged) is the truth, per case and over every axis, and how often each parameter's
95 % interval covers its truth (over the axes whose structure is right).

    python benchmarks/noise_acceptance.py --seeds 4 --json benchmarks/results/noise-acceptance-cpu.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from noise_identification import flat_components, truth_params  # the scoring is shared
from scipy.signal import lfilter

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the shared helpers
from _timing import cpu_name  # noqa: E402

#: (name, rate Hz, length s, truth): arw rad/s/√Hz, q rad, gm ((σ rad/s, T s), …),
#: rrw rad/s/√s, ramp rad/s².
CASES = [
    ("white", 400.0, 600.0, dict(arw=1e-3)),
    ("white + quantization", 400.0, 600.0, dict(arw=1e-3, q=1e-4)),
    ("white + random_walk", 100.0, 3600.0, dict(arw=1e-3, rrw=3.5e-5)),
    ("white + gauss_markov", 100.0, 600.0, dict(arw=1e-3, gm=((2e-3, 5.0),))),
    ("white + gauss_markov", 10.0, 600.0, dict(arw=1e-3, gm=((2e-3, 3.0),))),
    ("white + gauss_markov×2", 200.0, 7200.0, dict(arw=1e-3, gm=((3e-3, 2.0), (1e-3, 500.0)))),
    ("white + gauss_markov + random_walk", 50.0, 14400.0,
     dict(arw=1e-3, gm=((1e-3, 60.0),), rrw=5e-5)),
    ("white + random_walk + rate_ramp", 10.0, 14400.0, dict(arw=1e-3, rrw=2e-5, ramp=1e-6)),
    ("white + quantization + random_walk", 200.0, 1800.0, dict(arw=1e-3, q=1e-4, rrw=5e-5)),
    ("white + rate_ramp", 100.0, 3600.0, dict(arw=1e-3, ramp=3e-6)),
    ("white + quantization + gauss_markov", 400.0, 1800.0,
     dict(arw=1e-3, q=5e-5, gm=((1e-3, 20.0),))),
    ("white + gauss_markov×2 + random_walk", 100.0, 14400.0,
     dict(arw=1e-3, gm=((3e-3, 1.0), (1e-3, 100.0)), rrw=2e-5)),
    ("white + gauss_markov + rate_ramp", 50.0, 7200.0, dict(arw=1e-3, gm=((1e-3, 30.0),), ramp=5e-7)),
]
#: Amplitude factor of each axis.
AXIS_SCALE = (1.0, 0.8, 1.25)


def generate(rng: np.random.Generator, n: int, dt: float, kw: dict) -> np.ndarray:
    """One rate series (n,) in rad/s of the truth ``kw`` (module docstring)."""
    y = kw["arw"] / math.sqrt(dt) * rng.standard_normal(n)
    for s, tc in kw.get("gm", ()):
        phi = math.exp(-dt / tc)
        w = s * math.sqrt(1.0 - phi * phi) * rng.standard_normal(n)
        b0 = s * rng.standard_normal()
        y += lfilter([1.0], [1.0, -phi], w, zi=[phi * b0])[0]
    if kw.get("rrw"):
        y += np.cumsum(kw["rrw"] * math.sqrt(dt) * rng.standard_normal(n))
    if kw.get("ramp"):
        y += kw["ramp"] * dt * np.arange(n)
    if kw.get("q"):
        step = math.sqrt(12.0) * kw["q"]
        err = rng.uniform(-0.5 * step, 0.5 * step, n + 1)
        y += np.diff(err) / dt
    return y


def scaled(kw: dict, k: float) -> dict:
    """The truth with every amplitude times ``k`` (times unchanged)."""
    out = {key: v * k for key, v in kw.items() if key != "gm"}
    if "gm" in kw:
        out["gm"] = tuple((s * k, t) for s, t in kw["gm"])
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=4)
    ap.add_argument("--cases", type=str, default=None, help="comma-separated case indices")
    ap.add_argument("--seed-base", type=int, default=4200,
                    help="case i's recordings drawn from seed SEED_BASE + i (other records of the same truths)")
    ap.add_argument("--slow-part", action="store_true",
                    help="choose the slow part again by the block means' likelihood (identify's step 5)")
    ap.add_argument("--chi2", action="store_true",
                    help="with --slow-part: the χ² rule alone (no bootstrap of its close calls)")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    from diffgyro.stochastic import SLOW_PENALTY, identify, label

    pick = range(len(CASES)) if args.cases is None else [int(c) for c in args.cases.split(",")]
    rows, total_right, total_axes = [], 0, 0
    cover_all: list[bool] = []
    t_id, cpu_id = 0.0, 0.0
    for ci in pick:
        name, rate, length, kw = CASES[ci]
        dt, n = 1.0 / rate, int(round(rate * length))
        rng = np.random.default_rng(args.seed_base + ci)
        truths = [scaled(kw, k) for k in AXIS_SCALE]
        y = np.stack([np.stack([generate(rng, n, dt, tr) for tr in truths])
                      for _ in range(args.seeds)])  # (seeds, 3, n)
        t0, c0 = time.perf_counter(), time.process_time()
        res = identify(y, dt, slow_penalty=SLOW_PENALTY if args.slow_part else None,
                       slow_bootstrap=not args.chi2)
        t_id += time.perf_counter() - t0
        cpu_id += time.process_time() - c0
        right, cover, wrong = 0, {}, {}
        err: dict[str, list] = {}
        for s in range(args.seeds):
            for a in range(3):
                got = label(res.reported_structure(s, a))
                if got != name:
                    wrong[got] = wrong.get(got, 0) + 1
                    continue
                right += 1
                comps = flat_components(res.components(s, a))
                for k, v in truth_params(truths[a]).items():
                    val, lo, hi = comps[k]
                    ok = lo is not None and hi is not None and lo <= v <= hi
                    cover.setdefault(k, []).append(ok)
                    cover_all.append(ok)
                    err.setdefault(k, []).append(val / v - 1.0)
        axes = 3 * args.seeds
        total_right += right
        total_axes += axes
        row = {"case": ci, "structure": name, "rate_hz": rate, "length_s": length, "samples": n,
               "truth": {k: [list(p) for p in v] if k == "gm" else v for k, v in kw.items()},
               "axes": axes, "structure_right": right / axes, "chosen_instead": wrong,
               "coverage_95": {k: float(np.mean(v)) for k, v in cover.items()},
               "rel_rmse": {k: float(np.sqrt(np.mean(np.square(v)))) for k, v in err.items()}}
        rows.append(row)
        print(f"[{ci:2d}] {name:38s} {rate:5.0f} Hz {length / 60:6.0f} min  right {right}/{axes}"
              f"  cover " + " ".join(f"{k} {v:.2f}" for k, v in row["coverage_95"].items())
              + (f"  instead {wrong}" if wrong else ""), flush=True)
    out = {"benchmark": "noise_acceptance", "seeds": args.seeds, "axes": total_axes,
           "structure_right": total_right / max(total_axes, 1),
           "coverage_95": float(np.mean(cover_all)) if cover_all else None,
           "intervals": len(cover_all), "seed_base": args.seed_base, "identify_s": t_id, "identify_process_s": cpu_id,
           "slow_part": bool(args.slow_part), "bootstrap": bool(args.slow_part and not args.chi2),
           "machine": cpu_name(),
           "jax_backend": jax.default_backend(), "cases": rows}
    print(f"structure right on {total_right}/{total_axes} axes ({100 * out['structure_right']:.1f} %); "
          f"95 % intervals cover {100 * (out['coverage_95'] or 0):.1f} % of {len(cover_all)}; "
          f"identify {t_id:.1f} s ({cpu_id:.1f} s of CPU)")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
