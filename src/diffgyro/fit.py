"""fit(model, batch): calibrate every device of a batch at once.

The front door: :func:`fit` checks the data against the model, picks the path and
returns a :class:`FitResult` per batch. The paths are engines of their own: the sums
path (:mod:`diffgyro._fit_sums`, the default: one blocked pass per trial of the time
constants), the direct path (:mod:`diffgyro._direct`: the design matrix,
Levenberg–Marquardt and variable projection), and the fit of a model's noise component
(a random walk: :mod:`diffgyro.kalman`). Every result then gets its motion judgement
(:func:`diffgyro._motion_judge.judge_motion`). Each device gets its own status, so one
bad device never sinks the batch.
"""

from __future__ import annotations

import dataclasses
import warnings
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from . import _aux as aux_cols
from ._direct import solve_batch, solve_device
from ._fit_result import AbstractFitResult
from ._fit_sums import layout_of, solve_sums
from ._jit import release_compiled_if_crowded
from ._motion_judge import judge_motion
from ._options import FitOptions
from ._signal_builder import batch_signals, stacked_signals
from .channel import GRAVITY, as_channel, check_channel, check_model, reads_gravity
from .data import Batch, Recording, as_batch, inputs_of, pad_devices, valid_samples
from .effects import RandomWalk, noise_fit, register_noise_fit
from .errors import DataError, SpecError
from .model import ErrorModel, Params
from .motion import Motion, check_ahead, motion_check
from .signals import TempNorm
from .status import explain, residual_verdict

__all__ = ["fit", "FitResult", "AbstractFitResult", "FitOptions", "solve_device"]

# --------------------------------------------------------------------------- results


class FitResult(AbstractFitResult):
    """The deterministic fit of every device of a batch (direct or sums path): the fields
    of :class:`AbstractFitResult`, and the Gauss–Newton covariance, per-axis σ and the
    per-term flags below."""

    residual_tells_motion: ClassVar[bool] = True

    model: ErrorModel = eqx.field(static=True)
    devices: tuple[str, ...] = eqx.field(static=True)
    params: Params
    norm: TempNorm
    temp_range: Float[Array, "d 2"] | None
    #: Covariance of each device's flat parameters (β per axis, then θ).
    cov: Float[Array, "d k k"]
    rms: Float[Array, " d"]
    heldout_rms: Float[Array, " d"]
    fold_mse: Float[Array, "d f"]
    noise_floor: Float[Array, " d"]
    noise_axes: Float[Array, "d 3"]
    #: Residual standard deviation per axis, rad/s.
    sigma: Float[Array, "d 3"]
    steps: Int[Array, " d"]
    status: Int[Array, " d"]
    #: Terms whose signal left its calibrated range (per term).
    range_flags: Bool[Array, "d t"]
    #: Terms the rank check found collinear (per term).
    collinear: Bool[Array, "d t"]
    n_samples: Float[Array, " d"]
    options: FitOptions
    aux_norm: dict[str, TempNorm] = eqx.field(default_factory=dict)
    aux_range: dict[str, Float[Array, "d 2"]] = eqx.field(default_factory=dict)
    motion: Motion | None = None
    static_only: bool = eqx.field(static=True, default=False)
    n_recorded: Float[Array, " d"] | None = None
    #: The sensor fitted (:mod:`diffgyro.channel`): ``gyro``, or ``accel`` with its
    #: gravity reference (m/s², the reading the offsets are relative to).
    channel: str = eqx.field(static=True, default="gyro")
    reference: Float[np.ndarray, "d 3"] | None = None
    #: The gravity (m/s²) an accelerometer fit in several orientations took as its input
    #: (its scale is relative to it); None otherwise.
    gravity: float | None = eqx.field(static=True, default=None)

    def status_detail(self, i: int) -> str:
        """Status and, when not ok, why in plain words (:func:`diffgyro.status.explain`)."""
        def row(a):  # device i of the host copy (indexing a JAX array compiles, per shape)
            return None if a is None else np.asarray(a)[i]

        return explain(self.status_name(i), self.model, range_flags=row(self.range_flags),
                       collinear=row(self.collinear), temp_range=row(self.temp_range),
                       n_samples=row(self.n_samples), steps=row(self.steps),
                       motion=None if self.motion is None else self.motion.record(i),
                       channel=self.channel)

    def stderr(self, i: int) -> Params:
        """Standard errors of device ``i``'s parameters, shaped like its Params."""
        p, q = self.model.n_params, self.model.n_nonlinear
        sd = np.sqrt(np.diagonal(np.asarray(self.cov)[i]))  # on the host: no program per shape
        return Params(beta=jnp.asarray(sd[:3 * p].reshape(3, p)), theta=jnp.asarray(sd[3 * p:3 * p + q]))

    def residuals(self, batch: Batch) -> Float[Array, "d n 3"]:
        """Measured minus predicted rate for every sample of ``batch`` (padding zeroed)."""
        # the sampling intervals only for a model that reads dT/dt (the sums path's rule)
        intervals = "dt" in layout_of(self.model, inputs_of(batch))[1]
        return _residual_batch(self.model, self.params, self._signal_inputs(batch, intervals),
                               self.options.dtemp_window)

    def _verdict(self, i: int) -> dict:
        return {"residual_ratio": residual_verdict(self.heldout_rms[i], self.noise_floor[i])[1]}


@eqx.filter_jit
def _residual_batch(model: ErrorModel, params: Params, inputs: tuple,
                    dtemp_window: float) -> Float[Array, "d n 3"]:
    """Every device's residual (padding zeroed) from its signals' inputs
    (:func:`~diffgyro._signal_builder.signal_inputs`): one program, signals derived inside."""
    sig = stacked_signals(*inputs, dtemp_window)
    return (sig.gyro - jax.vmap(model.predict)(params, sig)) * sig.mask[..., None]


def fit(
    model: ErrorModel | str,
    data: Batch | Recording | list[Recording],
    *,
    norm: TempNorm | None = None,
    options: FitOptions | None = None,
    theta0: Float[Array, "d q"] | None = None,
    aux_norm: dict[str, TempNorm] | None = None,
    static_only: bool = False,
    check_motion: bool = True,
    channel: str = "gyro",
    gravity: float = GRAVITY,
    **option_overrides,
) -> AbstractFitResult:
    """Calibrate every device of ``data`` with ``model``.

    **Arguments:**

    - ``model``: a spec string (``"bias_poly(2)+gradient"``) or an :class:`ErrorModel`.
    - ``data``: a :class:`Batch`, one :class:`Recording` or a list of them.
    - ``norm``: the temperature centring (default: each device's own range).
    - ``options``: :class:`FitOptions`; keyword ``option_overrides`` set its fields
      (``n_folds=5``, ``max_steps=100``, ``path="direct"``, ...).
    - ``theta0``: (devices × nonlinear parameters, solver space = log τ) replaces the grid
      start of the nonlinear solve.
    - ``aux_norm``: the centring of extra columns by name (``aux(NAME)`` terms).
    - ``static_only``: fit the detected static samples only (the moving ones, and a
      window either side, masked out).
    - ``check_motion``: check every recording for motion (below); False skips it.
    - ``channel``: the sensor fitted, ``"gyro"`` or ``"accel"`` (below).
    - ``gravity``: the local gravity (m/s²) of an accelerometer fit in several orientations.

    **Returns:** an :class:`AbstractFitResult`: a :class:`FitResult`, or for a model with
    a noise component the result of its registered fit (a
    :class:`diffgyro.kalman.RandomWalkFit` for ``random_walk``).

    Every device's recording is checked for motion (:func:`diffgyro.motion.motion_check`,
    ``check_motion=False`` skips it): without a rate reference in the model, a device
    that moved (:meth:`diffgyro.motion.Motion.moved_all`: more than 2 % of its recording,
    turns of at least ten times the threshold)
    gets status ``in_motion`` instead of ``ok``.

    ``channel="accel"`` fits the accelerometer's thermal offset relative to its gravity
    reference (:func:`diffgyro.channel.as_channel`); the motion check is still the IMU's,
    of the gyro and accelerometer as loaded. ``static_only`` is refused there: the rest
    either side of a move may hold another orientation, so another gravity reference.
    A model that reads a reference input there (``scale_poly``, ``misalignment``) reads
    gravity in several orientations: the samples at rest are fitted, each with gravity
    along its face as the input, for the absolute offset, its thermal change and the
    scale (:mod:`diffgyro.channel`).
    """
    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    imu = as_batch(data)
    channel = check_channel(channel)
    check_model(model, channel)
    if channel != "gyro" and static_only:
        raise DataError("static_only is not available on the accelerometer channel: each "
                        "stretch of rest may hold another orientation (another gravity "
                        "reference)", hint="record the soak in one orientation, at rest, or "
                        "in several and fit scale_poly(0) with the bias (docs/imu.md)")
    if channel != "gyro":  # one orientation, or several where the model reads gravity
        # (the IMU's motion check, without a turntable's reference rate: it explains a
        # turn, not the gravity the turn tilts)
        oriented = reads_gravity(model)
        motion = motion_check(dataclasses.replace(imu, rate=None, quat=None)) \
            if check_motion or oriented else None
        batch, reference = as_channel(imu, channel, gravity=gravity,
                                      static=motion.static if oriented else None)
        result = fit(model, batch, norm=norm, options=options, theta0=theta0, aux_norm=aux_norm,
                     check_motion=False, **option_overrides)
        if not isinstance(result, AbstractFitResult):
            return result
        result = dataclasses.replace(result, channel=channel, reference=reference,
                                     gravity=float(gravity) if oriented else None)
        if not (check_motion or oriented):
            return result
        recorded = jax.device_put(valid_samples(imu.mask).astype(float))
        return judge_motion(result, dataclasses.replace(batch, rate=None), motion, recorded,
                            oriented)
    batch = imu
    if not (check_motion or static_only):
        return _fit(model, batch, norm, options, theta0, aux_norm, option_overrides)
    floor: list = []  # (the noise floor's waiter, where the fit does not wait for it)
    if static_only:  # the fit needs the check's static samples
        motion = motion_check(batch)  # of gyro − rate where the data hold a rate reference
        batch = eqx.tree_at(lambda b: b.mask, batch, np.asarray(motion.static) & np.asarray(batch.mask))
        result = _fit(model, batch, norm, options, theta0, aux_norm, option_overrides)
    else:  # the check's first look reads the samples while the fit runs; the check then
        # judges what the fitted model leaves (judge_motion), while the sums path's noise
        # floor is still formed on the host's threads
        ahead = check_ahead(imu, reads=model.requires()
                            if model.noise is None and imu.rate is None else None)
        # (on two cores the floor waits for the check's read: the judgement needs it first)
        result = _fit(model, batch, norm, options, theta0, aux_norm, option_overrides, floor,
                      ahead.reading)
        motion = None
    if not isinstance(result, AbstractFitResult):  # a user's noise fit with a result of its own
        return result
    # (counted after the fit: while the check's first look, beside it, may still be reading)
    recorded = jax.device_put(valid_samples(imu.mask).astype(float))
    result = judge_motion(result, batch, motion, recorded, static_only,
                          ahead=None if static_only else ahead)
    if not floor:
        return result
    noise_floor, noise_axes = floor[0]()
    return dataclasses.replace(result, noise_floor=jax.device_put(noise_floor),
                               noise_axes=jax.device_put(noise_axes))


@register_noise_fit(RandomWalk)
def _fit_random_walk(model: ErrorModel, batch: Batch, **kwargs):
    """The built-in noise process' fit: the state-space path
    (:func:`diffgyro.kalman.fit_random_walk`), imported on its first use, so that a fit
    without a noise component never loads it (nor the stochastic model it runs)."""
    from .kalman import fit_random_walk

    return fit_random_walk(model, batch, **kwargs)


def _fit(model: ErrorModel, batch: Batch, norm, options, theta0, aux_norm, option_overrides,
         floor: list | None = None, floor_after=None):
    """:func:`fit` without the motion check; ``floor``: the sums path's noise floor is not
    waited for but its waiter appended there (:func:`~diffgyro._fit_sums.solve_sums`), and
    the result holds NaN in its place until the caller replaces it; ``floor_after``: the
    work the floor starts after."""
    if not jax.config.read("jax_enable_x64"):
        warnings.warn("diffgyro.fit runs in float32 because JAX float64 is off; "
                      "call diffgyro.enable_x64() first", stacklevel=2)
    release_compiled_if_crowded(interval=1.0)  # before this fit compiles its programs
    names = aux_cols.aux_names(model.requires())
    aux_cols.check_columns(batch, names)  # DataError: missing, gaps, constant
    missing = model.requires() - set(batch.signals) - {"t"} - {f"aux:{k}" for k in names}
    if missing:
        col = {"temp": "temp", "temp_ext": "temp_ext", "accel": "ax, ay, az",
               "rate": "rx, ry, rz"}
        name = sorted(missing)[0]
        raise DataError(f"model {model.spec!r} needs column(s) {col.get(name, name)}, not in the data",
                        file=batch.sources[0] if batch.sources else None, column=col.get(name, name))
    if model.noise is not None:  # the state-space path (random_walk: diffgyro.kalman)
        if names:
            raise SpecError(f"{model.noise.spec} with aux terms ({model.spec!r}) is not supported",
                            hint=f"fit the aux terms without {model.noise.spec}")
        fit_noise = noise_fit(model.noise)
        return fit_noise(model, batch, norm=norm, options=options, **option_overrides)
    opts = options or FitOptions()
    if option_overrides:
        opts = opts.replace(**option_overrides)
    if opts.path not in ("auto", "direct", "sums"):
        raise ValueError(f"unknown fit path {opts.path!r}; use 'auto', 'direct' or 'sums'")
    extra = aux_cols.norms(batch, names, aux_norm), aux_cols.ranges(batch, names)
    if opts.solver != "lm" and opts.path in ("sums", "auto"):
        return _fit_sums(model, batch, norm, opts, theta0, extra, floor, floor_after)
    if opts.path == "sums":
        raise ValueError("path='sums' needs solver='closed'")
    n_dev = batch.n_devices
    batch = pad_devices(batch)  # a few device-count buckets: no compile per batch size
    pad = np.minimum(np.arange(batch.n_devices), n_dev - 1)
    scaled = aux_cols.scaled(batch, {k: TempNorm(centre=v.centre[pad], scale=v.scale[pad])
                                     for k, v in extra[0].items()})
    sig = batch_signals(batch, norm=norm, dtemp_window=opts.dtemp_window, aux=scaled)
    if theta0 is not None:
        theta0 = jnp.broadcast_to(jnp.asarray(theta0, sig.gyro.dtype), (n_dev, model.n_nonlinear))
        theta0 = theta0[np.minimum(np.arange(batch.n_devices), n_dev - 1)]
    out = solve_batch(model, sig, opts, theta0)
    sig_norm = sig.norm
    if batch.n_devices != n_dev:  # unpadded on the host: no slicing program per shape
        out, sig_norm = jax.device_put(jax.tree.map(lambda a: np.asarray(a)[:n_dev], (out, sig_norm)))
        batch = batch.select(np.arange(n_dev))
    temp_range = None
    if batch.temp is not None:
        tmask = np.where(batch.mask, batch.temp, np.nan)
        temp_range = jnp.stack([jnp.asarray(np.nanmin(tmask, axis=1)),
                                jnp.asarray(np.nanmax(tmask, axis=1))], axis=1)
    norm_out = sig_norm if sig_norm is not None else TempNorm(
        centre=jnp.zeros(batch.n_devices), scale=jnp.ones(batch.n_devices))
    return _result(model, batch, out, norm_out, temp_range, opts, extra)


def _result(model: ErrorModel, batch: Batch, out: dict, norm: TempNorm, temp_range, opts: FitOptions,
            extra) -> FitResult:
    """The :class:`FitResult` of either path's per-device outputs ``out``."""
    return FitResult(
        model=model, devices=batch.devices, params=Params(beta=out["beta"], theta=out["theta"]),
        norm=norm, temp_range=temp_range, cov=out["cov"], rms=out["rms"],
        heldout_rms=out["heldout_rms"], fold_mse=out["fold_mse"], noise_floor=out["noise_floor"],
        noise_axes=out["noise_axes"], sigma=out["sigma"], steps=out["steps"],
        status=out["status"], range_flags=out["range_flags"], collinear=out["collinear"],
        n_samples=out["n_samples"], options=opts, **_aux_fields(extra))


def _aux_fields(extra) -> dict:
    """FitResult's ``aux_norm`` and ``aux_range`` from (norms, ranges) (JAX arrays)."""
    norms, ranges = extra
    return dict(aux_norm={k: TempNorm(centre=jnp.asarray(v.centre), scale=jnp.asarray(v.scale))
                          for k, v in norms.items()},
                aux_range={k: jnp.asarray(v) for k, v in ranges.items()})


def _fit_sums(model: ErrorModel, batch: Batch, norm: TempNorm | None, opts: FitOptions,
              theta0=None, extra=({}, {}), floor: list | None = None,
              floor_after=None) -> FitResult:
    """The sums path (:mod:`diffgyro._fit_sums`): one blocked pass per trial of the time
    constants; ``floor``, ``floor_after``: see :func:`_fit`."""

    out = solve_sums(model, batch, norm, opts, theta0, aux=aux_cols.scaled(batch, extra[0]),
                     floor=floor, floor_after=floor_after)
    d = batch.n_devices
    if floor:  # (NaN until the caller has waited for the floor)
        out["noise_floor"], out["noise_axes"] = np.full(d, np.nan), np.full((d, 3), np.nan)
    if "norm_centre" in out:
        norm_out = TempNorm(centre=jax.device_put(out.pop("norm_centre")),
                            scale=jax.device_put(out.pop("norm_scale")))
    else:
        norm_out = TempNorm(centre=jnp.zeros(d), scale=jnp.ones(d))
    # device_put, not jnp.asarray: that compiles a copy for every new shape (~10 ms each)
    temp_range = jax.device_put(out.pop("temp_range")) if "temp_range" in out else None
    out = jax.device_put(out)
    return _result(model, batch, out, norm_out, temp_range, opts, extra)
