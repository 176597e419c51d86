"""random_walk: bias random walk (rate random walk), the model's noise component.

It adds no regressor columns: the deterministic terms of a model are fitted by
regression, while the walk is a state ``b_k = b_{k−1} + w_k``,
``w_k ~ N(0, q·Δt)``, estimated by the Kalman filter and RTS smoother of
:mod:`diffgyro.kalman`, with ``q`` ((rad/s)²/s; √q is the rate random walk in
rad/s²/√Hz) and the white measurement variance learned by maximum likelihood.
"""

from __future__ import annotations

from ._base import AbstractNoise, register


@register
class RandomWalk(AbstractNoise):
    """``b_i(t)``: a per-axis random walk starting at 0 at the first sample; variance learned."""

    name = "random_walk"
    follows = "time"
    evidence_phrase = "wanders in time with no physical signal explaining it"
    description = "stochastic bias random walk, Kalman-smoothed, variance by maximum likelihood"
    unit = "(rad/s)²/s"
