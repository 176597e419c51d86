"""``diffgyro demo``: the loop on a simulated batch with a hidden effect, end to end.

The command runs once, as a user runs it: its own process, stderr on a pseudo-terminal
(so its progress display is checked on the same run, :func:`test_cli_progress._on_terminal`).
A few lines wrapped around the command line take ``run_demo``'s result on the way out and
write what the checks need as JSON."""

from __future__ import annotations

import json

import pytest
from test_cli_progress import _on_terminal

from diffgyro._demo import BASE, TRUTH

CHILD = """
import json, sys, time
import diffgyro._demo as demo
real, summary = demo.run_demo, {}
def recorded(*args, **kwargs):
    r = real(*args, **kwargs)
    first, final = r.ladder.first, r.ladder.final
    summary.update(calls=summary.get("calls", 0) + 1, added=r.added, spec=r.ladder.spec, n_devices=int(r.batch.n_devices),
                   first=[[d.verdict, float(d.heldout_rms)] for d in first.devices],
                   final=[[d.verdict, float(d.heldout_rms), float(d.noise_floor)]
                          for d in final.devices])
    return r
demo.run_demo = recorded
from diffgyro.cli import main
start = time.perf_counter()
code = main(sys.argv[2:])
summary["elapsed"] = time.perf_counter() - start
with open(sys.argv[1], "w") as f:
    json.dump(summary, f)
sys.exit(code)
"""


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """``diffgyro demo --out demo`` once: (code, stdout, stderr as drawn, result, folder)."""
    folder = tmp_path_factory.mktemp("demo")
    result = folder / "result.json"
    code, out, err = _on_terminal([str(result), "demo", "--out", "demo"], folder,
                                  python=("-c", CHILD))
    assert code == 0, err
    return code, out, err, json.loads(result.read_text()), folder


def test_demo_command_names_the_hidden_effect_and_reaches_the_floor(demo_run):
    _, out, _, result, folder = demo_run
    assert BASE in out and "gradient" in out and "model ladder" in out
    assert result["calls"] == 1
    assert result["added"] == ["gradient"] and result["spec"] == TRUTH
    assert all(verdict == "missing_effect" for verdict, _ in result["first"])
    assert all(verdict == "adequate" for verdict, *_ in result["final"])
    assert len(result["first"]) == len(result["final"]) == result["n_devices"]
    for (_, before), (_, after, floor) in zip(result["first"], result["final"]):
        assert after < 0.8 * before
        assert after < 1.1 * floor
    assert (folder / "demo" / "index.html").exists()
    assert len(list((folder / "demo").glob("*.html"))) == 1 + result["n_devices"]
    # one minute on an idle 2-core machine; shared CI runners are slower
    assert result["elapsed"] < 300


def test_demo_shows_its_stages_on_a_terminal(demo_run):
    _, out, err, result, _ = demo_run
    assert f"simulating {result['n_devices']} gyros" in err and "\r" in err, err
    assert "added:" in out and "simulating" not in out  # the display is stderr's
