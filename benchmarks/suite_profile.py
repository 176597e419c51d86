"""Where the test suite's time goes: each test file's time, and how much of it JAX spends
building programs (tracing, lowering to StableHLO, XLA's compilation) rather than running
them.

The suite runs as the README says (``pytest -n 2``, a fresh compilation cache) with this
file loaded as a plugin in every worker. Each worker records its tests' times and, from
``jax.monitoring``'s duration events, every program it traces, lowers and compiles, keyed by
the test that was running; the parent adds them up per test file. Subprocesses a test starts
(the command line, a notebook's kernel) are counted in the test's time only.

    python benchmarks/suite_profile.py --json benchmarks/results/suite-profile-cpu2.json
    python benchmarks/suite_profile.py --top 40 -- tests/test_fit.py   # part of the suite
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))  # the shared helpers, also when loaded by path
from _timing import cpu_name  # noqa: E402

#: ``jax.monitoring`` duration events, by the name of the stage they time.
STAGES = {"/jax/core/compile/jaxpr_trace_duration": "trace",
          "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower",
          "/jax/core/compile/backend_compile_duration": "compile"}
_OUT = "DIFFGYRO_SUITE_PROFILE_DIR"

# ---- the plugin (loaded in every pytest process by ``-p suite_profile``) ----

_current = ["(collection)"]
_times: dict = collections.defaultdict(lambda: collections.defaultdict(float))
_started: dict[str, float] = {}


def _listener(event: str, duration: float, **_) -> None:
    stage = STAGES.get(event)
    if stage is not None:
        row = _times[_current[0]]
        row[stage] += duration
        row["programs"] += stage == "compile"


def pytest_configure(config) -> None:
    if os.environ.get(_OUT):
        import jax.monitoring

        jax.monitoring.register_event_duration_secs_listener(_listener)


def pytest_runtest_logstart(nodeid, location) -> None:
    _current[0] = nodeid
    _started[nodeid] = time.perf_counter()


def pytest_runtest_logfinish(nodeid, location) -> None:
    _times[nodeid]["wall"] += time.perf_counter() - _started.pop(nodeid, time.perf_counter())


def pytest_sessionfinish(session) -> None:
    folder = os.environ.get(_OUT)
    if folder:
        worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
        Path(folder, f"{worker}.json").write_text(json.dumps(_times))


# ---- the run and its table ----

def by_file(rows: dict[str, dict[str, float]]) -> dict[str, dict[str, float]]:
    """Per-test rows summed per test file (the part of a node id before ``::``)."""
    out: dict = collections.defaultdict(lambda: collections.defaultdict(float))
    for nodeid, row in rows.items():
        for k, v in row.items():
            out[nodeid.split("::")[0]][k] += v
    return {f: dict(r) for f, r in out.items()}


def summary(files: dict[str, dict[str, float]], wall: float, workers: int) -> dict:
    """Totals over the files: worker time, the share spent building programs, the suite's
    wall time."""
    total = {k: sum(r.get(k, 0.0) for r in files.values())
             for k in ("wall", "trace", "lower", "compile", "programs")}
    build = total["trace"] + total["lower"] + total["compile"]
    return {"suite_wall_s": wall, "workers": workers, "worker_s": total["wall"],
            "trace_s": total["trace"], "lower_s": total["lower"], "compile_s": total["compile"],
            "programs": int(total["programs"]),
            "build_share": build / total["wall"] if total["wall"] else float("nan")}


def table(files: dict[str, dict[str, float]], top: int) -> str:
    """Markdown table of the ``top`` test files by their time."""
    lines = ["| test file | s | trace s | lower s | compile s | programs | building % |",
             "|---|---|---|---|---|---|---|"]
    for name, r in sorted(files.items(), key=lambda kv: -kv[1].get("wall", 0.0))[:top]:
        build = r.get("trace", 0.0) + r.get("lower", 0.0) + r.get("compile", 0.0)
        share = 100.0 * build / r["wall"] if r.get("wall") else 0.0
        lines.append(f"| {name} | {r.get('wall', 0.0):.1f} | {r.get('trace', 0.0):.1f} | "
                     f"{r.get('lower', 0.0):.1f} | {r.get('compile', 0.0):.1f} | "
                     f"{int(r.get('programs', 0))} | {share:.0f} |")
    return "\n".join(lines)


def run(pytest_args: list[str], workers: int) -> tuple[dict, float]:
    """The suite (or ``pytest_args``) under the plugin, with a fresh compilation cache:
    (per-test rows of every worker, wall seconds)."""
    with tempfile.TemporaryDirectory() as out, tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, **{_OUT: out, "DIFFGYRO_CACHE_DIR": cache},
                   PYTHONPATH=os.pathsep.join(filter(None, [str(ROOT / "benchmarks"),
                                                            os.environ.get("PYTHONPATH")])))
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "suite_profile", "-p",
               "no:cacheprovider"] + (["-n", str(workers)] if workers else []) + pytest_args
        start = time.perf_counter()
        proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            raise SystemExit(f"pytest failed ({proc.returncode}):\n{proc.stdout[-3000:]}")
        rows: dict = {}
        for path in Path(out).glob("*.json"):
            if workers and path.stem == "main":  # (xdist's controller: it relays the workers'
                continue                         # tests and runs none, its rows hold no stage)
            rows.update(json.loads(path.read_text()))
    return rows, wall


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2, help="pytest-xdist workers (0: none)")
    ap.add_argument("--top", type=int, default=25, help="test files in the table")
    ap.add_argument("--json", help="write the totals and every file's row here")
    ap.add_argument("pytest_args", nargs="*", help="after --: what pytest runs (default: all)")
    args = ap.parse_args(argv)
    rows, wall = run(args.pytest_args, args.workers)
    files = by_file(rows)
    total = summary(files, wall, args.workers)
    print(f"suite {total['suite_wall_s']:.0f} s on {args.workers or 1} worker(s); worker time "
          f"{total['worker_s']:.0f} s, of which building programs {100 * total['build_share']:.0f} % "
          f"(trace {total['trace_s']:.0f} s, lower {total['lower_s']:.0f} s, compile "
          f"{total['compile_s']:.0f} s; {total['programs']} programs)")
    print(table(files, args.top))
    if args.json:
        out = {"benchmark": "suite_profile", "machine": cpu_name(),
               "cores": os.cpu_count(), "pytest_args": args.pytest_args, **total, "files": files}
        Path(args.json).write_text(json.dumps(out, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
