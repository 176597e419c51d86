"""Start-up time of the command line: ``--help`` answers without starting JAX.

Each command is run as its own process (``python -m diffgyro ...``), ``--runs`` times;
reported per command: the median, the fastest and the slowest wall time, start to
exit, and whether the process imported JAX (``-X importtime`` names every module a
process imports). For comparison, the same for ``python -c 'import jax'`` (what a
command pays once it runs) and for the bare interpreter. Goal: ≤ 0.5 s median for
``diffgyro --help`` and every ``diffgyro COMMAND --help``::

    python benchmarks/cli_help.py                      # 7 runs each
    python benchmarks/cli_help.py --runs 11 --json benchmarks/results/cli-help-cpu.json

Results: ``benchmarks/results/cli-help-cpu.json`` and the table in
``benchmarks/README.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the shared helpers
from _timing import cpu_name  # noqa: E402

COMMANDS = [["--help"], ["fit", "--help"], ["diagnose", "--help"], ["export", "--help"],
            ["recipe", "--help"], ["allan", "--help"], ["noise", "--help"],
            ["compensate", "--help"], ["simulate", "--help"], ["effects", "--help"],
            ["fit", "missing.csv", "--model", "bias_poly(1)"], ["fit", "--no-such-option"]]
GOAL_S = 0.5


def _time(argv: list[str], runs: int) -> dict:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False)
        times.append(time.perf_counter() - t0)
    trace = subprocess.run([argv[0], "-X", "importtime", *argv[1:]], capture_output=True,
                           text=True, check=False).stderr
    jax = any(line.rsplit("|", 1)[-1].strip() == "jax" for line in trace.splitlines())
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times),
            "runs": runs, "imports_jax": jax}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--runs", type=int, default=7, help="processes per command (default 7)")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    py = sys.executable
    rows = []
    cases = [("python (bare)", [py, "-c", "pass"]), ("python -c 'import jax'", [py, "-c", "import jax"])]
    cases += [("diffgyro " + " ".join(c), [py, "-m", "diffgyro", *c]) for c in COMMANDS]
    print(f"{'command':48s} {'median s':>9s} {'min s':>7s} {'max s':>7s}  jax")
    for name, argv in cases:
        row = {"command": name, **_time(argv, args.runs)}
        rows.append(row)
        print(f"{name:48s} {row['median_s']:9.3f} {row['min_s']:7.3f} {row['max_s']:7.3f}  "
              f"{'yes' if row['imports_jax'] else 'no'}")
    helps = [r for r in rows if r["command"].startswith("diffgyro") and "--help" in r["command"]]
    worst = max(r["median_s"] for r in helps)
    ok = worst <= GOAL_S and not any(r["imports_jax"] for r in rows[2:])
    print(f"slowest --help median {worst:.3f} s (goal ≤ {GOAL_S} s, no JAX): {'met' if ok else 'NOT met'}")
    if args.json:
        meta = {"machine": cpu_name(), "cores": os.cpu_count(), "python": platform.python_version(),
                "goal_s": GOAL_S, "goal_met": ok}
        with open(args.json, "w") as f:
            json.dump([{**meta, **r} for r in rows], f, indent=1)
            f.write("\n")


if __name__ == "__main__":
    main()
