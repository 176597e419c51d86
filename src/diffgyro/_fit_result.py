"""What every fit of a batch returns: :class:`AbstractFitResult`, the one base of the
deterministic fit's :class:`diffgyro.fit.FitResult` and the state-space path's
:class:`diffgyro.kalman.RandomWalkFit`.

The fields every fit has, and the methods that read only them (each device's status,
coefficients by label, its JSON record, the signals of a batch with the fit's centring),
are declared and documented here once; a subclass adds the fields of its own method (the
deterministic fit's covariance, the walk's noise levels and smoothed bias) and says how
it explains a batch (:meth:`AbstractFitResult.residuals`) and why a device is not ``ok``
(:meth:`AbstractFitResult.status_detail`). The calibration file, the motion judgement,
the limits and the command line read a fit through this base alone.
"""

import abc

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array, Float, Int

from . import _aux as aux_cols
from ._jsonio import number
from ._motion_result import Motion
from ._options import FitOptions
from ._signal_builder import signal_inputs, stacked_signals
from .data import Batch
from .model import ErrorModel, Params
from .signals import Signals, TempNorm
from .status import STATUS_NAMES

__all__ = ["AbstractFitResult"]


class AbstractFitResult(eqx.Module):
    """Per-device results of one fit of a batch: a leading device axis on every array.

    Every fit has the fields below; the methods read them alone.
    """

    #: Whether the residual keeps a turn the model cannot follow, so that the motion
    #: judgement may check it (:func:`diffgyro._motion_judge.judge_motion`): true of a
    #: deterministic model, false of a random walk, whose smoothed bias follows a turn.
    residual_tells_motion: eqx.AbstractClassVar[bool]

    #: The model fitted (its spec names it in every record).
    model: eqx.AbstractVar[ErrorModel]
    #: Device names, in the batch's order.
    devices: eqx.AbstractVar[tuple[str, ...]]
    #: Linear coefficients ``beta`` (d, 3, p) and time constants ``theta`` (d, q; log τ).
    params: eqx.AbstractVar[Params]
    #: Temperature centring of each device ((d,) centre and half-range).
    norm: eqx.AbstractVar[TempNorm]
    #: Calibrated temperature range of each device (d, 2); None without a temperature.
    temp_range: eqx.AbstractVar[Float[Array, "d 2"] | None]
    #: RMS residual over the samples fitted, rad/s.
    rms: eqx.AbstractVar[Float[Array, " d"]]
    #: RMS error on interleaved time blocks the fit did not see, rad/s.
    heldout_rms: eqx.AbstractVar[Float[Array, " d"]]
    #: Mean squared held-out error of each fold.
    fold_mse: eqx.AbstractVar[Float[Array, "d f"]]
    #: Model-free white-noise floor (RMS over the axes), rad/s.
    noise_floor: eqx.AbstractVar[Float[Array, " d"]]
    #: The same floor per axis.
    noise_axes: eqx.AbstractVar[Float[Array, "d 3"]]
    #: Solver steps taken.
    steps: eqx.AbstractVar[Int[Array, " d"]]
    #: Status code (:data:`diffgyro.status.STATUS_NAMES`).
    status: eqx.AbstractVar[Int[Array, " d"]]
    #: Valid samples fitted.
    n_samples: eqx.AbstractVar[Float[Array, " d"]]
    #: The options the fit ran with.
    options: eqx.AbstractVar[FitOptions]
    #: Centre and half-range of every extra column the model reads ((d,) arrays each).
    aux_norm: eqx.AbstractVar[dict[str, TempNorm]]
    #: Calibrated range of every extra column the model reads ((d, 2) each).
    aux_range: eqx.AbstractVar[dict[str, Float[Array, "d 2"]]]
    #: Whether each device was at rest (:mod:`diffgyro.motion`); None when not checked.
    motion: eqx.AbstractVar[Motion | None]
    #: Fitted from the detected static intervals only (``static_only=True``).
    static_only: eqx.AbstractVar[bool]
    #: Valid samples of each recording before the moving ones were left out.
    n_recorded: eqx.AbstractVar[Float[Array, " d"] | None]

    @property
    def n_devices(self) -> int:
        """Devices in the batch."""
        return len(self.devices)

    def status_name(self, i: int) -> str:
        """Device ``i``'s status by name (``ok``, ``in_motion``, ...)."""
        return STATUS_NAMES[int(np.asarray(self.status)[i])]  # (the host copy: see records)

    @abc.abstractmethod
    def status_detail(self, i: int) -> str:
        """Status and, when not ok, why in plain words (:func:`diffgyro.status.explain`)."""

    @abc.abstractmethod
    def residuals(self, batch: Batch) -> Float[Array, "d n 3"]:
        """What the fitted model leaves unexplained of every sample of ``batch`` (the same
        devices), padding zeroed."""

    def device_params(self, i: int) -> Params:
        """Device ``i``'s :class:`~diffgyro.model.Params`."""
        return jax.tree.map(lambda a: a[i], self.params)

    def param_dict(self, i: int) -> dict:
        """Device ``i``'s parameters by label: per axis ``term.coefficient`` (and a noise
        process' levels), the time constants in s under ``shared``."""
        pr = self.device_params(i)
        out: dict = {}
        labels = self.model.param_labels()
        for ax, name in enumerate("xyz"):
            out[name] = {lab: float(v) for lab, v in zip(labels[ax], np.asarray(pr.beta[ax]))}
            out[name] |= self._axis_noise(i, ax)
        if any(t.n_nonlinear for t in self.model.terms):
            out["shared"] = {}
            for (t, _, qs) in self.model.slices():
                if t.n_nonlinear:
                    vals = np.asarray(t.nonlinear_values(pr.theta[qs]))
                    for n, v in zip(t.nonlinear_names(), vals):
                        out["shared"][f"{t.spec}.{n}"] = float(v)
        return out

    def summary(self, i: int) -> dict:
        """One device as plain JSON-ready values (the ``fit --json`` record)."""
        return {
            "device": self.devices[i],
            "status": self.status_name(i),
            "status_detail": self.status_detail(i),
            "rms": number(self.rms[i]),
            "heldout_rms": number(self.heldout_rms[i]),
            "noise_floor": number(self.noise_floor[i]),
        } | self._likelihood(i) | {
            "steps": int(self.steps[i]),
            "n_samples": int(self.n_samples[i]),
            "params": self.param_dict(i),
            "motion": None if self.motion is None else self.motion.record(i),
        } | self._verdict(i) | (
            {"static_only": True, "n_recorded": int(self.n_recorded[i])} if self.static_only
            else {})

    def records(self) -> list[dict]:
        """Every device's :meth:`summary`, read from one host copy of the arrays (indexing a
        JAX array compiles a small program per shape: 14 of them in a two-device fit)."""
        host = self.on_host()
        return [host.summary(i) for i in range(self.n_devices)]

    def on_host(self):
        """The same result with numpy arrays (one transfer), for reading device by device."""
        return jax.device_get(self)

    def signals(self, batch: Batch) -> Signals:
        """Derived signals of ``batch`` with this fit's temperature centring (and the
        extra columns' centring)."""
        return stacked_signals(*self._signal_inputs(batch), self.options.dtemp_window)

    def _signal_inputs(self, batch: Batch, intervals: bool = True) -> tuple:
        """What :func:`~diffgyro._signal_builder.stacked_signals` reads of ``batch``, with
        this fit's centring of the temperature and the extra columns (``intervals``: see
        :func:`~diffgyro._signal_builder.signal_inputs`)."""
        names = aux_cols.aux_names(self.model.requires())
        aux_cols.check_columns(batch, names, vary=False)
        return signal_inputs(batch, norm=self.norm if self.model.requires() & {"temp"} else None,
                             aux=aux_cols.scaled(batch, self.aux_norm) if names else None,
                             intervals=intervals)

    def _axis_noise(self, i: int, axis: int) -> dict:
        """A noise process' levels on gyro axis ``axis`` of device ``i``, by label."""
        return {}

    def _likelihood(self, i: int) -> dict:
        """Record entries of a likelihood fit (after the noise floor)."""
        return {}

    def _verdict(self, i: int) -> dict:
        """Record entries judging the residual (after the motion record)."""
        return {}
