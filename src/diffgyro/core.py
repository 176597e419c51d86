"""Definitions shared by every fit path: options, statuses and the status rule,
the fold partition, device padding, and the registry of noise-component fits.

The bottom of the fitting code: :mod:`diffgyro.fit` (direct path and the
front door), :mod:`diffgyro.fit_sums` (sums path) and :mod:`diffgyro.kalman`
(random walk) import from here and never from each other below ``fit``, so
their held-out numbers, statuses and options mean the same thing.
"""

from __future__ import annotations

import collections
import importlib
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .data import Batch, Recording
from .effects import AbstractNoise
from .errors import SpecError

STATUS_NAMES = ("ok", "not_converged", "rank_deficient", "insufficient_range",
                "insufficient_data", "failed", "in_motion")
OK, NOT_CONVERGED, RANK_DEFICIENT, INSUFFICIENT_RANGE, INSUFFICIENT_DATA, FAILED, IN_MOTION = range(7)
#: How often each compiled batch function was traced (tests check that a new batch
#: size within a bucket does not compile again).
TRACE_COUNTS: collections.Counter = collections.Counter()


class FitOptions(eqx.Module):
    """Solver settings. Integers are static; tolerances are arrays so changing them
    does not compile again."""

    n_blocks: int = eqx.field(static=True, default=100)
    n_folds: int = eqx.field(static=True, default=5)
    max_steps: int = eqx.field(static=True, default=100)
    chunk: int = eqx.field(static=True, default=64)
    rtol: Float[Array, ""] = eqx.field(default_factory=lambda: jax.device_put(np.asarray(1e-10)))
    atol: Float[Array, ""] = eqx.field(default_factory=lambda: jax.device_put(np.asarray(1e-14)))
    rank_tol: Float[Array, ""] = eqx.field(default_factory=lambda: jax.device_put(np.asarray(1e-10)))
    dtemp_window: float = eqx.field(static=True, default=60.0)
    #: "closed": closed form (linear part) + variable projection (time constants);
    #: "lm": one Levenberg–Marquardt solve over all parameters (the reference path).
    solver: str = eqx.field(static=True, default="closed")
    #: "sums" reads the samples once per trial of the time constants and never forms the
    #: design (the fit_sums package; Newton on the projected cost for time constants); "direct"
    #: forms it (optimistix LM for time constants); "auto": "sums" with the closed-form
    #: solver (linear models and time constants alike), "direct" with ``solver="lm"``.
    path: str = eqx.field(static=True, default="auto")
    #: The model-free noise floor per device and axis (on the host's threads beside
    #: the compiled fit, :mod:`diffgyro.noise`); False skips it (NaN) when only
    #: coefficients matter.
    noise_floor: bool = eqx.field(static=True, default=True)

    def replace(self, **kw) -> FitOptions:
        """These options with some fields changed (unknown names raise TypeError)."""
        fields = {f: getattr(self, f) for f in self.__dataclass_fields__}
        for k, v in kw.items():
            if k not in fields:
                raise TypeError(f"unknown fit option {k!r}; options: {', '.join(fields)}")
            fields[k] = jax.device_put(np.asarray(v)) if k in ("rtol", "atol", "rank_tol") else v
        return FitOptions(**fields)


def fit_status(n_valid, min_samples: int, converged, finite, range_flags=None, rank_ok=None):
    """Status code of a fit, the most basic problem first: too few samples, a term
    whose signal does not vary (``range_flags``), collinear columns (``rank_ok``
    false on an axis), no convergence, non-finite results."""
    status = jnp.where(finite, OK, FAILED)
    status = jnp.where(~converged, NOT_CONVERGED, status)
    if rank_ok is not None:
        status = jnp.where(~jnp.all(rank_ok), RANK_DEFICIENT, status)
    if range_flags is not None:
        status = jnp.where(jnp.any(range_flags), INSUFFICIENT_RANGE, status)
    return jnp.where(n_valid < min_samples, INSUFFICIENT_DATA, status)


def min_samples(n_unknowns: int) -> int:
    """Fewest valid samples for a least-squares fit of ``n_unknowns`` parameters per axis."""
    return max(2 * n_unknowns, n_unknowns + 4)


# --------------------------------------------------------------------------- data


def as_batch(data: Batch | Recording | list[Recording]) -> Batch:
    """A Batch of ``data`` (a Batch, one Recording or a list of them)."""
    if isinstance(data, Batch):
        return data
    if isinstance(data, Recording):
        return Batch.from_recordings([data])
    return Batch.from_recordings(list(data))


def sampling_intervals(batch: Batch) -> np.ndarray:
    """Median sampling interval of each device's valid samples (s)."""
    out = np.ones(batch.n_devices)
    for i in range(batch.n_devices):
        n = int(batch.n_valid[i])
        if n >= 2:
            out[i] = float(np.median(np.diff(np.asarray(batch.t[i, :n]))))
    return out


def fold_ids(mask: Bool[Array, " n"], n_blocks: int, n_folds: int) -> Int[Array, " n"]:
    """Fold of every valid sample: contiguous time blocks dealt round-robin to folds
    (-1 where not valid)."""
    k = jnp.cumsum(mask) - 1
    n_valid = jnp.maximum(jnp.sum(mask), 1)
    block = (k * n_blocks) // n_valid
    return jnp.where(mask, block % n_folds, -1)


def device_bucket(n: int) -> int:
    """Padded device count of a direct-path batch: powers of two up to 64 (at least 8),
    then multiples of 64, so that a few more or fewer devices reuse the compiled fit."""
    n = max(int(n), 1)
    if n <= 64:
        return max(8, 1 << (n - 1).bit_length())
    return -(-n // 64) * 64


def pad_devices(batch: Batch) -> Batch:
    """The batch with its last device repeated up to :func:`device_bucket` devices."""
    n = batch.n_devices
    m = device_bucket(n)
    if m == n:
        return batch
    return batch.select(np.minimum(np.arange(m), n - 1))


# --------------------------------------------------------------------------- noise fits

#: Fit functions of models with a noise component, by the component's class.
_NOISE_FITS: dict[type, Callable] = {}


def register_noise_fit(cls: type[AbstractNoise]) -> Callable[[Callable], Callable]:
    """Decorator: ``fn(model, batch, *, norm, options, **overrides)`` fits models whose
    noise component is a ``cls`` (:func:`diffgyro.kalman.fit_random_walk` registers
    ``RandomWalk``). :func:`diffgyro.fit.fit` dispatches through this table, so the
    direct and sums paths never import the state-space path."""
    def add(fn: Callable) -> Callable:
        _NOISE_FITS[cls] = fn
        return fn

    return add


def noise_fit(noise: AbstractNoise) -> Callable:
    """The fit registered for the class of ``noise`` (or the nearest base class)."""
    for cls in type(noise).__mro__:  # a class names the module that registers its fit
        if getattr(cls, "fit_module", None):
            importlib.import_module(cls.fit_module)
    for cls in type(noise).__mro__:
        if cls in _NOISE_FITS:
            return _NOISE_FITS[cls]
    raise SpecError(f"no fit is registered for the noise component {noise.spec!r}",
                    hint="register one with diffgyro.core.register_noise_fit")
