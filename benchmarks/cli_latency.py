"""Wall time of every command of the README walkthrough, as a user runs it: cold (a fresh
persistent cache) and warm (the same command again, the caches filled), in one run.

Each command runs as its own process (``python -m diffgyro ...``) in a fresh folder, on
the walkthrough's files; the table gives the wall time from start to exit (and the child's CPU
time, user + system over its threads, which a shared machine disturbs less), the goal of
each command (issue 45: fit ≤ 1.5 s, diagnose ≤ 2.5 s, noise ≤ 1.5 s, the commands that
need no compiled program ≤ 0.5 s, cold ≤ 2× warm) and whether it is met.

    python benchmarks/cli_latency.py --json benchmarks/results/cli-latency-cpu.json

``--repeat N`` runs the walkthrough N times, each in a fresh folder and cache, and gives
the median of each command's cold and warm times (on a shared machine one run is noisy).
``--only NAMES`` times those commands alone (the ones whose files they read run once first).
``--trees main=../main/src,branch=src`` runs each walkthrough of each repeat on every source
tree in turn (a change of the machine's load touches both alike), one table per tree, to
compare a change with the tree before it.

The package's bytecode is compiled first (as ``pip install`` does for the files it
installs, and as Python does on a first import): a machine that sets
``PYTHONDONTWRITEBYTECODE`` would otherwise compile every module of the package from its
source in every command, which a user's installation never does.
"""

from __future__ import annotations

import argparse
import compileall
import importlib.util
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the shared helpers
from _timing import cpu_name  # noqa: E402

#: (name, arguments, goal warm s): the README walkthrough in order, then the small ones.
COMMANDS = [
    ("simulate thermal", ["simulate", "--plan", "thermal", "--devices", "2", "--duration", "3600",
                          "--rate", "2", "--effects", "bias_poly(2)+gradient", "--out", "x.csv"], None),
    ("diagnose", ["diagnose", "x.csv", "--model", "bias_poly(2)"], 2.5),
    ("fit", ["fit", "x.csv", "--model", "bias_poly(2)+gradient", "--out", "cal.json"], 1.5),
    ("compensate", ["compensate", "x.csv", "--cal", "cal.json", "--out", "corrected.csv"], 0.5),
    ("fit cubic", ["fit", "x.csv", "--model", "bias_poly(3)", "--out", "cal3.json"], 1.5),
    ("export px4", ["export", "cal3.json", "--format", "px4", "--device-id", "2293768,2293776",
                    "--out", "px4.params"], 0.5),
    ("export ardupilot", ["export", "cal3.json", "--format", "ardupilot", "--out", "ardupilot.parm"], 0.5),
    ("export c-header", ["export", "cal3.json", "--format", "c-header", "--device", "dev000",
                         "--out", "gyro_cal.h"], 0.5),
    ("simulate static", ["simulate", "--plan", "static", "--devices", "1", "--duration", "1200",
                         "--rate", "10", "--noise", "rrw=2e-5", "--out", "static.csv"], None),
    ("allan", ["allan", "static.csv", "--out", "allan.json"], None),
    ("noise", ["noise", "static.csv", "--json"], 1.5),
    ("effects", ["effects"], 0.5),
    ("bad input", ["fit", "missing.csv", "--model", "bias_poly(1)"], 0.5),
    ("bad column", ["fit", "nocol.csv", "--model", "bias_poly(1)"], 0.5),
]
#: The commands whose files a command reads (run once, untimed, under ``--only``).
SETUP = {"compensate": ["simulate thermal", "fit"], "export px4": ["simulate thermal", "fit cubic"],
         "export ardupilot": ["simulate thermal", "fit cubic"],
         "export c-header": ["simulate thermal", "fit cubic"], "fit": ["simulate thermal"],
         "fit cubic": ["simulate thermal"], "diagnose": ["simulate thermal"],
         "allan": ["simulate static"], "noise": ["simulate static"]}
#: A CSV without the column gz: the reader's one-line error.
NO_COLUMN = "device,t,gx,gy,temp\nimu0,0,0.1,0.2,25\nimu0,0.5,0.1,0.2,25\n"


def _run(args: list[str], cwd: Path, env: dict) -> tuple[float, int, float]:
    """(wall s, exit code, the child's CPU s: user + system, all its threads)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "diffgyro", *args], cwd=cwd, env=env,
                          capture_output=True, text=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, done.returncode, cpu


def _walkthrough(only: list[str], src: str | None = None
                 ) -> list[tuple[float, float, int, float, float]]:
    """(cold s, warm s, exit code, cold CPU s, warm CPU s) of every command in ``only``, in
    a fresh folder and cache (the commands whose files they read run first, once); ``src``:
    the source tree the commands run (put first on PYTHONPATH), default the installed one."""
    work = Path(tempfile.mkdtemp())
    (work / "nocol.csv").write_text(NO_COLUMN)
    env = {**os.environ, "DIFFGYRO_CACHE_DIR": str(work / "cache")}
    if src is not None:
        env["PYTHONPATH"] = os.pathsep.join([src, *filter(None, [env.get("PYTHONPATH")])])
    setup = {s for name in only for s in SETUP.get(name, [])} - set(only)
    out = []
    for name, cmd, _ in COMMANDS:
        if name in setup:
            _run(cmd, work, env)
        if name not in only:
            continue
        cold, code, cold_cpu = _run(cmd, work, env)
        warm, _, warm_cpu = _run(cmd, work, env)
        out.append((cold, warm, code, cold_cpu, warm_cpu))
    shutil.rmtree(work, ignore_errors=True)
    return out


def _compile_bytecode(src: str | None) -> None:
    """The bytecode of the package a tree runs (``src``, or the installed one), as an
    installation has it."""
    if src is not None:
        pkg = Path(src) / "diffgyro"
    else:
        pkg = Path(importlib.util.find_spec("diffgyro").submodule_search_locations[0])
    compileall.compile_dir(str(pkg), quiet=1)


def _rows(only: list[str], runs: list) -> list[dict]:
    """Each command's medians over ``runs`` (walkthroughs), its goal and whether it is met."""
    rows = []
    for k, (name, _, goal) in enumerate(c for c in COMMANDS if c[0] in only):
        cold = statistics.median(r[k][0] for r in runs)
        warm = statistics.median(r[k][1] for r in runs)
        cold_cpu = statistics.median(r[k][3] for r in runs)
        warm_cpu = statistics.median(r[k][4] for r in runs)
        met = None if goal is None else (warm <= goal and cold <= 2 * max(warm, 1e-9))
        rows.append({"command": name, "cold_s": round(cold, 3), "warm_s": round(warm, 3),
                     "goal_warm_s": goal, "exit": runs[0][k][2], "met": met,
                     "cold_cpu_s": round(cold_cpu, 3), "warm_cpu_s": round(warm_cpu, 3),
                     "cold_over_warm": round(cold / max(warm, 1e-9), 3),
                     "runs": [[round(r[k][0], 3), round(r[k][1], 3)] for r in runs],
                     "runs_cpu": [[round(r[k][3], 3), round(r[k][4], 3)] for r in runs]})
    return rows


def _print(rows: list[dict], tree: str | None = None) -> None:
    first = "| tree " if tree is not None else ""
    print(f"{first}| command | cold s | warm s | goal (warm; cold ≤ 2× warm) | met "
          "| cold / warm | cold CPU s | warm CPU s |")
    print("|---" * (8 + (tree is not None)) + "|")
    for r in rows:
        goal = "—" if r["goal_warm_s"] is None else f"≤ {r['goal_warm_s']} s"
        met = "—" if r["met"] is None else ("yes" if r["met"] else "no")
        lead = f"| {tree} " if tree is not None else ""
        print(f"{lead}| {r['command']} | {r['cold_s']:.2f} | {r['warm_s']:.2f} | {goal} | {met} "
              f"| {r['cold_over_warm']:.2f} | {r['cold_cpu_s']:.2f} | {r['warm_cpu_s']:.2f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json")
    ap.add_argument("--repeat", type=int, default=1, help="walkthroughs; medians reported")
    ap.add_argument("--only", help="comma-separated command names (default: all), e.g. "
                    "'compensate,export px4,effects,bad input,bad column'")
    ap.add_argument("--trees", help="NAME=SRC,...: source trees run in turn, each walkthrough "
                    "of each repeat in a fresh cache (e.g. 'main=../main/src,branch=src')")
    args = ap.parse_args()
    only = [c[0] for c in COMMANDS] if not args.only else [n.strip() for n in args.only.split(",")]
    unknown = set(only) - {c[0] for c in COMMANDS}
    if unknown:
        ap.error(f"unknown command(s) {sorted(unknown)}; one of {[c[0] for c in COMMANDS]}")
    # (absolute: the commands run in a fresh folder, where a relative tree is not found and
    # the installed package would run instead)
    trees = ({name: str(Path(src).resolve()) for name, src in
              (t.split("=", 1) for t in args.trees.split(","))} if args.trees else {None: None})
    runs: dict = {name: [] for name in trees}
    loads = []
    for src in trees.values():
        _compile_bytecode(src)
    for _ in range(max(args.repeat, 1)):
        for name, src in trees.items():  # in turn: a change of load touches every tree alike
            loads.append(round(os.getloadavg()[0], 2))
            runs[name].append(_walkthrough(only, src))
    rows = {name: _rows(only, r) for name, r in runs.items()}
    for name, r in rows.items():
        _print(r, name)
    out = {"machine": cpu_name(), "cores": os.cpu_count(),
           "repeat": max(args.repeat, 1), "load_1min": loads}
    if args.trees:
        out["trees"] = {name: {"src": src, "rows": rows[name]} for name, src in trees.items()}
    else:
        out["rows"] = rows[None]
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
