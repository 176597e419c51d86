"""benchmarks/run.py's cases run at toy sizes and report comparable answers (not a benchmark)."""

from __future__ import annotations

import importlib.util

import pytest
from conftest import ROOT

KEYS = {"case", "devices", "samples", "diffgyro_s", "baseline", "baseline_s", "speedup",
        "max_abs_diff", "bytes", "fraction_of_bandwidth_limit", "compile_s"}


def _script(name: str, file: str):
    """benchmarks/``file`` loaded as the module ``name``."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "benchmarks" / file)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture(scope="module")
def bench():
    return _script("bench_run", "run.py")


@pytest.mark.parametrize("case,args", [
    ("bias_poly3", dict(devices=6, samples=700, subset=3, full_fit=False)),
    ("kalman", dict(devices=2, samples=400, subset=150)),
    ("allan", dict(devices=1, samples=4096, subset=2)),
    ("load", dict(devices=2, samples=500, subset=0)),
])
def test_case_runs_and_agrees(bench, case, args):
    rows = bench.CASES[case](repeats=1, bw=1e10, **args)
    assert rows
    for r in rows:
        assert KEYS <= set(r)
        assert r["diffgyro_s"] > 0 and r["baseline_s"] > 0 and r["speedup"] > 0
        assert r["max_rel_diff"] < 1e-8, (case, r["baseline"], r["max_rel_diff"])
        assert 0 < r["fraction_of_bandwidth_limit"]
    assert "| " + case in bench.table(rows)


def test_compile_case_runs_in_fresh_processes(bench):
    """The compile case: cold, cached and after-another-spec first calls of fit() in
    child processes."""
    (r,) = bench.case_compile(4, 400, 0, 1, 1e10, specs=("bias_poly(1)",))
    assert KEYS <= set(r) and r["case"] == "compile:bias_poly(1)"
    assert r["compile_s"] > 0 and r["compile_cached_s"] >= 0 and r["diffgyro_s"] > 0
    assert r["compile_after_other_spec_s"] >= 0 and len(r["compile_s_all"]) == 1
    assert "compile:bias_poly(1)" in bench.table([r])


def test_stream_fits_every_chunk_and_agrees_with_lstsq(tmp_path):
    """benchmarks/stream.py at a toy size: every device of every chunk fitted, the first
    chunk's coefficients equal to numpy's lstsq, the limits and fractions reported."""
    import json

    mod = _script("bench_stream", "stream.py")
    out = tmp_path / "stream.json"
    assert mod.main(["--devices", "12", "--samples", "2000", "--chunk", "8", "--no-defaults",
                     "--limit-gb", "0.05", "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["machine"]["bytes"] == 12 * 2000 * (3 * 8 + 8 + 1)
    (row,) = got["rows"]
    assert row["ok"] == 12 and row["max_rel_diff_vs_lstsq"] < 1e-9
    assert row["s"] > 0 and row["fraction_of_binding"] > 0


def test_timing_medians_interleave_and_take_the_median(monkeypatch):
    """benchmarks/_timing.py: the candidate's first call is timed apart, then candidate and
    baselines run in turn each round, and each reports the median of its own rounds."""
    mod = _script("bench_timing", "_timing.py")
    clock = iter(range(1000))
    monkeypatch.setattr(mod.time, "perf_counter", lambda: next(clock) ** 2)
    order = []
    first, dg, base, (out_c, out_b) = mod.measure(
        lambda: order.append("c") or "C", {"b": lambda: order.append("b") or "B"}, 3)
    assert order == ["c", "b"] + ["c", "b"] * 3
    assert (out_c, out_b) == ("C", {"b": "B"})
    # the clock reads t² at its t-th read: the first call (0, 1), then c (2, 3), b (4, 5),
    # c (6, 7), b (8, 9), c (10, 11), b (12, 13): c took 5, 13, 21 and b 9, 17, 25
    assert first == 1
    assert dg == 13 and base == {"b": 17}
    assert mod.median_time(lambda: None, 1) == 15 ** 2 - 14 ** 2


def test_suite_profile_counts_a_programs_stages_for_the_running_test():
    """benchmarks/suite_profile.py's plugin: a program built while a test runs is counted for
    that test (trace, lowering, compilation, one program), and its rows add up per file."""
    import jax
    import jax.monitoring
    import jax.numpy as jnp
    import numpy as np

    prof = _script("suite_profile", "suite_profile.py")
    prof.pytest_runtest_logstart("tests/test_x.py::test_a", None)
    jax.monitoring.register_event_duration_secs_listener(prof._listener)
    try:
        # (an offset of this run's own: a new program, not one the compilation cache holds)
        offset = float(np.random.default_rng().uniform(1.0, 2.0))
        jax.jit(lambda x: jnp.sin(x) * 3.0 + offset)(np.arange(7.0)).block_until_ready()
    finally:
        jax.monitoring.unregister_event_duration_listener(prof._listener)
    prof.pytest_runtest_logfinish("tests/test_x.py::test_a", None)
    row = prof._times["tests/test_x.py::test_a"]
    assert row["programs"] == 1 and row["wall"] > 0
    assert all(row[stage] > 0 for stage in ("trace", "lower", "compile"))
    rows = {"tests/test_x.py::test_a": dict(row),
            "tests/test_x.py::test_b": {"wall": 2.0, "compile": 1.0, "programs": 2},
            "tests/test_y.py::test_c": {"wall": 1.0}}
    files = prof.by_file(rows)
    assert files["tests/test_x.py"]["programs"] == 3
    assert files["tests/test_x.py"]["wall"] == pytest.approx(row["wall"] + 2.0)
    total = prof.summary(files, wall=5.0, workers=2)
    assert total["programs"] == 3 and total["worker_s"] == pytest.approx(row["wall"] + 3.0)
    build = row["trace"] + row["lower"] + row["compile"] + 1.0
    assert total["build_share"] == pytest.approx(build / (row["wall"] + 3.0))
    assert prof.table(files, 1).count("\n") == 2 and "tests/test_x.py" in prof.table(files, 1)
