"""diagnose(model, batch): where a model fails, and which physical effect is missing.

For every device the base model is fitted (:func:`diffgyro.fit.fit`), and then,
for every registered effect whose signals the data has and the model lacks
(built-in or registered by the user), the model *with that term added* is
scored on held-out data. The comparison is built to stay honest when the
residual is correlated in time, where a plain F-test on 10⁵ samples calls
everything significant:

* **Held-out error on whole time blocks.** The samples are cut into the fit's
  interleaved time blocks and dealt to ``n_folds`` folds (the fit's own, so
  the base numbers are the fit's); every fold is predicted by the model fitted
  on the others. Base and candidate use the same folds, so their per-fold mean
  squared errors are *paired*. Every score comes from per-block sums
  (:mod:`.scoring`), so memory does not grow with the number of candidates.
* **A white-noise level that does not depend on any model**
  (:func:`white_noise_rms`): a windowed RMS of successive differences of
  ``gyro − rate`` (slow drift and the steps of a rate table drop out),
  checked against the short-τ Allan deviation of the residual. The decision
  measures held-out errors against it. The ``noise_floor`` reported beside it
  is :mod:`diffgyro._noise`'s, the one ``fit`` reports for the same device.
* **Significant means large and material** (:mod:`.decision`): a paired t
  over the folds, a base model materially above the floor, a real share of
  that gap closed and a material gain. These keep time-correlated noise
  (flicker, a small random walk) from being "explained" by any slowly
  varying term.
* **Time constants are chosen on training folds only.** Terms with a
  nonlinear parameter (``thermal_lag``, ``warmup``, user terms) are scored
  on a dense grid of time constants; each fold picks its own on the training
  blocks, so the held-out number pays for the search.
* **A random walk must not win by default** (:mod:`.random_walk`): a smoother
  can follow any slowly varying residual, so ``random_walk`` is scored
  separately and enters the ranking only when no deterministic term closes the
  gap (``rw_prefer``), nor the best one followed by the best second term
  (:mod:`.greedy`), *and* the residual's Allan deviation rises at long τ; a
  residual that follows a product no term is linear in (T·dT/dt) is an effect
  outside the vocabulary, not a walk.
* **Look-alikes are shown, not hidden** (gradient / thermal lag / inside–outside
  difference; scale asymmetry / nonlinearity; g-sensitivity / misalignment).

The package: :mod:`.thresholds` (the rule's numbers), :mod:`.floor` (white-noise
level, temperature read-out), :mod:`.candidates` (what is tried),
:mod:`.scoring` (held-out errors from block sums), :mod:`.random_walk`,
:mod:`.decision` (significance, ranking, verdict), :mod:`.greedy` (before a
random walk is named: the best term followed by the best second term),
:mod:`.evidence`
(correlations and the explanation), :mod:`.results` (the records),
:mod:`.run` (the batch, streamed per chunk of devices) and :mod:`.ladder`
(``--auto``). The thresholds were tuned on recordings made apart from the
project's simulator (``tests/hidden_effects.py``) and on the simulator's own
batches; ``tests/test_diagnose.py`` measures the rates they give.
"""

from __future__ import annotations

from ._candidates import CandidateSpec, candidate_specs
from ._decision import redecide
from ._evidence import evidence, explain
from ._floor import white_noise_rms
from ._ladder import Ladder, LadderStep, choose_effect, diagnose_auto
from ._results import AllanCurves, Candidate, DeviceDiagnosis, Diagnosis
from ._run import diagnose
from ._thresholds import GRID_POINTS, RW_GRID, Thresholds, families, family_of

__all__ = ["diagnose", "diagnose_auto", "Diagnosis", "DeviceDiagnosis", "Ladder", "LadderStep",
           "GRID_POINTS", "RW_GRID", "AllanCurves", "Candidate", "CandidateSpec", "Thresholds",
           "candidate_specs", "choose_effect", "evidence", "explain", "families", "family_of",
           "redecide", "white_noise_rms"]
