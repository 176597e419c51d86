"""Timing shared by the benchmark scripts: call a function N times, report the median;
and the name of the CPU the times were taken on.

The median, not the mean, because the benchmarks run on shared machines where a
single slow call (another process taking the core) is common; calls compared with
each other are timed in turn within each round, so that a change of load falls on all
of them alike.
"""

from __future__ import annotations

import platform
import statistics
import time
from collections.abc import Callable
from typing import Any


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what :mod:`platform` knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def timed(f: Callable[[], Any]) -> tuple[float, Any]:
    """(seconds, result) of one call of ``f``."""
    t0 = time.perf_counter()
    out = f()
    return time.perf_counter() - t0, out


def medians(calls: list[Callable[[], Any]], repeats: int) -> list[float]:
    """The median time of each call over ``repeats`` rounds, the calls in turn in each round."""
    times: list[list[float]] = [[] for _ in calls]
    for _ in range(repeats):
        for f, ts in zip(calls, times):
            ts.append(timed(f)[0])
    return [statistics.median(ts) for ts in times]


def median_time(f: Callable[[], Any], repeats: int) -> float:
    """Median seconds of ``repeats`` calls of ``f`` after one warm-up call."""
    f()
    return medians([f], repeats)[0]


def measure(candidate: Callable[[], Any], baselines: dict[str, Callable[[], Any]],
            repeats: int) -> tuple[float, float, dict[str, float], tuple[Any, dict[str, Any]]]:
    """The candidate's first call timed (its compilation), then every baseline's warm-up, then
    the candidate and each baseline in turn, ``repeats`` times.

    Returns (first-call time, median candidate time, {name: median baseline time},
    (candidate output, {name: baseline output})).
    """
    first, out_c = timed(candidate)
    out_b = {k: f() for k, f in baselines.items()}
    names = list(baselines)
    med = medians([candidate, *(baselines[k] for k in names)], repeats)
    return first, med[0], dict(zip(names, med[1:])), (out_c, out_b)
