"""Several missing effects, and one outside the vocabulary: neither is a random walk.

Data: thermal runs made apart from the project's simulator (``hidden_effects.py``)
whose base model ``bias_poly(2)`` lacks both the dT/dt gradient and the cubic
temperature term (each alone closes about half of the gap, and a random-walk
smoother follows the sum, so a one-term rule names the walk), or whose bias
follows T·dT/dt, which no built-in term is linear in.
"""

from __future__ import annotations

from unittest import mock

import hidden_effects as H
import pytest
from rich.console import Console

from diffgyro.cli.diagnose import print_diagnosis
from diffgyro.data import Batch
from diffgyro.diagnose import _run as run_module
from diffgyro.diagnose import diagnose, diagnose_auto

BASE = "bias_poly(2)"
TWO = "gradient+bias_poly"
NOISE = H.Noise(white=2e-4, flicker=0.1, drift=0.1)


def _thermal(effect: str, seed: int, size: float) -> H.Hidden:
    return H.make_recording("thermal", effect, BASE, seed, size=size, noise=NOISE, hours=2.0,
                            device=f"{effect}-{seed}")


@pytest.fixture(scope="module")
def two_effects():
    """The ladder of one device missing both effects, and every base fit its diagnoses ran
    (model spec, devices, the fit options they were given)."""
    hs = [_thermal(TWO, 500, 1.5)]
    batch = Batch.from_recordings([h.recording for h in hs])
    fits = []

    def recorded(model, data, **options):
        fits.append((model.spec, data.n_devices, options))
        return real(model, data, **options)

    real = run_module.fit_fn
    with mock.patch.object(run_module, "fit_fn", recorded):
        ladder = diagnose_auto(BASE, batch, max_steps=2)
    return hs, ladder, fits


def test_a_deterministic_term_first_and_the_next_one_named(two_effects):
    """The walk would close the gap, but so does the best term followed by the best second
    term: the verdict names the first, ``next`` (and the explanation) the second."""
    _, ladder, _ = two_effects
    for d, rec in zip(ladder.first.devices, ladder.first.records()):
        assert d.verdict == "missing_effect" and d.best is not None, d.explanation
        assert not d.best.stochastic and d.random_walk is not None and not d.random_walk.significant
        assert d.best.closure < 0.85 and d.random_walk.closure > 0.85  # one term alone: walk wins
        assert d.next is not None and d.next.closure >= 0.85
        assert {d.best.effect, d.next.effect} & {"gradient", "bias_poly"}
        assert f"expected to add `{d.next.term}`" in d.explanation
        assert rec["next"]["term"] == d.next.term and rec["best_term"] == d.best.term
    console = Console(record=True, width=240)
    print_diagnosis(ladder.first, console)  # the CLI table: "add" shows both
    assert f"{d.best.term}, then {d.next.term}" in console.export_text()


def test_two_rounds_of_auto_reach_the_noise(two_effects):
    hs, ladder, _ = two_effects
    added = [s.added for s in ladder.steps[1:]]
    assert len(added) == 2 and "random_walk" not in added, added
    for h, got, v in zip(hs, ladder.steps[-1].heldout_rms, ladder.steps[-1].verdicts):
        assert v == "adequate"
        assert abs(got / h.noise_rms - 1.0) <= 0.10, (got / h.noise_rms, added)


def test_the_pair_is_fitted_without_a_second_motion_check(two_effects):
    """The pair's nested diagnosis fits base + first term on the devices whose walk won
    without checking their recordings for motion again (the base fit's check judged them
    fit to judge); every rung of the ladder checks its own fit, as diagnose does."""
    _, ladder, fits = two_effects
    first = ladder.first.devices[0]
    nested = [(spec, n) for spec, n, o in fits if o.get("check_motion") is False]
    assert nested[0] == (first.best.spec, 1), fits
    rungs = [spec for spec, _, o in fits if "check_motion" not in o]
    assert rungs == [s.spec for s in ladder.steps], fits


def test_an_effect_outside_the_vocabulary_names_the_signal_not_a_term():
    """Bias ∝ T·dT/dt: no term closes a material part of the gap and the walk, which would,
    is not named; without synthesis the explanation names the product and points to
    ``@register``; with it (the default) a thermal product of the logged signals is
    proposed that reaches the floor."""
    h = _thermal("temp_x_dtemp", 700, 2.0)
    batch = Batch.from_recordings([h.recording])
    d = diagnose(BASE, batch, greedy=False, synthesis=False).devices[0]
    assert d.verdict == "missing_effect" and d.best is None, d.explanation
    assert not any(c.significant for c in d.candidates)
    assert d.random_walk is not None and d.random_walk.closure > 0.85
    assert d.evidence["temp_dtemp"]["explains"] >= 0.5
    assert "T·dT/dt" in d.explanation and "@register" in d.explanation, d.explanation
    assert d.record()["best"] is None and d.record()["next"] is None
    from diffgyro.internal import synthesise

    dg = diagnose(BASE, batch, greedy=False, synthesis=False)
    synthesise(dg.devices, batch, dg.fit, dg.model, dg.raw["candidates"], dg.raw["ok"],
               dg.thresholds)
    s = dg.devices[0]
    assert s.best is not None and s.best.effect == "term" and not s.random_walk.significant
    assert "temp" in s.best.term and s.best.heldout_rms <= 1.1 * h.noise_rms, s.explanation


def test_a_function_of_a_logged_column_names_the_column():
    """Bias ∝ sin(5π·duty) of a logged duty column: ``aux(duty)`` (a line) closes nothing and
    a smoother cannot follow 20 s levels; the explanation names `duty`, followed not along a
    line (η), and suggests a higher order or a registered term."""
    h = _thermal("sin_duty", 710, 2.0)
    d = diagnose(BASE, Batch.from_recordings([h.recording]), greedy=False).devices[0]
    assert d.verdict == "missing_effect" and d.best is None, d.explanation
    assert "bias_poly(2)+aux(duty)" in [c.spec for c in d.candidates]
    ev = d.evidence["aux:duty"]
    assert ev["eta"] > 0.8 and abs(ev["r"]) < 0.3, ev
    assert "follows `duty` most, not along a line" in d.explanation, d.explanation
    assert "aux(duty,k)" in d.explanation and "@register" in d.explanation
