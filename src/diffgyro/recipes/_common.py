"""Pieces every recipe shares: the result base class, signals from plain arrays,
least squares on a toolkit model's design, and JSON conversion."""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._jsonio import to_json_safe
from ..data import Batch, Recording
from ..errors import DataError
from ..fit import fit
from ..model import ErrorModel
from ..signals import Signals, make_signals


@dataclasses.dataclass(frozen=True)
class RecipeResult:
    """Base of every recipe's result: plain numpy fields, JSON via :meth:`to_dict`."""

    name: ClassVar[str] = "recipe"

    def to_dict(self) -> dict:
        """All fields as JSON-ready values (arrays become lists, NaN becomes null)."""
        return {f.name: jsonable(getattr(self, f.name)) for f in dataclasses.fields(self)}


def jsonable(x):
    """numpy / JAX values -> plain Python (lists, floats, None for non-finite).

    **Arguments:**

    - ``x``: a value, or a dict, list or tuple of them.
    """
    return to_json_safe(x)


#: :func:`~diffgyro.signals.make_signals` compiled as one program per length: run op by op
#: it compiled each of its few dozen operations apart, again for every new length (a
#: recipe's bins, its poses, its static stretches).
_make_signals = eqx.filter_jit(make_signals)


def signals_for(
    gyro: np.ndarray,
    *,
    t: np.ndarray | None = None,
    rate: np.ndarray | None = None,
    temp: np.ndarray | None = None,
    temp_ext: np.ndarray | None = None,
    accel: np.ndarray | None = None,
    dtemp_window: float = 60.0,
) -> Signals:
    """Toolkit signals for plain arrays (every sample valid; ``t`` defaults to the index)."""
    gyro = jnp.asarray(gyro, jnp.float64)
    n = gyro.shape[0]
    t = jnp.arange(n, dtype=gyro.dtype) if t is None else jnp.asarray(t, gyro.dtype)

    def arr(x):
        return None if x is None else jnp.asarray(x, gyro.dtype)

    sig = _make_signals(t, gyro, jnp.ones(n, bool), rate=arr(rate), temp=arr(temp),
                        temp_ext=arr(temp_ext), accel=arr(accel), dtemp_window=dtemp_window)
    if sig.temp is None:
        return sig
    # the centred temperature as make_signals gives it run op by op: compiled with the
    # rest, its quotient can differ in the last bit, and the recipes' numbers with it
    return eqx.tree_at(lambda s: s.temp_s, sig, (sig.temp - sig.norm.centre) / sig.norm.scale)


@eqx.filter_jit
def _design(model: ErrorModel, sig: Signals, theta):
    """``model.design`` as one compiled program per model and length (as above)."""
    return model.design(sig, theta)


def least_squares_params(model: ErrorModel, sig: Signals, y: np.ndarray,
                         weights: np.ndarray | None = None) -> np.ndarray:
    """Per-axis least-squares coefficients ``beta (3, p)`` of a linear model's design.

    ``y`` is what the terms must explain (measured minus true rate). Columns are
    scaled to unit norm before the solve; a rank-deficient design raises.
    """
    if not model.is_linear:
        raise ValueError(f"{model.spec} has time constants; use diffgyro.fit.fit")
    x = np.asarray(_design(model, sig, jnp.zeros((0,))))  # (n, 3, p)
    y = np.asarray(y, float)
    w = np.ones(x.shape[0]) if weights is None else np.asarray(weights, float)
    sw = np.sqrt(w)
    beta = np.zeros((3, x.shape[2]))
    for i in range(3):
        a = x[:, i, :] * sw[:, None]
        scale = np.linalg.norm(a, axis=0)
        scale[scale == 0] = 1.0
        coef, _, rank, _ = np.linalg.lstsq(a / scale, y[:, i] * sw, rcond=None)
        if rank < a.shape[1]:
            raise DataError(f"the data cannot separate the terms of {model.spec!r} (axis {'xyz'[i]})",
                            hint="the recipe's positions or motions do not excite every term")
        beta[i] = coef / scale
    return beta


def toolkit_compensate(spec: str, fit_on: Recording, apply_to: Recording | None = None, **options):
    """Fit the toolkit model ``spec`` to ``fit_on`` and compensate ``apply_to``.

    The comparison every recipe offers: the same data, a richer model.
    Returns ``(fit_result, compensated_rate (n, 3), error (n, 3))`` where
    ``error`` is the model's whole error (bias, scale, ...) on ``apply_to``
    at its compensated rate (default: ``fit_on`` itself).

    **Arguments:**

    - ``spec``: the toolkit's model spec.
    - ``fit_on``: the :class:`~diffgyro.data.Recording` fitted.
    - ``apply_to``: the recording compensated (default: ``fit_on``).
    - ``**options``: further arguments of :func:`diffgyro.fit.fit`.
    """

    apply_to = fit_on if apply_to is None else apply_to
    out = fit(spec, fit_on, **options)
    batch = Batch.from_recordings([apply_to])
    comp = np.asarray(_compensate(out.model, out.params, out.signals(batch)))[0, : apply_to.n]
    return out, comp, np.asarray(apply_to.gyro) - comp


@eqx.filter_jit
def _compensate(model, params, sig):
    """Compensated rate of every device, compiled once per model and shape."""
    return jax.vmap(model.compensate)(params, sig)


def single_axis(rec: Recording, axis: int) -> Recording:
    """One gyro axis copied onto all three (the toolkit fits three axes; a single-axis
    rate table only excites one). Read the result from axis 0.

    **Arguments:**

    - ``rec``: the :class:`~diffgyro.data.Recording`.
    - ``axis``: the gyro axis copied (0, 1 or 2).
    """
    def rep(a):
        return None if a is None else np.repeat(np.asarray(a)[:, axis:axis + 1], 3, axis=1)

    return Recording(t=rec.t, gyro=rep(rec.gyro), temp=rec.temp, temp_ext=rec.temp_ext,
                     rate=rep(rec.rate), device=rec.device, source=rec.source)


def require(rec: Recording, *signals: str, recipe: str) -> None:
    """Raise a clear DataError when a recording lacks a signal a recipe reads."""
    cols = {"temp": "temp", "temp_ext": "temp_ext", "accel": "ax, ay, az", "mag": "mx, my, mz",
            "rate": "rx, ry, rz", "quat": "qw, qx, qy, qz"}
    for s in signals:
        if getattr(rec, s) is None:
            raise DataError(f"recipe {recipe} needs column(s) {cols.get(s, s)}, not in the data",
                            file=rec.source, device=rec.device, column=cols.get(s, s))
