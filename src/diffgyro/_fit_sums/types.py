"""The typed pytrees one device's program hands on: its sums and what its finish reads."""

from __future__ import annotations

import equinox as eqx
from jaxtyping import Array, Bool, Float, Int


class SplitSums(eqx.Module):
    """Sums of a model with time constants, kept apart: ``fixed`` products of columns that
    do not move with θ (computed once) and ``moving`` ones at the optimum θ
    (:func:`.normal_equations.unpack_split` joins them)."""

    fixed: Float[Array, "... f"]
    moving: Float[Array, "... m"]


class FoldSums(eqx.Module):
    """One device's sums over all its samples (``tot``), per held-out fold (``held``) and
    per training fold (``train`` = total − fold), at the time constants ``theta``."""

    tot: Float[Array, " s"] | SplitSums
    held: Float[Array, "k s"] | SplitSums
    train: Float[Array, "k s"] | SplitSums
    theta: Float[Array, " q"]
    steps: Int[Array, ""]
    converged: Bool[Array, ""]
    #: Products for the θ part of the covariance (:func:`.layout.covariance_pairs`); None
    #: for a linear model.
    covariance: Float[Array, " c"] | None = None


class DeviceSums(eqx.Module):
    """What :func:`.finish.finish` reads of one device: its :class:`FoldSums`, the offset
    ``y0`` taken out of the constant column, the terms' range flags and, with a
    temperature, its range and normalisation."""

    sums: FoldSums
    y0: Float[Array, " 3"]
    range_flags: Bool[Array, " terms"]
    temp_range: Float[Array, " 2"] | None = None
    norm_centre: Float[Array, ""] | None = None
    norm_scale: Float[Array, ""] | None = None
