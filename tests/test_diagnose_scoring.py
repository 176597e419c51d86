"""The time-constant search on segment means picks what the search on samples picks.

``diffgyro.diagnose._scoring`` searches a lag or warm-up time constant on segment
means once a record is longer than ``SEARCH_POINTS`` samples, then scores the
picks on the samples. The test catalogue's records are shorter, so here the
limit is lowered until each segment holds about 20 samples (10 s at 2 Hz), twice as
coarse as the segments of a 200 Hz × 1 h log relative to its shortest lag.
"""

from __future__ import annotations

import hidden_effects as H
import numpy as np
import pytest

from diffgyro.data import Batch
from diffgyro.diagnose import _scoring as scoring
from diffgyro.diagnose import diagnose


@pytest.mark.parametrize("effect", ["thermal_lag", "warmup"])
def test_segment_search_matches_the_sample_search(monkeypatch, effect):
    """Same verdict and term; the chosen τ within 10 % and every candidate's held-out RMS
    within 1 % of the sample-level search's (the numbers come from the samples at the
    picks, so only a different pick could move them)."""
    hs = [H.make_recording("thermal", effect, "bias_poly(2)", 40 + k, size=1.5,
                           noise=H.Noise(white=2e-4, flicker=0.1, drift=0.1), device=f"d{k}")
          for k in range(2)]
    batch = Batch.from_recordings([h.recording for h in hs])
    kw = dict(candidates=["thermal_lag", "warmup"], dtemp_window=60.0, greedy=False)
    on_samples = diagnose("bias_poly(2)", batch, **kw)
    n_blocks = on_samples.options["n_blocks"]
    length = int(batch.t.shape[1])
    assert scoring.segment_length(length, n_blocks) == 1  # the catalogue searches on samples
    monkeypatch.setattr(scoring, "SEARCH_POINTS", n_blocks * (length // n_blocks // 20))
    assert 19 <= scoring.segment_length(length, n_blocks) <= 21
    on_segments = diagnose("bias_poly(2)", batch, **kw)
    for a, b in zip(on_samples.devices, on_segments.devices):
        assert (a.verdict, a.best.effect) == (b.verdict, b.best.effect) == ("missing_effect", effect)
        for ca in a.candidates:
            cb = next(c for c in b.candidates if c.effect == ca.effect)
            assert cb.heldout_rms == pytest.approx(ca.heldout_rms, rel=1e-2), ca.effect
        tau_a = next(c.tau for c in a.candidates if c.effect == effect)
        tau_b = next(c.tau for c in b.candidates if c.effect == effect)
        assert np.isclose(tau_b, tau_a, rtol=0.1), (tau_a, tau_b)
