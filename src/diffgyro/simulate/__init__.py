"""Simulated gyro batches with known truth: test plans, device populations, noise.

:func:`simulate` runs a test plan (:mod:`.plans`) for a population of devices
(:mod:`.population`) and returns the measured :class:`~diffgyro.data.Batch`
with its :class:`~.truth.Truth`. Per device:

1. the plan gives the chamber temperature, the dissipated power, the true
   rate, the specific force and the attitude;
2. the sensor temperature lags the chamber and self-heats
   (:mod:`.thermal`), with its exact time derivative;
3. the deterministic gyro error is the project's own
   :class:`~diffgyro.model.ErrorModel` evaluated on
   :func:`~diffgyro.signals.make_signals` built from the *true* sensor
   temperature, the chamber temperature as ``temp_ext``, the true specific
   force and the true rate, with the truth's fixed TempNorm; ``dtemp`` is
   replaced by the true derivative (and the heating/cooling latch is taken
   from it), so the gradient and hysteresis effects are physical;
4. noise (:mod:`.noise`) is added and the output quantised; the reported
   temperatures get read-out noise and optional quantisation
   (``temp_quantum``); the accelerometer gets its own errors and noise.

A fit given the truth's norm (``fit(spec, batch, norm=truth.norm)``) thus
estimates ``truth.params`` directly; use ``truth.params_for(norm)`` to compare
with a fit made in another normalisation.

Float64: call :func:`diffgyro.enable_x64` first (the CLI and the tests do);
the true rate is added in numpy float64 either way.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._aux import aux_names
from ..channel import check_model, reads_gravity
from ..data import Batch, Recording
from ..errors import DataError, SpecError
from ..model import ErrorModel, Params
from ..signals import HEATING_THRESHOLD, TempNorm, latched_heating, make_signals
from ._motion import to_body
from ._noise import NoiseLevels, gyro_noise, noise_levels, quantise
from ._plans import PLANS, Environment, Plan, get_plan
from ._population import (
    PRESETS,
    Preset,
    draw_accel_errors,
    draw_params,
    draw_thermal,
    get_preset,
    stream,
)
from ._supply import supply_voltage
from ._thermal import sensor_temperature
from ._truth import Truth, rebase, truth_path

__all__ = ["simulate", "get_plan", "Truth", "Plan", "PLANS", "PRESETS", "Environment",
           "NoiseLevels", "Preset", "demo_batch", "model_error", "rebase", "truth_path"]

#: Samples × devices evaluated per compiled call of the error model.
CHUNK_SAMPLES = 4_000_000


@eqx.filter_jit
def _error_chunk(model: ErrorModel, norm: TempNorm, params: Params, t, rate, temp, dtemp,
                 temp_ext, accel, aux):
    def one(params, t, rate, temp, dtemp, temp_ext, accel, aux):
        n = t.shape[0]
        mask = jnp.ones((n,), bool)
        sig = make_signals(t, jnp.zeros_like(rate), mask, rate=rate, temp=temp, temp_ext=temp_ext,
                           accel=accel, norm=norm, dt=t[1] - t[0], aux=aux)
        heating = latched_heating(dtemp, mask, HEATING_THRESHOLD)
        sig = eqx.tree_at(lambda s: (s.dtemp, s.heating), sig, (dtemp, heating))
        return model.error(params, sig)

    return jax.vmap(one)(params, t, rate, temp, dtemp, temp_ext, accel, aux)


def model_error(model: ErrorModel, params: Params, norm: TempNorm, t, rate, temp, dtemp,
                temp_ext, accel, aux_s: dict | None = None) -> np.ndarray:
    """Deterministic error (devices, n, 3) of ``model`` on true signals, evaluated in
    device chunks of equal size (one compilation).

    **Arguments:**

    - ``model``: the true :class:`~diffgyro.model.ErrorModel`.
    - ``params``: its coefficients, beta (devices, 3, P) and theta (devices, Q).
    - ``norm``: the temperature normalisation they refer to.
    - ``t``: sample times (n,), s.
    - ``rate``: the true rate (devices, n, 3), rad/s.
    - ``temp``: the true die temperature (devices, n), °C.
    - ``dtemp``: the true dT/dt (devices, n), °C/s.
    - ``temp_ext``: the external temperature (devices, n), °C.
    - ``accel``: the true specific force (devices, n, 3), m/s².
    - ``aux_s``: the extra columns, centred and scaled, (devices, n) each.
    """
    aux_s = dict(aux_s or {})
    d, n = temp.shape
    if model.n_params == 0:
        return np.zeros((d, n, 3))
    chunk = max(1, min(d, CHUNK_SAMPLES // max(n, 1)))
    tt = np.broadcast_to(t, (chunk, n))
    out = np.empty((d, n, 3))
    put = lambda x: jax.device_put(np.asarray(x))  # noqa: E731  (jnp.asarray compiles a copy)
    for lo in range(0, d, chunk):
        idx = np.minimum(np.arange(lo, lo + chunk), d - 1)  # pad the last chunk by repetition
        res = _error_chunk(
            model, norm, Params(beta=put(params.beta[idx]), theta=put(params.theta[idx])),
            put(tt), put(rate[idx]), put(temp[idx]), put(dtemp[idx]), put(temp_ext[idx]),
            put(accel[idx]), {k: put(v[idx]) for k, v in aux_s.items()})
        hi = min(lo + chunk, d)
        out[lo:hi] = np.asarray(res)[: hi - lo]
    return out


def _device_params(params: Params, model: ErrorModel, d: int) -> Params:
    beta = np.asarray(params.beta, float)
    theta = np.asarray(params.theta, float)
    if beta.ndim == 2:
        beta = np.broadcast_to(beta, (d, *beta.shape))
    if theta.ndim == 1:
        theta = np.broadcast_to(theta, (d, *theta.shape))
    if beta.shape != (d, 3, model.n_params) or theta.shape != (d, model.n_nonlinear):
        raise SpecError(
            f"params do not fit model {model.spec!r}: beta {beta.shape}, theta {theta.shape}",
            hint=f"expected beta (3, {model.n_params}) or ({d}, 3, {model.n_params}) and theta "
                 f"({model.n_nonlinear},) or ({d}, {model.n_nonlinear})")
    return Params(beta=np.array(beta), theta=np.array(theta))


def simulate(
    plan: str | Plan,
    n_devices: int = 3,
    effects: str | None = None,
    seed: int = 0,
    preset: str | Preset | None = None,
    noise: dict | str | NoiseLevels | None = None,
    temp_quantum: float | None = None,
    *,
    params: Params | None = None,
    temp_norm: TempNorm | None = None,
    accel_errors: bool | None = None,
    accel_effects: str | None = None,
    accel_params: Params | None = None,
    keep_components: bool = False,
    device_prefix: str = "dev",
    aux: dict | None = None,
    **plan_options,
) -> tuple[Batch, Truth]:
    """Simulate ``n_devices`` gyros through test ``plan``; returns ``(batch, truth)``.

    **Arguments:**

    - ``plan``: the test plan's name (``"thermal"``, ``"rate_table"``, ``"six_face"``,
      ``"warmup"``, …) or a plan object.
    - ``n_devices``: how many devices.
    - ``effects``: the true model spec (default: the plan's).
    - ``seed``: the seed; the same arguments and seed always give identical output.
    - ``preset``: ``"mems"`` or ``"fog"`` (default: the plan's): coefficient spreads and
      noise.
    - ``noise``: overrides the noise levels (``"none"``, or a dict such as
      ``{"arw": 1e-4, "rrw": 0}``).
    - ``temp_quantum``: rounds the reported temperatures (°C).
    - ``params``: fixes the true coefficients (Params with beta (3, P) or (d, 3, P),
      theta (Q,) or (d, Q)).
    - ``temp_norm``: the normalisation ``params`` refer to (default: the plan's).
    - ``accel_errors``: turns accelerometer bias/scale/misalignment on (default: the
      plan's).
    - ``accel_effects``: a spec of bias terms (``bias_poly(3)+gradient``) that adds the
      accelerometer's thermal offset; the truth keeps its coefficients in ``truth.accel``
      (``thermal_beta``, ``thermal_theta``) and the spec in
      ``truth.info["accel_effects"]``.
    - ``accel_params``: that offset's coefficients (m/s² per unit regressor, same
      temperature norm; default: drawn like the gyro's and :data:`ACCEL_PER_GYRO` times
      larger).
    - ``keep_components``: store the deterministic error, the true specific force, each
      noise part (and the accelerometer's thermal offset, ``accel_thermal``) in
      ``truth.env``.
    - ``device_prefix``: devices are named ``{device_prefix}000``, ….
    - ``aux``: extra columns by name ((n,) or (devices, n) arrays); a column an
      ``aux(NAME)`` effect reads that is not given is a simulated supply voltage
      (:func:`.supply.supply_voltage`); ``truth.aux_norm`` holds the centring the true
      coefficients refer to (pass it to ``fit(..., aux_norm=)``).
    - ``**plan_options``: the plan's options (see :mod:`.plans`), e.g. ``sample_rate``,
      ``duration``.
    """
    if isinstance(n_devices, bool) or not isinstance(n_devices, int | np.integer) or n_devices < 1:
        raise DataError(f"number of devices must be a positive integer, not {n_devices!r}")
    d = int(n_devices)
    plan_obj = get_plan(plan, **plan_options)
    preset_obj = get_preset(preset or plan_obj.default_preset)
    model = ErrorModel.from_spec(effects or plan_obj.default_effects)
    env = plan_obj.build(d, seed)
    n, dt = env.n, env.dt
    norm = temp_norm or plan_obj.temp_norm(env)
    norm = TempNorm(centre=np.float64(norm.centre), scale=np.float64(norm.scale))

    # 1. thermal response of every device
    thermal = draw_thermal(preset_obj, d, seed)
    temp, dtemp, heat_state = sensor_temperature(
        env.chamber, env.power, dt, thermal["tau_sensor"], thermal["self_heating"],
        thermal["tau_heating"], env.settled)
    chamber = np.broadcast_to(env.chamber, (d, n))

    # 2. deterministic error from the project's model
    if params is None:
        params = draw_params(model, preset_obj, d, seed, float(norm.scale))
    else:
        params = _device_params(params, model, d)
    rate = np.broadcast_to(env.rate, (d, n, 3))
    force = np.broadcast_to(env.specific_force, (d, n, 3))
    extra, aux_norm = _extra_columns(model, aux, env.t, d, seed)
    aux_s = {k: (v - aux_norm[k].centre) / aux_norm[k].scale for k, v in extra.items()}
    error = model_error(model, params, norm, env.t, rate, temp, dtemp, chamber, force, aux_s)

    # 3. noise, quantisation, other sensors
    levels = noise_levels(preset_obj, d, seed, noise, temp_quantum)
    gnoise, parts = gyro_noise(levels, n, dt, seed, keep=keep_components)
    gyro = quantise(rate + error + gnoise, levels.quantum)
    use_accel_errors = plan_obj.default_accel_errors if accel_errors is None else bool(accel_errors)
    acc = draw_accel_errors(preset_obj, d, seed, use_accel_errors)
    temp_out, ext_out, accel, mag = _other_sensors(env, levels, acc, temp, chamber, force, seed)
    info = dict(env.info)
    if accel_effects:
        accel_thermal = _accel_thermal(accel_effects, accel_params, acc, preset_obj, d, seed,
                                       norm, env, temp, dtemp, chamber, force)
        accel = accel + accel_thermal
        info["accel_effects"] = ErrorModel.from_spec(accel_effects).spec

    # 4. recordings, batch, truth
    devices = tuple(f"{device_prefix}{i:03d}" for i in range(d))
    recs = _recordings(env, devices, f"simulate:{plan_obj.name}", gyro, temp_out, ext_out, accel,
                       mag, rate, extra)
    batch = Batch.from_recordings(recs)
    env_arrays = {"t": env.t, "temp": temp, "dtemp": dtemp, "chamber": env.chamber,
                  "power_state": heat_state}
    if keep_components and accel_effects:
        env_arrays["accel_thermal"] = accel_thermal
    if keep_components:
        env_arrays.update({"error": error, "specific_force": np.array(force), "rate": np.array(rate),
                           **{f"noise_{k}": v for k, v in parts.items()}})
    truth = Truth(
        plan=plan_obj.name, options=plan_obj.resolved(), spec=model.spec, preset=preset_obj.name,
        seed=int(seed), devices=devices, params=params, norm=norm, noise=levels,
        thermal=thermal, accel=acc, outputs=tuple(sorted(env.outputs)), segments=env.segments,
        info=info, env=env_arrays, aux_norm=aux_norm)
    return batch, truth


#: A MEMS accelerometer's thermal offsets in m/s² per °C are roughly this many times its
#: gyro's in rad/s per °C (about 0.5 mg/°C against 0.01 °/s/°C).
ACCEL_PER_GYRO = 20.0


def _accel_thermal(spec: str, params, acc: dict, preset_obj, d: int, seed: int, norm, env, temp,
                   dtemp, chamber, force) -> np.ndarray:
    """The accelerometer's thermal offset (devices, n, 3) of ``spec``; its coefficients are
    written into ``acc`` (``thermal_beta``, ``thermal_theta``)."""
    model = ErrorModel.from_spec(spec)
    check_model(model, "accel")
    if reads_gravity(model):
        raise SpecError(f"accel_effects {spec!r} holds a term of the input; the accelerometer's "
                        "thermal offset is bias terms only",
                        hint="its scale and misalignment are drawn with accel_errors=True")
    if params is None:
        drawn = draw_params(model, preset_obj, d, seed + 7919, float(norm.scale))
        params = Params(beta=np.asarray(drawn.beta) * ACCEL_PER_GYRO, theta=drawn.theta)
    params = _device_params(params, model, d)
    acc["thermal_beta"], acc["thermal_theta"] = np.array(params.beta), np.array(params.theta)
    zero = np.zeros((d, env.n, 3))
    return model_error(model, params, norm, env.t, zero, temp, dtemp, chamber, force)


def _other_sensors(env, levels: NoiseLevels, acc: dict, temp, chamber, force, seed: int):
    """Read-outs beside the gyro: the two temperatures (noisy, quantised), the
    accelerometer (with its errors ``acc``) and the magnetometer where the plan has one."""
    d, n = temp.shape
    rng = stream(seed, "sensor_noise")
    temp_out = quantise(temp + levels.temp_noise * rng.standard_normal((d, n)), levels.temp_quantum)
    ext_out = quantise(chamber + levels.temp_noise * rng.standard_normal((d, n)), levels.temp_quantum)
    accel = (np.einsum("dij,dnj->dni", np.eye(3) + acc["error_matrix"], force)
             + acc["bias"][:, None, :]
             + rng.standard_normal((d, n, 3)) * (levels.accel_noise / math.sqrt(env.dt))[:, None, None])
    mag = None
    if "mag" in env.outputs and env.mag_field is not None:

        quat_d = np.broadcast_to(env.quat, (d, n, 4))
        mag = to_body(quat_d, env.mag_field) + levels.mag_noise * rng.standard_normal((d, n, 3))
    return temp_out, ext_out, accel, mag


def _recordings(env, devices, source, gyro, temp_out, ext_out, accel, mag, rate, extra):
    """One Recording per device, with the outputs the plan records."""
    quat = np.broadcast_to(env.quat, (len(devices), env.n, 4))
    return [Recording(
        t=env.t.copy(), gyro=gyro[i], temp=temp_out[i],
        temp_ext=ext_out[i] if "temp_ext" in env.outputs else None,
        accel=accel[i], mag=None if mag is None else mag[i],
        rate=np.array(rate[i]) if "rate" in env.outputs else None,
        quat=np.array(quat[i]) if "quat" in env.outputs else None,
        device=dev, source=source, aux={k: np.array(v[i]) for k, v in extra.items()})
        for i, dev in enumerate(devices)]


def _extra_columns(model: ErrorModel, given, t, d: int, seed: int):
    """Extra columns (devices, n) by name, and each one's centring over all devices."""

    n = t.shape[0]
    out = {}
    for name, values in dict(given or {}).items():
        arr = np.asarray(values, np.float64)
        if arr.shape not in ((n,), (d, n)):
            raise DataError(f"extra column {name!r} has shape {arr.shape}; expected ({n},) "
                            f"or ({d}, {n})", column=name)
        out[name] = np.array(np.broadcast_to(arr, (d, n)))
    for name in aux_names(model.requires()):
        if name not in out:
            out[name] = supply_voltage(t, d, seed, name)
    norms = {}
    for name, arr in out.items():
        lo, hi = float(arr.min()), float(arr.max())
        norms[name] = TempNorm(centre=np.float64(0.5 * (lo + hi)),
                               scale=np.float64(max(0.5 * (hi - lo), 1e-12)))
    return out, norms


def demo_batch(n_devices: int = 4, seed: int = 0, effects: str = "bias_poly(2)+gradient",
               duration: float = 7200.0, sample_rate: float = 1.0, **kwargs) -> tuple[Batch, Truth]:
    """A small thermal batch with a hidden effect, for demos and tests.

    The truth is ``bias_poly(2)+gradient`` (MEMS preset): a fit with
    ``bias_poly(2)`` alone leaves residuals that follow dT/dt during the
    ramps (about 1e-3 rad/s at the fastest ramp, well above the noise), and
    adding ``gradient`` closes the gap. Two hours at 1 Hz, the default
    thermal profile compressed (ramps ≈ 2× faster).

    **Arguments:**

    - ``n_devices``: how many devices.
    - ``seed``: the seed.
    - ``effects``: the true model spec.
    - ``duration``: the run's length, s.
    - ``sample_rate``: samples per second.
    - ``**kwargs``: further arguments of :func:`simulate`.
    """
    return simulate("thermal", n_devices, effects=effects, seed=seed, duration=duration,
                    sample_rate=sample_rate, **kwargs)
