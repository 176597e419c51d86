"""Overlapping Allan deviation of gyro rates and the read-outs of its noise terms.

For a rate series ``y`` sampled every ``dt`` seconds, the overlapping Allan
deviation at ``τ = m·dt`` is (NIST SP 1065 eq. 11)::

    σ²(τ) = 1 / (2 τ² (N+1-2m)) · Σ_i (x[i+2m] - 2 x[i+m] + x[i])²

with the phase (angle) ``x = dt·[0, cumsum(y - mean y)]``: one pass of
cumulative sums, then O(N) per τ. The definition, the mean removal and the
counting are those of ``allantools.oadev(y, rate=1/dt, data_type="freq")``
(its ``taus`` are ``m·dt``), which the tests reproduce to 1e-10.

Everything is vmapped: a Batch's gyro (devices, samples, 3) gives one curve
per device and axis, padded samples excluded through ``n_valid``.

Its companions, for comparison with published tables and other tools, work
on the same phase in numpy, one vectorised pass per τ: the non-overlapping
deviation (:func:`adev_nonoverlapping`, SP 1065 eq. 7) and the modified one
(:func:`mdev`, SP 1065 eq. 14). A τ with fewer than one term is NaN.

Confidence intervals are chi-square intervals (SP 1065 eq. 45) with the
equivalent degrees of freedom of SP 1065 Table 5 ("simple" EDF) for the noise
type the curve shows at that τ: the local log-log slope picks white FM /
angle random walk (≤ −1/4; also used, conservatively, for quantisation),
flicker FM / bias instability (0) or random-walk FM / rate random walk (+1/2).

Read-outs (IEEE Std 952 conventions), units stated:

* ``arw`` N (rad/s/√Hz = rad/√s): σ at τ = 1 s on the −1/2 line ``N/√τ``;
* ``bias_instability`` B (rad/s): the flat floor ``0.664·B`` divided by
  √(2 ln 2 / π) ≈ 0.664;
* ``rrw`` K (rad/s²/√Hz = rad/s/√s): σ at τ = 3 s on the +1/2 line ``K·√(τ/3)``;
* ``quantization`` Q (rad): the −1 line ``√3·Q/τ``.

How the lines are placed (``method``):

* ``"fit"`` (default): the Allan *variance* is fitted with all four terms at
  once, ``σ² = 3Q²/τ² + N²/τ + 0.664²B² + K²τ/3``, by non-negative weighted
  least squares (weights EDF/σ⁴, the inverse variance of σ̂²). Each line is
  then free of the others' contamination: on simulated white + flicker
  noise the −1/2 line alone read ARW 6 % high, the fit reads it within 1 %.
  A term is reported only if it carries at least half the variance at some
  measured τ (it shows a region of its own slope) *and* dropping it worsens
  the weighted misfit by more than ``evidence`` (χ², default 25, chosen
  because neighbouring τ are strongly correlated); otherwise NaN.
* ``"lines"``: the graphical reading automated: each fixed-slope line is
  fitted alone (log-log, EDF-weighted) over the largest run of τ whose local
  slope is within ``tol`` of −1/2 or ``tol_rrw`` of +1/2, and the bias
  instability is the curve's minimum / 0.664 where the slope there is within
  ``tol_flat`` of 0.

A read-out the data do not support is NaN (``None`` in JSON): no number is
invented for a term the curve does not show. White noise plus a bias random
walk has a minimum where the two lines cross, but no flat floor: "fit"
reports no bias instability there ("lines" reports the crossing, as a
reading by eye would).
"""

from __future__ import annotations

from ._curves import (
    AllanResult,
    allan,
    allan_at_taus,
    allan_batch,
    cluster_sizes,
    sample_interval,
    sample_intervals,
)
from ._intervals import ONE_SIGMA, alpha_from_slope, chi2_ppf, edf_simple  # noqa: F401
from ._json import to_json
from ._nist import adev_nonoverlapping, mdev
from ._oadev import OADEV_OPTIONS, STOP_RATIO, default_m, oadev  # noqa: F401  (used by name)
from ._plot import plot_allan
from ._readouts import FLICKER_FACTOR, Readouts, log_slope, noise_terms

__all__ = ["allan", "allan_batch", "AllanResult", "Readouts", "noise_terms", "plot_allan",
           "to_json", "allan_at_taus", "oadev", "adev_nonoverlapping", "mdev", "log_slope",
           "default_m", "cluster_sizes", "sample_interval", "sample_intervals", "edf_simple",
           "chi2_ppf", "alpha_from_slope", "FLICKER_FACTOR"]
