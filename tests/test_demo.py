"""``diffgyro demo``: the loop on a simulated batch with a hidden effect, end to end.

The command runs once; its result is taken from ``run_demo`` on the way out."""

from __future__ import annotations

import time

import diffgyro._demo as demo
from diffgyro._demo import BASE, TRUTH
from diffgyro.cli import main


def test_demo_command_names_the_hidden_effect_and_reaches_the_floor(tmp_path, capsys,
                                                                    monkeypatch):
    results = []
    real = demo.run_demo

    def recorded(*args, **kwargs):
        results.append(real(*args, **kwargs))
        return results[-1]

    monkeypatch.setattr(demo, "run_demo", recorded)
    start = time.perf_counter()
    code = main(["demo", "--out", str(tmp_path / "demo")])
    elapsed = time.perf_counter() - start
    out = capsys.readouterr().out
    assert code == 0
    assert BASE in out and "gradient" in out and "model ladder" in out

    (result,) = results
    first, final = result.ladder.first, result.ladder.final
    assert result.added == ["gradient"] and result.ladder.spec == TRUTH
    assert all(d.verdict == "missing_effect" for d in first.devices)
    assert all(d.verdict == "adequate" for d in final.devices)
    for a, b in zip(first.devices, final.devices):
        assert b.heldout_rms < 0.8 * a.heldout_rms
        assert b.heldout_rms < 1.1 * b.noise_floor
    assert (tmp_path / "demo" / "index.html").exists()
    assert len(list((tmp_path / "demo").glob("*.html"))) == 1 + result.batch.n_devices
    assert elapsed < 300  # one minute on an idle 2-core machine; shared CI runners are slower
