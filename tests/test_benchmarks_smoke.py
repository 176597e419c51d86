"""benchmarks/run.py's cases run at toy sizes and report comparable answers (not a benchmark)."""

from __future__ import annotations

import importlib.util

import pytest
from conftest import ROOT

KEYS = {"case", "devices", "samples", "diffgyro_s", "baseline", "baseline_s", "speedup",
        "max_abs_diff", "bytes", "fraction_of_bandwidth_limit", "compile_s"}


@pytest.fixture(scope="module")
def bench():
    spec = importlib.util.spec_from_file_location("bench_run", ROOT / "benchmarks" / "run.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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

    spec = importlib.util.spec_from_file_location("bench_stream", ROOT / "benchmarks" / "stream.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "stream.json"
    assert mod.main(["--devices", "12", "--samples", "2000", "--chunk", "8", "--no-defaults",
                     "--limit-gb", "0.05", "--json", str(out)]) == 0
    got = json.loads(out.read_text())
    assert got["machine"]["bytes"] == 12 * 2000 * (3 * 8 + 8 + 1)
    (row,) = got["rows"]
    assert row["ok"] == 12 and row["max_rel_diff_vs_lstsq"] < 1e-9
    assert row["s"] > 0 and row["fraction_of_binding"] > 0
