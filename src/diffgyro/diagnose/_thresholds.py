"""The decision's thresholds, the look-alike families and the search grids."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..effects import registry


@dataclass(frozen=True)
class Thresholds:
    """When a candidate counts as significant (see the module docstring).

    ``t_min``: paired t of the per-fold held-out MSE gains (``n_folds − 1``
    degrees of freedom); an effect confined to part of the record (a warm-up
    transient) improves one or two folds a lot and the others not at all, so
    it also passes when no fold gets worse by more than ``consistency`` × the
    mean gain. ``excess_min``: the base model's held-out MSE must
    exceed the floor's by this fraction of the floor's. ``closure_min``:
    share of that gap the candidate closes. ``gain_min``: its held-out MSE
    gain as a fraction of the floor's MSE. ``rw_slope_min``: long-τ Allan
    slope of the residual needed to name a random walk, ``rw_excess_min`` the
    excess it needs (low-level flicker and rate random walk are noise, not a
    missing effect). A significant deterministic term is preferred to the
    random walk when it closes at least ``rw_prefer`` of the gap, or leaves
    less than ``rw_ratio`` times the gap the random walk leaves; a term whose
    time constant ran to the slow end of its search (a warm-up with τ of a
    quarter of the record) fits a drift, not a physical transient, and does
    not count. The best physical term followed by the best second term
    (:mod:`.greedy`) is preferred to the walk when the pair closes at least
    ``rw_prefer`` of the gap (the verdict names the first term). ``alt_share``: a significant candidate is a close
    alternative when it closes at least this share of what the best closes.

    An effect confined to a small part of the record (a warm-up transient,
    the highest rates of a rate table) can be material where it happens yet
    small over the whole record. So a candidate is also material when, in the
    ``local_share`` of time blocks it improves most, the base model's held-out
    MSE is at least ``1 + local_excess`` times the floor's and the candidate
    closes ``local_closure`` of that local gap, with a whole-record gain of at
    least ``local_gain_min`` and at least ``local_closure_min`` of the
    whole-record gap closed (so a term that follows one flicker excursion does
    not pass); never for the random walk.

    A model whose held-out MSE is ``1 + unexplained_excess`` times the
    floor's or more is ``missing_effect`` even when no single term is
    significant (several effects missing at once, or one outside the
    vocabulary); it then names none.

    A random walk is not named when a signal no term is linear in (a product
    such as T·dT/dt, :data:`.evidence.OUTSIDE`) explains at least
    ``outside_share`` of the residual's variance above the floor: the
    verdict is then ``missing_effect`` with no term named (an effect outside
    the vocabulary), never the smoother.
    """

    t_min: float = 3.0
    consistency: float = 0.25
    excess_min: float = 0.15
    closure_min: float = 0.3
    gain_min: float = 0.03
    rw_slope_min: float = 0.25
    rw_excess_min: float = 0.2
    rw_prefer: float = 0.85
    rw_ratio: float = 2.0
    alt_share: float = 0.6
    local_share: float = 0.02
    local_excess: float = 2.0
    local_closure: float = 0.5
    local_gain_min: float = 0.005
    local_closure_min: float = 0.5
    unexplained_excess: float = 1.0
    outside_share: float = 0.5


#: Time-constant grid density for candidate terms with one nonlinear parameter.
GRID_POINTS = 24
#: Walk variance grid (q·dt / r) searched by the local-level smoother.
RW_GRID = tuple(10.0 ** np.linspace(-10.0, -1.0, 19))


def family_of(name: str) -> str | None:
    """The look-alike family of the registered effect ``name`` (its ``family``), or None.

    **Arguments:**

    - ``name``: a registered effect's name.
    """
    cls = registry().get(name)
    return None if cls is None else cls.family


def families() -> dict[str, tuple[str, ...]]:
    """Every look-alike family of the registered effects and its members' names."""
    out: dict[str, tuple[str, ...]] = {}
    for name, cls in registry().items():
        if cls.family is not None:
            out[cls.family] = (*out.get(cls.family, ()), name)
    return out
