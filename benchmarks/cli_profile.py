"""Where one command's time goes: the walkthrough's ``fit``, ``diagnose``, ``noise``,
``compensate``, ``export`` and ``effects``, each run warm (its programs already in the persistent caches) in a process that times
its own parts.

The process times ``import jax, equinox`` first, then runs the command in-process
(``diffgyro.cli.main``) with timers around JAX's steps: the rest of the imports, tracing
(``trace_to_jaxpr_dynamic``), lowering to StableHLO (``lower_jaxpr_to_module``), reads
of the persistent caches (XLA's compiled programs, and diffgyro's stored traced
programs, ``jax.export.deserialize``), and XLA compilation (``backend_compile_and_load``:
a program the cache does not hold). Each timer counts its own time, not that of a timed
step inside it; what no timer holds is the command's work itself (the numerical
passes, loading and checking the file, tables) and Python around it. Interpreter
start-up is measured apart (``python -c pass``), and the wall time of the same command
run plainly less the parts above is the process's exit and what no part holds.

    python benchmarks/cli_profile.py --json benchmarks/results/cli-profile-cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: (name, set-up commands, the command timed), on the walkthrough's files.
CASES = [
    ("fit", [["simulate", "--plan", "thermal", "--devices", "2", "--duration", "3600", "--rate",
              "2", "--effects", "bias_poly(2)+gradient", "--out", "x.csv"]],
     ["fit", "x.csv", "--model", "bias_poly(2)+gradient", "--out", "cal.json"]),
    ("diagnose", [], ["diagnose", "x.csv", "--model", "bias_poly(2)"]),
    ("noise", [["simulate", "--plan", "static", "--devices", "1", "--duration", "1200",
                "--rate", "10", "--noise", "rrw=2e-5", "--out", "static.csv"]],
     ["noise", "static.csv", "--json"]),
    ("compensate", [], ["compensate", "x.csv", "--cal", "cal.json", "--out", "corrected.csv"]),
    ("export px4", [["fit", "x.csv", "--model", "bias_poly(3)", "--out", "cal3.json"]],
     ["export", "cal3.json", "--format", "px4", "--device-id", "2293768,2293776", "--out",
      "px4.params"]),
    ("effects", [], ["effects"]),
]

#: The child: times its parts and prints them as JSON on its last stderr line.
CHILD = r"""
import builtins, importlib._bootstrap as boot, json, sys, time
t0 = time.perf_counter()
import jax, equinox
t_jax = time.perf_counter() - t0
from jax._src import compiler
from jax._src.interpreters import mlir, partial_eval as pe
import jax.export

spent, stack = {}, []

def timed(kind, fn):
    def run(*a, **k):
        stack.append([time.perf_counter(), 0.0])
        try:
            return fn(*a, **k)
        finally:
            start, inner = stack.pop()
            took = time.perf_counter() - start
            spent[kind] = spent.get(kind, 0.0) + took - inner
            if stack:
                stack[-1][1] += took
    return run

boot._find_and_load = timed("imports", boot._find_and_load)
pe.trace_to_jaxpr_dynamic = timed("trace", pe.trace_to_jaxpr_dynamic)
mlir.lower_jaxpr_to_module = timed("lower", mlir.lower_jaxpr_to_module)
compiler._cache_read = timed("cache reads", compiler._cache_read)
jax.export.deserialize = timed("cache reads", jax.export.deserialize)
compiler.backend_compile_and_load = timed("compile", compiler.backend_compile_and_load)
t1 = time.perf_counter()
from diffgyro.cli import main
code = main(sys.argv[1:])
total = time.perf_counter() - t1
spent["imports"] = spent.get("imports", 0.0)
print(json.dumps({"jax import": t_jax, "in command": total, **spent, "exit": code}), file=sys.stderr)
"""


def _child(args: list[str], cwd: Path, env: dict) -> dict:
    run = subprocess.run([sys.executable, "-c", CHILD, *args], cwd=cwd, env=env,
                         capture_output=True, text=True, check=True)
    return json.loads(run.stderr.strip().splitlines()[-1])


def _wall(args: list[str], cwd: Path, env: dict) -> float:
    t0 = time.perf_counter()
    subprocess.run(args, cwd=cwd, env=env, capture_output=True, check=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json")
    ap.add_argument("--runs", type=int, default=3, help="warm runs per command; medians")
    args = ap.parse_args()
    work = Path(tempfile.mkdtemp())
    env = {**os.environ, "DIFFGYRO_CACHE_DIR": str(work / "cache")}
    start = statistics.median(_wall([sys.executable, "-c", "pass"], work, env) for _ in range(5))
    rows = []
    for name, setup, cmd in CASES:
        for s in setup:
            subprocess.run([sys.executable, "-m", "diffgyro", *s], cwd=work, env=env,
                           capture_output=True, check=True)
        subprocess.run([sys.executable, "-m", "diffgyro", *cmd], cwd=work, env=env,
                       capture_output=True, check=False)  # fills the caches
        runs = [_child(cmd, work, env) for _ in range(args.runs)]
        wall = statistics.median(_wall([sys.executable, "-m", "diffgyro", *cmd], work, env)
                                 for _ in range(args.runs))
        keys = ["jax import", "imports", "cache reads", "trace", "lower", "compile", "in command"]
        med = {k: statistics.median(r.get(k, 0.0) for r in runs) for k in keys}
        med["work"] = med["in command"] - sum(med[k] for k in keys[1:-1])
        med["exit and the rest"] = wall - start - med["jax import"] - med["in command"]
        rows.append({"command": name, "wall_s": round(wall, 3), "python_start_s": round(start, 3),
                     **{k: round(v, 3) for k, v in med.items()}, "runs": args.runs})
    cols = ["python_start_s", "jax import", "imports", "cache reads", "trace", "lower",
            "compile", "work", "exit and the rest"]
    print("| command | wall s | python start | " + " | ".join(cols[1:]) + " |")
    print("|---|" + "---|" * (len(cols) + 1))
    for r in rows:
        print(f"| {r['command']} | {r['wall_s']:.2f} | "
              + " | ".join(f"{r[c]:.2f}" for c in cols) + " |")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"rows": rows, "cores": os.cpu_count()}, fh, indent=1)


if __name__ == "__main__":
    main()
