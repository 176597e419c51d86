"""Noise identification on simulated gyros with known truth: diffgyro's GMWM against its peers.

Six structures (white + random walk; white + Gauss–Markov; white + two Gauss–Markov
with τ a decade apart; white + Gauss–Markov + random walk; white + quantization;
white + random walk + rate ramp), ``--seeds`` recordings of each. Reported per
structure: how often diffgyro chose the right structure out of its whole catalogue
(24 candidates), each parameter's relative RMSE and its 95 % intervals' coverage
(over the seeds where the structure was chosen right), and the same parameters'
RMSE from the peers:

* ``avlr``: Allan-variance linear regression, the graphical reading automated on
  allantools' overlapping ADEV: each fixed-slope line (−1 quantization, −½ ARW,
  +½ RRW, +1 ramp) fitted in log-log over the τ whose local slope is within 0.15
  of its own (ARW and RRW read at τ = 1 s and 3 s as IEEE Std 952 does);
* ``allan_variance``: the PyPI package ``allan-variance`` (non-negative least
  squares of the Allan variance on quantization, white, flicker, walk and ramp
  terms, relative weights; all its effects switched on, as it is run by default);
* ``avar``: the PyPI package ``avar`` (power-law terms and first-order
  Gauss–Markov processes fitted to the Allan variance in log space by its
  optimiser), given the true structure and the true Gauss–Markov τ as its
  starting components (the package places them by hand, interactively): an
  oracle start, which favours it.

The peers are baselines here only, not dependencies of diffgyro::

    pip install allantools allan-variance avar
    python benchmarks/noise_identification.py                  # 50 seeds, 2^16 samples
    python benchmarks/noise_identification.py --seeds 5 --n 16384 --json out.json

Results: ``benchmarks/results/noise-identification-cpu.json`` and the table in
``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the shared helpers
from _timing import cpu_name  # noqa: E402

DT = 0.01
#: Truth per structure (SI: arw rad/s/√Hz, q rad, gm ((σ rad/s, τ s), …), rrw rad/s/√s, ramp rad/s²).
TRUTHS = {
    "white + random_walk": dict(arw=1e-3, rrw=2e-4),
    "white + gauss_markov": dict(arw=1e-3, gm=((1e-3, 10.0),)),
    "white + gauss_markov×2": dict(arw=1e-3, gm=((4e-3, 0.5), (3e-3, 5.0))),
    "white + gauss_markov + random_walk": dict(arw=1e-3, gm=((3e-3, 0.5),), rrw=5.5e-4),
    "white + quantization": dict(arw=1e-3, q=1e-4),
    "white + random_walk + rate_ramp": dict(arw=1e-3, rrw=1e-3, ramp=2e-4),
}


def truth_params(kw: dict) -> dict[str, float]:
    """Flat {parameter: true value} of one structure (GM ordered by τ)."""
    out = {"arw": kw["arw"]}
    if kw.get("q"):
        out["q"] = kw["q"]
    for i, (s, t) in enumerate(sorted(kw.get("gm", ()), key=lambda p: p[1])):
        out[f"gm{i + 1}_sigma"], out[f"gm{i + 1}_tau"] = s, t
    if kw.get("rrw"):
        out["rrw"] = kw["rrw"]
    if kw.get("ramp"):
        out["r"] = kw["ramp"]
    return out


def flat_components(components: list[dict]) -> dict[str, tuple[float, float, float]]:
    """{parameter: (value, lo, hi)} of diffgyro's JSON components."""
    out, gm = {}, 0
    for c in components:
        p = c["params"]
        if c["kind"] == "gauss_markov":
            gm += 1
            for k in ("sigma", "tau"):
                out[f"gm{gm}_{k}"] = (p[k]["value"], *p[k]["ci"])
        else:
            (name, v), = p.items()
            out[name] = (v["value"], *v["ci"])
    return out


def wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson 95 % interval of a proportion k/n: how far a coverage measured on n seeds
    may sit from the intervals' true coverage (48 seeds: about ±6 points)."""
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return c - h, c + h


def avlr(tau, adev):
    """Fixed-slope line read-outs (module docstring): {arw, q, rrw, r}."""
    lt, la = np.log(tau), np.log(adev)
    slope = np.gradient(la, lt)
    out = {}
    for name, s, tread, conv in (("q", -1.0, 1.0, lambda v: v / math.sqrt(3.0)),
                                 ("arw", -0.5, 1.0, lambda v: v),
                                 ("rrw", 0.5, 3.0, lambda v: v),
                                 ("r", 1.0, 1.0, lambda v: v * math.sqrt(2.0))):
        sel = np.abs(slope - s) < 0.15
        if sel.sum() < 2:
            continue
        b = np.mean(la[sel] - s * lt[sel])  # log σ = b + s·log τ
        out[name] = conv(math.exp(b + s * math.log(tread)))
    return out


def peers(y: np.ndarray, kw: dict, report: dict) -> dict:
    """Every available peer's read-outs of one series: {peer: {param: value}}."""
    out: dict[str, dict] = {}
    try:
        import allantools
    except ImportError:
        report["skipped"].add("avlr (pip install allantools)")
    else:
        n = len(y)
        taus = DT * np.unique(np.round(np.logspace(0, math.log10(n // 4), 40)).astype(int))
        t, ad, _, _ = allantools.oadev(y, rate=1.0 / DT, data_type="freq", taus=taus)
        out["avlr"] = avlr(np.asarray(t), np.asarray(ad))
    try:
        from allan_variance import compute_avar, estimate_parameters
    except ImportError:
        report["skipped"].add("allan_variance (pip install allan-variance)")
    else:
        tau, av = compute_avar(y, DT)
        params, _ = estimate_parameters(tau, av)
        got = {"arw": params["white"], "q": params["quantization"], "rrw": params["walk"],
               "r": params["ramp"]}
        out["allan_variance"] = {k: float(v) for k, v in got.items() if float(v) > 0}
    try:
        import avar
    except ImportError:
        report["skipped"].add("avar (pip install avar)")
    else:
        out["avar"] = avar_oracle(avar, y, kw)
    return out


def avar_oracle(avar, y, kw):
    """The ``avar`` package's fit from the true structure (its components placed at the truth)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.optimize import leastsq

    n = len(y)
    M = np.unique(np.round(np.logspace(0, math.log10(n // 4), 40)).astype(int))
    with contextlib.redirect_stdout(io.StringIO()):
        va = avar.variance(y, M)
    tau = M * DT
    comps = [(-1, kw["arw"] ** 2, None, "arw")]
    if kw.get("q"):
        comps.append((-2, kw["q"] ** 2, None, "q"))
    for i, (s, t) in enumerate(sorted(kw.get("gm", ()), key=lambda p: p[1])):
        comps.append((0, s**2, t, f"gm{i + 1}_sigma"))
    if kw.get("rrw"):
        comps.append((1, kw["rrw"] ** 2, None, "rrw"))
    if kw.get("ramp"):
        comps.append((2, kw["ramp"] ** 2, None, "r"))
    ks = [[c[0], c[1]] + ([c[2]] if c[2] is not None else []) for c in comps]
    names = [c[3] for c in comps]
    fit = avar.fit(tau, va, T=DT, ks=ks)
    k1 = leastsq(fit.fopt, [math.log10(k[1]) for k in fit.ks], maxfev=1000)[0]
    plt.close("all")
    return {name: math.sqrt(10.0 ** v) for name, v in zip(names, k1)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--n", type=int, default=1 << 16, help="samples per recording (100 Hz)")
    ap.add_argument("--penalty", type=float, default=None)
    ap.add_argument("--no-peers", action="store_true")
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--timing", type=int, default=0, metavar="DEVICES",
                    help="only time identify on DEVICES × 3 axes of --n samples against the "
                         "allan-variance fit of the same series (and allantools on 3)")
    ap.add_argument("--repeat", type=int, default=3, help="warm repeats of --timing (median)")
    ap.add_argument("--slow-part", action="store_true",
                    help="--timing: identify with the slow part chosen by the block likelihood, "
                         "and without it in the same run (process and wall times of both)")
    args = ap.parse_args(argv)
    if args.timing:
        return timing(args)

    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from diffgyro.stochastic import identify, label, simulate_noise
    from diffgyro.stochastic._selection import PENALTY

    penalty = PENALTY if args.penalty is None else args.penalty
    names = list(TRUTHS)
    ys = []
    for i, name in enumerate(names):
        kw = TRUTHS[name]
        keys = jax.random.split(jax.random.PRNGKey(1000 + i), args.seeds)
        f = jax.jit(jax.vmap(lambda k, kw=kw: simulate_noise(k, args.n, DT, **kw)))
        ys.append(np.asarray(f(keys)))
    y = np.stack(ys)  # (structures, seeds, n)
    t0 = time.perf_counter()
    res = identify(jnp.asarray(y), DT, penalty=penalty)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    identify(jnp.asarray(y), DT, penalty=penalty)
    warm = time.perf_counter() - t0

    report = {"skipped": set()}
    rows = []
    for i, name in enumerate(names):
        kw = TRUTHS[name]
        truth = truth_params(kw)
        right = [label(res.structure(i, s)) == name for s in range(args.seeds)]
        est = {k: [] for k in truth}
        cover = {k: [] for k in truth}
        for s in range(args.seeds):
            if not right[s]:
                continue
            got = flat_components(res.components(i, s))
            for k, v in truth.items():
                val, lo, hi = got[k]
                est[k].append(val)
                cover[k].append(lo is not None and hi is not None and lo <= v <= hi)
        peer_est: dict[str, dict[str, list]] = {}
        if not args.no_peers:
            for s in range(args.seeds):
                for peer, vals in peers(y[i, s], kw, report).items():
                    for k, v in vals.items():
                        if k in truth:
                            peer_est.setdefault(peer, {}).setdefault(k, []).append(v)
        params = {}
        for k, v in truth.items():
            e = np.asarray(est[k])
            row = {"truth": v, "n": int(e.size),
                   "rel_rmse": float(np.sqrt(np.mean((e / v - 1.0) ** 2))) if e.size else None,
                   "coverage_95": float(np.mean(cover[k])) if cover[k] else None,
                   "coverage_95_ci": list(wilson(int(np.sum(cover[k])), len(cover[k])))
                   if cover[k] else None}
            for peer, vals in peer_est.items():
                if k in vals:
                    pe = np.asarray(vals[k])
                    row[f"{peer}_rel_rmse"] = float(np.sqrt(np.mean((pe / v - 1.0) ** 2)))
                    row[f"{peer}_n"] = int(pe.size)
            params[k] = row
        wrong = {}
        for s in range(args.seeds):
            if not right[s]:
                lab = label(res.structure(i, s))
                wrong[lab] = wrong.get(lab, 0) + 1
        rows.append({"structure": name, "truth": {k: list(map(list, v)) if k == "gm" else v
                                                  for k, v in kw.items()},
                     "chosen_right": float(np.mean(right)), "chosen_instead": wrong,
                     "params": params})
        print(f"{name:38s} chosen {100 * np.mean(right):5.1f} %  " + "  ".join(
            f"{k}: rmse {p['rel_rmse'] if p['rel_rmse'] is not None else float('nan'):.3f} "
            f"cov {p['coverage_95'] if p['coverage_95'] is not None else float('nan'):.2f}"
            for k, p in params.items()), flush=True)
        if wrong:
            print(f"{'':38s} instead: {wrong}")
    out = {"benchmark": "noise_identification", "seeds": args.seeds, "samples": args.n,
           "dt": DT, "penalty": penalty, "series": int(y.shape[0] * y.shape[1]),
           "identify_first_call_s": first, "identify_warm_s": warm,
           "machine": cpu_name(),
           "jax_backend": jax.default_backend(), "skipped_peers": sorted(report["skipped"]),
           "structures": rows}
    print(f"identify: {y.shape[0] * y.shape[1]} series of {args.n} samples: first call "
          f"{first:.1f} s, warm {warm:.1f} s")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


def timing(args) -> int:
    """Time identify on devices × 3 axes of white + Gauss–Markov noise, and the fastest peer."""
    import jax

    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from diffgyro.stochastic import SLOW_PENALTY, identify, simulate_noise

    f = jax.jit(jax.vmap(lambda k: simulate_noise(k, args.n, DT, arw=1e-3, gm=((1e-3, 10.0),))))
    keys = jax.random.split(jax.random.PRNGKey(0), args.timing * 3)
    y = jnp.concatenate([f(keys[i:i + 30]) for i in range(0, len(keys), 30)])
    y = y.reshape(args.timing, 3, args.n).block_until_ready()
    slow = SLOW_PENALTY if args.slow_part else None
    t0, c0 = time.perf_counter(), time.process_time()
    identify(y, DT, slow_penalty=slow)
    first, first_cpu = time.perf_counter() - t0, time.process_time() - c0
    peer, bare, cpu, bare_cpu, chi2_cpu, theirs_cpu = {}, [], [], [], [], []
    try:
        from allan_variance import compute_avar, estimate_parameters
    except ImportError:
        compute_avar = None
    yy = np.asarray(y)
    ours, theirs = [], []
    for _ in range(args.repeat):  # interleaved, medians (timings vary between runs)
        t0, c0 = time.perf_counter(), time.process_time()
        res = identify(y, DT, slow_penalty=slow)
        ours.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        if args.slow_part:
            t0, c0 = time.perf_counter(), time.process_time()
            identify(y, DT)
            bare.append(time.perf_counter() - t0)
            bare_cpu.append(time.process_time() - c0)
            c0 = time.process_time()  # the slow part by the χ² rule alone, no draws
            identify(y, DT, slow_penalty=slow, slow_bootstrap=False)
            chi2_cpu.append(time.process_time() - c0)
        if compute_avar is not None:
            t0, c0 = time.perf_counter(), time.process_time()
            for d in range(args.timing):
                for a in range(3):
                    tau, av = compute_avar(yy[d, a], DT)
                    estimate_parameters(tau, av)
            theirs.append(time.perf_counter() - t0)
            theirs_cpu.append(time.process_time() - c0)
    warm = float(np.median(ours))
    if theirs:
        peer["allan_variance_fit_s"] = float(np.median(theirs))
        peer["allan_variance_fit_process_s"] = float(np.median(theirs_cpu))
    try:
        import allantools

        yy = np.asarray(y[0])
        m = 2 ** np.arange(int(math.log2(args.n // 4)) + 1)
        t0 = time.perf_counter()
        for a in range(3):
            allantools.oadev(yy[a], rate=1.0 / DT, data_type="freq", taus=m * DT)
        peer["allantools_oadev_s_per_series"] = (time.perf_counter() - t0) / 3
    except ImportError:
        pass
    out = {"benchmark": "noise_identification_timing", "devices": args.timing, "axes": 3,
           "samples": args.n, "identify_first_call_s": first,
           "identify_first_call_process_s": first_cpu, "identify_warm_s": warm,
           "identify_warm_runs_s": ours, "identify_warm_process_s": float(np.median(cpu)),
           "slow_part": bool(args.slow_part), "backend": jax.default_backend(), "device": str(jax.devices()[0]),
           "chosen_white_gm": float(np.mean([len(res.structure(i, a)) == 2 and
                                             res.structure(i, a)[1] == "gauss_markov"
                                             for i in range(args.timing) for a in range(3)])),
           **peer}
    if bare:  # the same identification without the slow part, interleaved
        out["identify_no_slow_part_warm_s"] = float(np.median(bare))
        out["identify_no_slow_part_warm_process_s"] = float(np.median(bare_cpu))
        out["identify_slow_part_chi2_warm_process_s"] = float(np.median(chi2_cpu))
    if peer:
        out["allantools_dyadic_curves_only_s"] = peer["allantools_oadev_s_per_series"] * args.timing * 3
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
