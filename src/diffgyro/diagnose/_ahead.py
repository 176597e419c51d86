"""What the scoring reads of the base fit besides its coefficients, known before the fit.

The candidates' ranges and the scoring program read the base fit's temperature
normalisation (each device centred on its own temperature range), the centring of the
extra columns the model reads (each on its own range) and three of its options (the
blocks, the folds, the dT/dt window). Each is a function of the batch and the options
alone, so :func:`predicted` forms them on the host before the fit runs. The diagnosis
then runs the ranges, knows its candidates, and has the scoring program traced and
compiled (or read from the caches) on a thread of its own while the fit runs: XLA
compiles without Python's lock, and the fit's own work is mostly Python tracing.

After the fit :func:`same` checks the prediction against what the fit holds
(:func:`of_fit`), bit for bit: where anything differs (a path that centres otherwise,
options the prediction did not know), the ranges and the candidates are formed again
from the fit, as they were before, and the program prepared ahead is left unused. So
the scores never depend on the prediction, only the time they take.
"""

from __future__ import annotations

import collections
import dataclasses
import warnings
from typing import NamedTuple

import numpy as np

from .. import _aux as aux_cols
from .._options import FitOptions
from ..data import Batch
from ..model import ErrorModel
from ..signals import TempNorm

#: How the programs prepared before the fit served (``"hit"``: the scoring's call ran the
#: program compiled ahead; ``"miss"``: its arguments' shapes differed from those foreseen;
#: ``"refit"``: the fit's setting differed from the prediction, so the ranges and the
#: candidates were formed again from the fit). Tests read it; nothing else does.
AHEAD: collections.Counter = collections.Counter()


class Setting(NamedTuple):
    """The base fit's part in the scoring's inputs: the model, each device's temperature
    norm (numpy (d,) centre and scale; None where the model reads no temperature), the norm
    of every extra column the model reads, and the blocks, folds and dT/dt window (s)."""

    model: ErrorModel
    norm: TempNorm | None
    aux_norm: dict[str, TempNorm]
    n_blocks: int
    n_folds: int
    dtemp_window: float


#: Every fit option, and the defaults of the three the setting reads (read from the class:
#: an instance puts its tolerances on the device).
_OPTIONS = frozenset(f.name for f in dataclasses.fields(FitOptions))
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(FitOptions)
             if f.name in ("n_blocks", "n_folds", "dtemp_window")}


def predicted(model: ErrorModel, batch: Batch, fit_options: dict) -> Setting | None:
    """The :class:`Setting` a fit of ``model`` on ``batch`` with ``fit_options`` will hold,
    formed as the fit forms it (the device's own temperature range: centre its middle,
    scale its half-width, at least 0.5 °C); None where the options hold more than
    :class:`~diffgyro.fit.FitOptions` fields and ``check_motion`` (a norm given,
    ``static_only``), which the prediction does not follow. Whether the recordings are
    checked for motion sets the fit's status, not its setting (a greedy pair's nested
    diagnosis fits without the check: :func:`._run._nested`)."""
    if not set(fit_options) - {"check_motion"} <= _OPTIONS:
        return None
    opts = {**_DEFAULTS, **{k: v for k, v in fit_options.items() if k in _DEFAULTS}}
    norm = None
    if "temp" in model.requires() and batch.temp is not None:
        mask = np.asarray(batch.mask, bool)
        temp = np.asarray(batch.temp, np.float64)
        with np.errstate(all="ignore"):
            lo = np.min(np.where(mask, temp, np.inf), axis=1)
            hi = np.max(np.where(mask, temp, -np.inf), axis=1)
            norm = TempNorm(centre=0.5 * (lo + hi), scale=np.maximum(0.5 * (hi - lo), 0.5))
    names = aux_cols.aux_names(model.requires())
    if not set(names) <= set(batch.aux):
        return None  # the fit raises its error for the missing column
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an empty column: the fit names it
        aux = aux_cols.norms(batch, names)
    return Setting(model, norm, aux, opts["n_blocks"], opts["n_folds"],
                   float(opts["dtemp_window"]))


def of_fit(res) -> Setting:
    """The :class:`Setting` a base fit ``res`` holds (its arrays on the host)."""
    norm = None
    if "temp" in res.model.requires():
        norm = TempNorm(centre=np.asarray(res.norm.centre), scale=np.asarray(res.norm.scale))
    aux = {k: TempNorm(centre=np.asarray(v.centre), scale=np.asarray(v.scale))
           for k, v in res.aux_norm.items()}
    opts = res.options
    return Setting(res.model, norm, aux, opts.n_blocks, opts.n_folds, float(opts.dtemp_window))


def _same_norm(a: TempNorm | None, b: TempNorm | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return all(np.asarray(x).dtype == np.asarray(y).dtype and np.shape(x) == np.shape(y)
               and np.asarray(x).tobytes() == np.asarray(y).tobytes()
               for x, y in ((a.centre, b.centre), (a.scale, b.scale)))


def same(a: Setting, b: Setting) -> bool:
    """Whether two settings give the scoring the same inputs, bit for bit."""
    return (a.model is b.model and (a.n_blocks, a.n_folds, a.dtemp_window)
            == (b.n_blocks, b.n_folds, b.dtemp_window) and _same_norm(a.norm, b.norm)
            and a.aux_norm.keys() == b.aux_norm.keys()
            and all(_same_norm(a.aux_norm[k], b.aux_norm[k]) for k in a.aux_norm))
