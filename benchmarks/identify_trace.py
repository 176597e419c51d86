"""Trace and lowering time of the noise identification's programs (the cold part of a first
``noise`` call that runs on one core: XLA compiles the fits' program while the choice's
is traced, and the choice's after that).

Each source tree runs in a fresh process, in turn (a change of the machine's load touches
every tree alike): the programs :func:`diffgyro.stochastic.identify` compiles for SERIES
series of N samples (a tree with one program: that one) are traced and lowered
``--repeat`` times, JAX's caches cleared before
each (``jax.clear_caches``: every trace as in a fresh process), and the thread CPU time of
each step is reported (median and minimum of the repeats after the first; the machine's
other work disturbs thread time less than wall time).

    python benchmarks/identify_trace.py --trees before=../main/src,after=src --rounds 3
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

#: The child: traces and lowers the program, prints its times as JSON.
CHILD = r"""
import functools, json, sys, time
import jax
jax.config.update("jax_enable_x64", True)
from diffgyro.stochastic import _identify, catalogue
from diffgyro.stochastic._wavelet_variance import dyadic_m
series, n, repeat = (int(a) for a in sys.argv[1:4])
scales = len(dyadic_m(n))
if hasattr(_identify, "program_specs"):  # the fits' and the choice's programs
    fits, choice = _identify.program_specs(series, n, catalogue(2))
    bodies = [(functools.partial(_identify._fits_series, n_scales=scales), fits[:-1]),
              (_identify._choice_series, choice)]
else:  # one program
    bodies = [(functools.partial(_identify._identify_series, n_scales=scales),
               _identify.chunk_specs(series, n, catalogue(2)))]
trace, lower = [], []
for _ in range(repeat):
    jax.clear_caches()
    took = [0.0, 0.0]
    for body, specs in bodies:
        c0 = time.thread_time()
        traced = jax.jit(body).trace(*specs)
        c1 = time.thread_time()
        traced.lower()
        took[0] += c1 - c0
        took[1] += time.thread_time() - c1
    trace.append(took[0])
    lower.append(took[1])
print(json.dumps({"trace": trace, "lower": lower}))
"""


def _child(src: str | None, series: int, n: int, repeat: int) -> dict:
    env = dict(os.environ)
    if src is not None:
        env["PYTHONPATH"] = os.pathsep.join([src, *filter(None, [env.get("PYTHONPATH")])])
    run = subprocess.run([sys.executable, "-c", CHILD, str(series), str(n), str(repeat)],
                         env=env, capture_output=True, text=True, check=True)
    return json.loads(run.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--series", type=int, default=3, help="series (devices × axes)")
    ap.add_argument("--n", type=int, default=12000, help="samples per series")
    ap.add_argument("--repeat", type=int, default=8, help="traces per process")
    ap.add_argument("--rounds", type=int, default=3, help="processes per tree, in turn")
    ap.add_argument("--trees", help="NAME=SRC,...: source trees (default: the installed one)")
    ap.add_argument("--json")
    args = ap.parse_args()
    trees = dict(t.split("=", 1) for t in args.trees.split(",")) if args.trees else {"installed": None}
    runs: dict = {name: [] for name in trees}
    loads = []
    for _ in range(args.rounds):
        for name, src in trees.items():
            loads.append(round(os.getloadavg()[0], 2))
            runs[name].append(_child(src, args.series, args.n, max(args.repeat, 2)))
    rows = {}
    print("| tree | trace s (median) | trace s (min) | lower s (median) | lower s (min) |")
    print("|---|---|---|---|---|")
    for name, rs in runs.items():
        trace = [t for r in rs for t in r["trace"][1:]]
        lower = [t for r in rs for t in r["lower"][1:]]
        rows[name] = {"src": trees[name], "trace_median_s": round(statistics.median(trace), 3),
                      "trace_min_s": round(min(trace), 3),
                      "lower_median_s": round(statistics.median(lower), 3),
                      "lower_min_s": round(min(lower), 3), "runs": rs}
        r = rows[name]
        print(f"| {name} | {r['trace_median_s']:.3f} | {r['trace_min_s']:.3f} "
              f"| {r['lower_median_s']:.3f} | {r['lower_min_s']:.3f} |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"series": args.series, "n": args.n, "repeat": args.repeat,
                       "rounds": args.rounds, "cores": os.cpu_count(), "load_1min": loads,
                       "trees": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
