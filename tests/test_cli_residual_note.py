"""``fit`` says in one line when a device's held-out RMS stands several times above its
noise floor, and points to ``diagnose``; a model that holds every effect gets no such
line, and ``--json`` keeps stdout pure (the ratio is a field there)."""

from __future__ import annotations

import json
import re

import pytest

from diffgyro.cli import main

NOTE = re.compile(r"^(dev\d{3}): held-out RMS ([\d.]+)x its noise floor: .*diffgyro diagnose",
                  re.M)


@pytest.fixture(scope="module")
def walkthrough(tmp_path_factory):
    """The README walkthrough's batch: two gyros whose bias follows temperature and dT/dt."""
    from diffgyro.io import save
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 2, effects="bias_poly(2)+gradient", seed=0, duration=3600.0,
                        sample_rate=2.0)
    return save(batch, tmp_path_factory.mktemp("note") / "x.csv")


def test_fit_names_a_residual_above_the_floor_and_points_to_diagnose(walkthrough, capsys,
                                                                      monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["fit", str(walkthrough), "-m", "bias_poly(2)"]) == 0
    out = capsys.readouterr().out
    notes = NOTE.findall(out)
    assert len([line for line in out.splitlines() if "noise floor:" in line]) == len(notes)

    assert main(["fit", str(walkthrough), "-m", "bias_poly(2)", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)  # stdout is the JSON object alone
    above = [(d["device"], f"{d['residual_ratio']:.3g}") for d in doc["devices"]
             if d["residual_ratio"] > 3.0]
    # a line for each device above three times its floor (dev000, 4.7x), none for the other
    assert notes == above and [d for d, _ in notes] == ["dev000"], (notes, above)
    assert all(float(r) <= 10.0 for _, r in notes)  # several times: written, not refused

    assert main(["fit", str(walkthrough), "-m", "bias_poly(2)+gradient"]) == 0
    assert not NOTE.search(capsys.readouterr().out)  # the right model: nothing to say
