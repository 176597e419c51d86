"""Differentiable chamber / rate-table test plans, their predicted accuracy, and plan design.

A :class:`ChamberPlan` is a thermal-chamber profile with a rate table inside
(the fog-one-run procedure generalised): from the start temperature the chamber ramps
at ``ramp`` (°C/s) to each soak temperature ``temps[k]`` in turn and holds it
for ``soaks[k]`` seconds. The last ``spin_fraction`` of every soak turns the
table at each rate level ``rates[r]``, clockwise then counter-clockwise for
equal times; the static rest of the soak is split into ``2·n_headings`` equal
dwells at table headings ``360°·j/n_headings``, ``j = 0 … n−1`` and back
(ramps and spins start at heading 0).

Every number of the plan is a JAX array and the whole chain

    plan → chamber temperature → sensor temperature (first-order lag)
         → table rate, Earth rate, gravity → :func:`~diffgyro.signals.make_signals`

is smooth (table edges are logistic steps ``edge`` seconds wide and chamber
corners are rounded over ``corner`` seconds, each at least one sample), so the Fisher
information of a plan, the predicted compensation error over an operating
range, and an expected fit through :func:`~diffgyro.fit.solve_device` can all
be differentiated with respect to soak temperatures and durations, ramp rate,
table rates and spin time. The number of headings is an integer (static):
its effect is a finite difference (see :func:`heading_study`).

Noise is white with angle random walk ``arw`` (rad/s/√Hz): a sample of
interval ``dt`` has variance ``arw²/dt``, so the information of a plan,
``Σ Jᵀ J · dt / arw²``, does not depend on the grid. Earth rate (latitude,
NWU frame as in :mod:`diffgyro.simulate`) is in the fit's reference rate when
``earth_rate="known"``; with ``"unknown"`` only its vertical part is (the
table's heading is not surveyed), and the horizontal part is a systematic
error the prediction carries (:func:`expected_fit_error`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.signal import lfilter

from ._direct import solve_device
from .data import Batch
from .effects import first_order_lag
from .fit import FitOptions, fit
from .model import ErrorModel, Params, columns_times
from .signals import Signals, TempNorm, make_signals

__all__ = ["predict_plan", "optimise_plan", "plan_sensitivity", "heading_study",
           "budget_for_accuracy", "simulate_devices", "monte_carlo", "PlanConfig", "ChamberPlan",
           "s2_plan", "plan_duration", "plan_environment", "OperatingRange", "operating_signals",
           "compensation_error", "Prediction", "DesignResult", "MonteCarlo", "PlanSpace",
           "Environment", "default_truth", "flat", "unflat", "output_jacobian", "smooth_max",
           "DEG", "EARTH_RATE"]

EARTH_RATE = 7.292115e-5  # rad/s
G0 = 9.80665
DEG = math.pi / 180.0


# --------------------------------------------------------------------------- plan and settings


class ChamberPlan(eqx.Module):
    """The continuous knobs of a chamber + rate-table plan (physical units)."""

    temps: Float[Array, " k"]          # soak chamber set points, °C, in order
    soaks: Float[Array, " k"]          # soak durations, s
    ramp: Float[Array, ""]             # chamber ramp rate, °C/s
    rates: Float[Array, " r"]          # table rate levels, rad/s
    spin_fraction: Float[Array, ""]    # share of every soak spent spinning

    @property
    def n_soaks(self) -> int:
        return int(self.temps.shape[0])


class PlanConfig(eqx.Module):
    """Everything about a plan that is not optimised (static, hashable)."""

    #: time grid; keep its interval well below the shortest spin (fog-one-run: 1 min → ≥ 2048 samples)
    n_samples: int = eqx.field(static=True, default=8192)
    edge: float = eqx.field(static=True, default=5.0)  # s, width of table edges (≥ one sample)
    corner: float = eqx.field(static=True, default=30.0)  # s, rounding of chamber corners
    n_headings: int = eqx.field(static=True, default=1)
    start_temp: float = eqx.field(static=True, default=25.0)
    temp_limits: tuple[float, float] = eqx.field(static=True, default=(-40.0, 70.0))
    ramp_limits: tuple[float, float] = eqx.field(static=True, default=(0.25 / 60, 3.0 / 60))
    rate_limit: float = eqx.field(static=True, default=100.0 * DEG)
    tau_sensor: float = eqx.field(static=True, default=600.0)
    self_heating: float = eqx.field(static=True, default=0.0)
    mount: tuple[float, float, float] = eqx.field(
        static=True, default=(1 / math.sqrt(3), 1 / math.sqrt(3), 1 / math.sqrt(3)))
    latitude: float = eqx.field(static=True, default=45.0)
    earth_rate: str = eqx.field(static=True, default="known")  # "known" | "unknown" | "none"
    dtemp_window: float = eqx.field(static=True, default=60.0)


def s2_plan(step: float = 10.0, soak: float = 1800.0, ramp_per_min: float = 1.5,
            table_rate_deg: float = 10.0, spin: float = 60.0,
            limits: tuple[float, float] = (-40.0, 70.0)) -> ChamberPlan:
    """The published fog-one-run profile: −40…70 °C in 10 °C steps, 30 min soaks, ±10 °/s for 1 min each way.

    The patent cools at 1–2 °C/min; 1.5 °C/min is taken. Its total time is
    :func:`plan_duration` (about 8 h from a 25 °C start).

    **Arguments:**

    - ``step``: the temperature step, °C.
    - ``soak``: each soak, s.
    - ``ramp_per_min``: the ramp rate, °C/min.
    - ``table_rate_deg``: the table's rate, °/s.
    - ``spin``: each spin, s.
    - ``limits``: the coldest and hottest temperatures, °C.
    """
    temps = np.arange(limits[0], limits[1] + 1e-9, step)
    k = len(temps)
    f64 = np.float64
    return ChamberPlan(temps=jnp.asarray(temps, f64), soaks=jnp.asarray(np.full(k, soak), f64),
                       ramp=jnp.asarray(ramp_per_min / 60.0, f64),
                       rates=jnp.asarray([table_rate_deg * DEG], f64),
                       spin_fraction=jnp.asarray(2.0 * spin / soak, f64))


def _smooth_abs(x, eps=0.01):
    return jnp.sqrt(x * x + eps * eps)


def ramp_times(plan: ChamberPlan, config: PlanConfig) -> Float[Array, " k"]:
    """Duration (s) of the ramp into every soak."""
    prev = jnp.concatenate([jnp.asarray([config.start_temp], plan.temps.dtype), plan.temps[:-1]])
    return _smooth_abs(plan.temps - prev) / plan.ramp


def plan_duration(plan: ChamberPlan, config: PlanConfig) -> Float[Array, ""]:
    """Total test time (s): every ramp and every soak.

    **Arguments:**

    - ``plan``: the :class:`ChamberPlan`.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    """
    return jnp.sum(ramp_times(plan, config)) + jnp.sum(plan.soaks)


def _rotation_to(v) -> np.ndarray:
    """Rotation matrix taking the table axis (nav z, up) onto body vector ``v``."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ v)
    if c > 1 - 1e-12:
        return np.eye(3)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    a = np.cross(z, v)
    s = np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]]) / s
    return np.eye(3) + s * k + (1 - c) * k @ k


class Environment(eqx.Module):
    """What one device sees on a plan's time grid (JAX arrays)."""

    t: Float[Array, " n"]
    chamber: Float[Array, " n"]
    temp: Float[Array, " n"]          # sensor temperature, °C
    rate_true: Float[Array, "n 3"]    # true inertial body rate
    rate_ref: Float[Array, "n 3"]     # the reference rate the fit is given
    accel: Float[Array, "n 3"]        # specific force, m/s²
    dt: Float[Array, ""]


def plan_environment(plan: ChamberPlan, config: PlanConfig,
                     tau_sensor=None, self_heating=None) -> Environment:
    """Chamber and sensor temperature, table and Earth rate of one device on the plan's grid.

    ``tau_sensor`` (s) and ``self_heating`` (°C) default to the config's
    nominal device; pass arrays to vmap over a population.

    **Arguments:**

    - ``plan``: the :class:`ChamberPlan`.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``tau_sensor``: the sensor lag, s (default: the config's).
    - ``self_heating``: the self-heating, °C (default: the config's).
    """
    dtype = plan.temps.dtype
    tau = jnp.asarray(config.tau_sensor if tau_sensor is None else tau_sensor, dtype)
    heat = jnp.asarray(config.self_heating if self_heating is None else self_heating, dtype)
    k, n, nh = plan.n_soaks, config.n_samples, config.n_headings
    ramps = ramp_times(plan, config)
    # knot times: ramp_k ends at e_k, soak_k ends at f_k
    seg = jnp.stack([ramps, plan.soaks], axis=1).reshape(-1)
    ends = jnp.cumsum(seg)
    # the record runs a few edge widths past the last soak so that the last spin ends
    total = ends[-1] + 10 * config.edge
    soak_start, soak_end = ends[0::2], ends[1::2]
    dt = total / (n - 1)
    t = jnp.arange(n, dtype=dtype) * dt
    # chamber: ramps at ±ramp between soaks, corners rounded over ``corner`` seconds (a
    # controller's response; it also keeps the profile smooth in every plan number)
    prev = jnp.concatenate([jnp.asarray([config.start_temp], dtype), plan.temps[:-1]])
    slope = (plan.temps - prev) / ramps                       # (k,) °C/s, finite for equal temps
    ramp_start = jnp.concatenate([jnp.zeros((1,), dtype), soak_end[:-1]])
    corner = jnp.maximum(config.corner, dt)

    def rise(a):  # smoothed max(t − a, 0)
        return corner * jax.nn.softplus((t[:, None] - a[None, :]) / corner)

    chamber = config.start_temp + (rise(ramp_start) - rise(soak_start)) @ slope
    temp = first_order_lag(t, chamber + heat, tau)

    width = jnp.maximum(config.edge, dt)

    def step(edge):  # smooth unit step at time(s) ``edge``, at least one sample wide
        return jax.nn.sigmoid((t[:, None] - jnp.atleast_1d(edge)[None, :]) / width)

    # table rate: last spin_fraction of every soak, each level CW then CCW
    r = plan.rates.shape[0]
    spin = plan.spin_fraction * plan.soaks / (2 * r)                  # (k,) per direction
    spin0 = soak_end - plan.spin_fraction * plan.soaks               # (k,)
    a = spin0[:, None] + 2 * jnp.arange(r, dtype=dtype)[None, :] * spin[:, None]  # (k, r)
    s = jnp.broadcast_to(spin[:, None], (k, r))
    pulses = step(a.reshape(-1)) - 2 * step((a + s).reshape(-1)) + step((a + 2 * s).reshape(-1))
    omega = pulses @ jnp.broadcast_to(plan.rates[None, :], (k, r)).reshape(-1)  # (n,)
    mount = jnp.asarray(config.mount, dtype)
    mount = mount / jnp.linalg.norm(mount)
    table = omega[:, None] * mount[None, :]

    # heading: 2·nh equal static dwells at headings 0, 1, …, nh−1, nh−1, …, 0 (× 360°/nh; the
    # mirrored order cancels a linear temperature drift within the soak), plus the angle
    # the table turns while spinning
    heading = jnp.cumsum(omega) * dt
    if nh > 1:
        dwell = (spin0 - soak_start) / (2 * nh)
        j = np.arange(1, 2 * nh)
        jump = np.where(j < nh, 1.0, np.where(j == nh, 0.0, -1.0))
        edges = soak_start[:, None] + dwell[:, None] * jnp.asarray(j, dtype)[None, :]  # (k, 2nh-1)
        heading = heading + (2 * jnp.pi / nh) * (
            step(edges.reshape(-1)) @ jnp.tile(jnp.asarray(jump, dtype), k))
    rot = jnp.asarray(_rotation_to(config.mount), dtype)  # table frame -> body
    lat = config.latitude * DEG
    if config.earth_rate == "none":
        earth = jnp.zeros_like(table)
        vertical = earth
    else:
        horiz = EARTH_RATE * math.cos(lat)
        e_table = jnp.stack([horiz * jnp.cos(heading), -horiz * jnp.sin(heading),
                             jnp.full_like(heading, EARTH_RATE * math.sin(lat))], axis=1)
        earth = e_table @ rot.T
        vertical = jnp.broadcast_to(EARTH_RATE * math.sin(lat) * mount, earth.shape)
    rate_true = table + earth
    if config.earth_rate == "unknown":
        rate_ref = table + vertical
    else:
        rate_ref = rate_true
    accel = jnp.broadcast_to(G0 * mount, (n, 3))
    return Environment(t=t, chamber=chamber, temp=temp, rate_true=rate_true, rate_ref=rate_ref,
                       accel=accel, dt=dt)


def env_signals(env: Environment, norm: TempNorm, gyro=None, reference: bool = True,
                dtemp_window: float = 60.0) -> Signals:
    """Signals of an environment as a fit sees them (``reference``) or as the truth acts."""
    n = env.t.shape[0]
    gyro = jnp.zeros((n, 3), env.temp.dtype) if gyro is None else gyro
    return make_signals(env.t, gyro, jnp.ones((n,), bool),
                        rate=env.rate_ref if reference else env.rate_true,
                        temp=env.temp, temp_ext=env.chamber, accel=env.accel, norm=norm,
                        dtemp_window=dtemp_window, dt=env.dt)


# --------------------------------------------------------------------------- operating range


@dataclass(frozen=True)
class OperatingRange:
    """Where the calibration is used: sensor temperatures, input rate, steady temperature.

    The compensation error is evaluated on a grid of ``n_temps`` temperatures
    at input rates ``−rate, 0, +rate`` (rad/s) on every axis at once, at
    ``dtemp`` °C/s and long after power-on.
    """

    temps: tuple[float, float] = (-40.0, 70.0)
    rate: float = 10.0 * DEG
    n_temps: int = 23
    dtemp: float = 0.0

    @property
    def norm(self) -> TempNorm:
        lo, hi = self.temps
        return TempNorm(centre=jnp.asarray(0.5 * (lo + hi)), scale=jnp.asarray(0.5 * (hi - lo)))

    def grid(self) -> tuple[np.ndarray, np.ndarray]:
        """(temperatures (m,), rate vectors (m, 3)) of all operating points."""
        temps = np.linspace(*self.temps, self.n_temps)
        levels = (-self.rate, 0.0, self.rate) if self.rate else (0.0,)
        tt = np.repeat(temps, len(levels))
        rr = np.tile(np.asarray(levels), len(temps))[:, None] * np.ones((1, 3))
        return tt, rr


def operating_signals(temps, rates, norm: TempNorm, dtemp: float = 0.0,
                      accel=(0.0, 0.0, G0), t_on: float = 1e7) -> Signals:
    """One single-sample :class:`Signals` per operating point (leading axis m).

    A single sample is steady state for every term: a lagged temperature
    equals the temperature, the warm-up transient is over (``t_on`` s after
    power-on), the inside–outside difference is zero.

    **Arguments:**

    - ``temps``: the operating temperatures (m,), °C.
    - ``rates``: the true rates (m, 3) or (3,), rad/s.
    - ``norm``: the temperature normalisation.
    - ``dtemp``: dT/dt there, °C/s.
    - ``accel``: the specific force, m/s².
    - ``t_on``: the time since power-on, s.
    """
    temps = jnp.asarray(temps, jnp.result_type(float))
    m = temps.shape[0]
    rates = jnp.broadcast_to(jnp.asarray(rates, temps.dtype), (m, 3))
    one = jnp.ones((m, 1), temps.dtype)
    centre, scale = jnp.asarray(norm.centre, temps.dtype), jnp.asarray(norm.scale, temps.dtype)
    return Signals(
        t=one * t_on, gyro=rates[:, None, :], mask=jnp.ones((m, 1), bool), rate=rates[:, None, :],
        temp=temps[:, None], temp_s=((temps - centre) / scale)[:, None], dtemp=one * dtemp,
        heating=one * 0.0, temp_ext=temps[:, None],
        accel=jnp.broadcast_to(jnp.asarray(accel, temps.dtype), (m, 1, 3)),
        norm=TempNorm(centre=jnp.broadcast_to(centre, (m,)), scale=jnp.broadcast_to(scale, (m,))),
        has_rate=True)


def compensation_error(fit_model: ErrorModel, fitted: Params, op: Signals,
                       truth_model: ErrorModel | None = None, truth: Params | None = None):
    """Compensated minus true rate at every operating point, (m, 3).

    The gyro output is what the truth produces at the operating point
    (``truth_model``/``truth``; default: the fitted model with ``truth``),
    then inverted with the fitted calibration.

    **Arguments:**

    - ``fit_model``: the calibrated :class:`~diffgyro.model.ErrorModel`.
    - ``fitted``: its fitted parameters.
    - ``op``: the operating points (:func:`operating_signals`).
    - ``truth_model``: the true model (default: ``fit_model``).
    - ``truth``: the true parameters.
    """
    truth_model = fit_model if truth_model is None else truth_model

    def one(s):
        meas = truth_model.predict(truth, s) if truth is not None else s.rate
        comp = fit_model.compensate(fitted, eqx.tree_at(lambda z: z.gyro, s, meas))
        return (comp - s.rate)[0]

    return jax.vmap(one)(op)


# --------------------------------------------------------------------------- information


def flat(params: Params) -> Float[Array, " k"]:
    """(beta per axis, theta) as one vector, in FitResult.cov's order.

    **Arguments:**

    - ``params``: the :class:`~diffgyro.model.Params`.
    """
    return jnp.concatenate([params.beta.reshape(-1), params.theta])


def unflat(vec: Float[Array, " k"], model: ErrorModel) -> Params:
    """The :class:`~diffgyro.model.Params` of a :func:`flat` vector.

    **Arguments:**

    - ``vec``: the flat vector.
    - ``model``: the :class:`~diffgyro.model.ErrorModel` it belongs to.
    """
    p, q = model.n_params, model.n_nonlinear
    return Params(beta=vec[:3 * p].reshape(3, p), theta=vec[3 * p:3 * p + q])


def output_jacobian(model: ErrorModel, sig: Signals, params: Params) -> Float[Array, "n 3 k"]:
    """∂(model output per sample and axis)/∂(flat params): the Gauss–Newton rows.

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``sig``: one device's :class:`~diffgyro.signals.Signals`.
    - ``params``: the parameters it is linearised at.
    """
    p, q = model.n_params, model.n_nonlinear
    x = model.design(sig, params.theta)  # (n, 3, p)
    n = x.shape[0]
    eye = jnp.eye(3, dtype=x.dtype)
    jb = (x[:, :, None, :] * eye[None, :, :, None]).reshape(n, 3, 3 * p)
    if not q:
        return jb
    jt = jax.jacfwd(lambda th: columns_times(model.design(sig, th), params.beta))(
        params.theta)
    return jnp.concatenate([jb, jt], axis=-1)


def information(model: ErrorModel, sig: Signals, params: Params, arw, dt) -> Float[Array, "k k"]:
    """Fisher information of the flat parameters under white noise (ARW per axis, rad/s/√Hz)."""
    jac = output_jacobian(model, sig, params)
    wgt = sig.mask.astype(jac.dtype)[:, None] * dt / jnp.broadcast_to(jnp.asarray(arw) ** 2, (3,))
    jw = (jac * wgt[:, :, None]).reshape(-1, jac.shape[-1])
    return jw.T @ jac.reshape(-1, jac.shape[-1])


def scaled_inverse(info: Float[Array, "k k"]) -> Float[Array, "k k"]:
    """Inverse of a symmetric positive-definite matrix after diagonal scaling."""
    d = jnp.sqrt(jnp.maximum(jnp.diagonal(info), 1e-300))
    g = info / (d[:, None] * d[None, :])
    return jnp.linalg.inv(g) / (d[:, None] * d[None, :])


def default_truth(model: ErrorModel, dtype=jnp.float64) -> Params:
    """Nominal parameters used to linearise nonlinear models (time constants 10 min).

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``dtype``: the arrays' dtype.
    """
    beta = jnp.full((3, model.n_params), 1e-3, dtype)
    theta = jnp.full((model.n_nonlinear,), math.log(600.0), dtype)
    return Params(beta=beta, theta=theta)


class Prediction(eqx.Module):
    """Predicted accuracy of a plan: 1σ compensation error over the operating grid."""

    sigma: Float[Array, "m 3"]        # random part (from the Fisher information)
    systematic: Float[Array, "m 3"]   # expected error of the fit itself (misspecification)
    cov: Float[Array, "k k"]
    duration: Float[Array, ""]

    @property
    def total(self) -> Float[Array, "m 3"]:
        return jnp.sqrt(self.sigma**2 + self.systematic**2)

    @property
    def worst(self) -> Float[Array, ""]:
        return jnp.max(self.total)


@eqx.filter_jit
def predict_plan(plan: ChamberPlan, config: PlanConfig, model: ErrorModel, arw,
                 op: OperatingRange, truth: Params | None = None, truth_model: ErrorModel | None = None,
                 systematic: bool | None = None, fit_options=None) -> Prediction:
    """Predicted compensation error of ``model`` calibrated on ``plan`` (differentiable).

    Random part: ``G C Gᵀ`` with ``C`` the inverse Fisher information of the
    plan and ``G`` the Jacobian of the compensated rate at the operating
    points. Systematic part (when the truth differs from the fitted model, or
    Earth rate is not in the reference): the compensation error of the fit to
    the plan's noiseless data through :func:`~diffgyro.fit.solve_device` —
    closed form for linear models, optimistix's implicit adjoint otherwise.

    **Arguments:**

    - ``plan``: the :class:`ChamberPlan`.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``model``: the :class:`~diffgyro.model.ErrorModel` calibrated.
    - ``arw``: the white-noise density, rad/s/√Hz.
    - ``op``: the :class:`OperatingRange` the error is judged over.
    - ``truth``: the true parameters (default: :func:`default_truth`).
    - ``truth_model``: the true model, where it differs from ``model``.
    - ``systematic``: include the systematic part (default: where the truth differs or Earth
      rate is unknown).
    - ``fit_options``: the fit's :class:`~diffgyro.fit.FitOptions`.
    """
    dtype = plan.temps.dtype
    truth = default_truth(model, dtype) if truth is None else truth
    norm = op.norm
    env = plan_environment(plan, config)
    sig = env_signals(env, norm, dtemp_window=config.dtemp_window)
    fitted = None  # the noiseless fit, solved once for the linearisation and the bias
    if truth_model is not None and truth_model.spec != model.spec:
        fitted = _fit_noiseless(plan, config, model, truth_model, truth, norm, fit_options)
    lin = truth if fitted is None else fitted
    info = information(model, sig, lin, arw, env.dt)
    cov = scaled_inverse(info)
    tt, rr = op.grid()
    ops = operating_signals(tt, rr, norm, op.dtemp)
    g = jax.jacfwd(lambda v: compensation_error(model, unflat(v, model), ops, model, lin))(flat(lin))
    sigma = jnp.sqrt(jnp.maximum(jnp.einsum("mik,kl,mil->mi", g, cov, g), 0.0))
    if systematic is None:
        systematic = (truth_model is not None and truth_model.spec != model.spec) or \
            config.earth_rate == "unknown"
    if systematic:
        if fitted is None:
            fitted = _fit_noiseless(plan, config, model, truth_model or model, truth, norm,
                                    fit_options)
        sys_err = _fit_error(model, fitted, op, truth_model or model, truth)
    else:
        sys_err = jnp.zeros_like(sigma)
    return Prediction(sigma=sigma, systematic=sys_err, cov=cov, duration=plan_duration(plan, config))


def _fit_noiseless(plan, config, model, truth_model, truth, norm, fit_options):

    env = plan_environment(plan, config)
    true_sig = env_signals(env, norm, reference=False, dtemp_window=config.dtemp_window)
    gyro = truth_model.predict(truth, true_sig)
    sig = env_signals(env, norm, gyro=gyro, dtemp_window=config.dtemp_window)
    out = solve_device(model, sig, fit_options or FitOptions(n_folds=2, n_blocks=2))
    return Params(beta=out["beta"], theta=out["theta"])


def expected_fit_error(plan: ChamberPlan, config: PlanConfig, model: ErrorModel,
                       truth_model: ErrorModel, truth: Params, op: OperatingRange,
                       fit_options=None) -> Float[Array, "m 3"]:
    """Compensation error of ``model`` fitted to the plan's noiseless truth data.

    Differentiable in the plan: the fit is :func:`~diffgyro.fit.solve_device`
    (closed form, or variable projection with optimistix's implicit adjoint).
    """
    fitted = _fit_noiseless(plan, config, model, truth_model, truth, op.norm, fit_options)
    return _fit_error(model, fitted, op, truth_model, truth)


def _fit_error(model, fitted, op, truth_model, truth):
    """The compensation error, over ``op``'s grid, of ``fitted`` against the truth."""
    tt, rr = op.grid()
    ops = operating_signals(tt, rr, op.norm, op.dtemp)
    return compensation_error(model, fitted, ops, truth_model, truth)


def smooth_max(x: Float[Array, "..."], p: float = 16.0) -> Float[Array, ""]:
    """Power mean of order ``p``: a smooth stand-in for ``max`` (≤ max, → max as p grows).

    **Arguments:**

    - ``x``: the values.
    - ``p``: the power mean's order.
    """
    m = jax.lax.stop_gradient(jnp.max(x))
    return m * jnp.mean((x / m) ** p) ** (1.0 / p)


# --------------------------------------------------------------------------- plan optimisation

PLAN_FIELDS = ("temps", "soaks", "ramp", "rates", "spin_fraction")
DEFAULT_FREE = ("temps", "soaks", "ramp", "spin_fraction")
MAX_SPIN_FRACTION = 0.95
_MIN_SOAK_SHARE = 0.02


def _logit(p):
    p = jnp.clip(p, 1e-3, 1 - 1e-3)
    return jnp.log(p) - jnp.log1p(-p)


class PlanSpace(eqx.Module):
    """Unconstrained coordinates of plans that take exactly ``budget`` seconds.

    Soak temperatures, ramp rate, table rates and spin share pass through
    logistic maps into their limits; the soak durations are a softmax share
    of whatever the ramps leave of the budget.
    """

    config: PlanConfig = eqx.field(static=True)
    budget: Float[Array, ""]

    def to_plan(self, raw: dict) -> tuple[ChamberPlan, Float[Array, ""]]:
        """The plan of ``raw`` and a penalty (> 0 when the ramps alone overrun the budget)."""
        c = self.config
        lo, hi = c.temp_limits
        temps = lo + (hi - lo) * jax.nn.sigmoid(raw["temps"])
        rlo, rhi = c.ramp_limits
        ramp = rlo + (rhi - rlo) * jax.nn.sigmoid(raw["ramp"])
        rates = c.rate_limit * jax.nn.sigmoid(raw["rates"])
        spin = MAX_SPIN_FRACTION * jax.nn.sigmoid(raw["spin_fraction"])
        probe = ChamberPlan(temps=temps, soaks=jnp.zeros_like(temps), ramp=ramp, rates=rates,
                            spin_fraction=spin)
        avail = self.budget - jnp.sum(ramp_times(probe, c))
        floor = _MIN_SOAK_SHARE * self.budget
        penalty = (jax.nn.relu(floor - avail) / self.budget) ** 2 * 1e3
        soaks = jax.nn.softmax(raw["soaks"]) * jnp.maximum(avail, floor)
        return eqx.tree_at(lambda p: p.soaks, probe, soaks), penalty

    def from_plan(self, plan: ChamberPlan) -> dict:
        """Coordinates of ``plan`` (its soak shares are kept; the budget rescales them)."""
        c = self.config
        lo, hi = c.temp_limits
        rlo, rhi = c.ramp_limits
        return {
            "temps": _logit((plan.temps - lo) / (hi - lo)),
            "soaks": jnp.log(plan.soaks / jnp.sum(plan.soaks)),
            "ramp": _logit((plan.ramp - rlo) / (rhi - rlo)),
            "rates": _logit(plan.rates / c.rate_limit),
            "spin_fraction": _logit(plan.spin_fraction / MAX_SPIN_FRACTION),
        }


class DesignResult(eqx.Module):
    """An optimised plan, its predicted accuracy and the criterion at every step."""

    plan: ChamberPlan
    prediction: Prediction
    history: Float[Array, " steps"]
    raw: dict


def design_objective(raw: dict, space: PlanSpace, model: ErrorModel, arw, op: OperatingRange,
                     p: float = 16.0, **predict_kw) -> Float[Array, ""]:
    """log of the smooth worst-case predicted error, plus the budget penalty."""
    plan, penalty = space.to_plan(raw)
    pred = predict_plan(plan, space.config, model, arw, op, **predict_kw)
    return jnp.log(smooth_max(pred.total, p)) + penalty


def optimise_plan(plan0: ChamberPlan, config: PlanConfig, model: ErrorModel | str, arw,
                  op: OperatingRange, budget: float | None = None,
                  free: tuple[str, ...] = DEFAULT_FREE, steps: int = 300, lr: float = 0.05,
                  p: float = 16.0, **predict_kw) -> DesignResult:
    """Minimise the predicted worst-case compensation error of a plan by gradient (Adam).

    ``budget`` (s) is the total test time (default: ``plan0``'s own); only the
    fields named in ``free`` move (the rate table's speed, for one, is kept
    unless ``"rates"`` is listed). The objective is the log of a power mean
    of order ``p`` of the predicted 1σ error over the operating grid; the
    learning rate follows a cosine decay to a tenth.

    **Arguments:**

    - ``plan0``: the starting plan.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``model``: the model calibrated: a spec or an :class:`~diffgyro.model.ErrorModel`.
    - ``arw``: the white-noise density, rad/s/√Hz.
    - ``op``: the :class:`OperatingRange` the error is judged over.
    - ``budget``: the total test time, s (default: ``plan0``'s own).
    - ``free``: the plan's fields that move.
    - ``steps``: Adam steps.
    - ``lr``: the initial learning rate.
    - ``p``: the power mean's order.
    - ``**predict_kw``: options of :func:`predict_plan`.
    """
    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    unknown = set(free) - set(PLAN_FIELDS)
    if unknown:
        raise ValueError(f"unknown plan fields {sorted(unknown)}; choose from {PLAN_FIELDS}")
    budget = float(plan_duration(plan0, config)) if budget is None else float(budget)
    space = PlanSpace(config=config, budget=jnp.asarray(budget, plan0.temps.dtype))
    raw0 = space.from_plan(plan0)
    mask = {k: jnp.asarray(1.0 if k in free else 0.0) for k in raw0}
    raw, hist = _adam(raw0, space, model, jnp.asarray(arw), op, mask, steps, jnp.asarray(lr),
                      p, predict_kw)
    plan, _ = space.to_plan(raw)
    pred = predict_plan(plan, config, model, arw, op, **predict_kw)
    return DesignResult(plan=plan, prediction=pred, history=jnp.exp(hist), raw=raw)


@eqx.filter_jit
def _adam(raw0, space, model, arw, op, mask, steps, lr, p, predict_kw):
    value_and_grad = jax.value_and_grad(design_objective)
    b1, b2, eps = 0.9, 0.999, 1e-8

    def body(carry, i):
        raw, m, v = carry
        val, g = value_and_grad(raw, space, model, arw, op, p, **predict_kw)
        g = jax.tree.map(lambda gi, mi: jnp.where(jnp.isfinite(gi), gi, 0.0) * mi, g, mask)
        m = jax.tree.map(lambda a, b: b1 * a + (1 - b1) * b, m, g)
        v = jax.tree.map(lambda a, b: b2 * a + (1 - b2) * b * b, v, g)
        rate = lr * (0.55 + 0.45 * jnp.cos(jnp.pi * i / steps))
        corr = jnp.sqrt(1 - b2 ** (i + 1)) / (1 - b1 ** (i + 1))
        raw = jax.tree.map(lambda r, a, b: r - rate * corr * a / (jnp.sqrt(b) + eps), raw, m, v)
        return (raw, m, v), val

    zeros = jax.tree.map(jnp.zeros_like, raw0)
    (raw, _, _), hist = jax.lax.scan(body, (raw0, zeros, zeros), jnp.arange(steps))
    return raw, hist


def plan_sensitivity(plan: ChamberPlan, config: PlanConfig, model: ErrorModel | str, arw,
                     op: OperatingRange, **predict_kw) -> dict:
    """Gradient of the predicted worst-case error with respect to every plan number.

    Returns ``worst`` (1σ, rad/s), ``grad`` (a ChamberPlan of ∂worst/∂field,
    in rad/s per field unit) and ``elasticity`` (∂log worst/∂log field: the
    % change of the error per % change of the field).

    **Arguments:**

    - ``plan``: the :class:`ChamberPlan`.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``model``: the model calibrated: a spec or an :class:`~diffgyro.model.ErrorModel`.
    - ``arw``: the white-noise density, rad/s/√Hz.
    - ``op``: the :class:`OperatingRange` the error is judged over.
    - ``**predict_kw``: options of :func:`predict_plan`.
    """
    if isinstance(model, str):
        model = ErrorModel.from_spec(model)

    def worst(pl):
        return predict_plan(pl, config, model, arw, op, **predict_kw).worst

    val, grad = eqx.filter_jit(jax.value_and_grad(worst))(plan)
    elastic = jax.tree.map(lambda g, x: g * x / val, grad, plan)
    return dict(worst=val, grad=grad, elasticity=elastic)


def heading_study(plan: ChamberPlan, config: PlanConfig, model: ErrorModel | str, arw,
                  op: OperatingRange, headings=(1, 2, 4), **predict_kw) -> dict[int, float]:
    """Predicted worst-case error for several numbers of table headings (an integer knob:
    a finite difference, not a gradient). It matters when Earth rate is not in the
    reference (``config.earth_rate="unknown"``).

    **Arguments:**

    - ``plan``: the :class:`ChamberPlan`.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``model``: the model calibrated: a spec or an :class:`~diffgyro.model.ErrorModel`.
    - ``arw``: the white-noise density, rad/s/√Hz.
    - ``op``: the :class:`OperatingRange` the error is judged over.
    - ``headings``: the numbers of headings tried.
    - ``**predict_kw``: options of :func:`predict_plan`.
    """
    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    out = {}
    for h in headings:
        cfg = dataclasses.replace(config, n_headings=int(h))
        out[int(h)] = float(predict_plan(plan, cfg, model, arw, op, **predict_kw).worst)
    return out


def budget_for_accuracy(target: float, plan0: ChamberPlan, config: PlanConfig,
                        model: ErrorModel | str, arw, op: OperatingRange, lo: float, hi: float,
                        iterations: int = 4, **opt_kw) -> tuple[float, DesignResult]:
    """Shortest test time whose optimised plan reaches a predicted worst-case ``target``.

    From ``hi`` seconds (which must reach the target), steps down in time by
    the white-noise law (error ∝ time^−½) until the target is missed, then
    regula falsi (Illinois) on log error against log time, never below
    ``lo``; every trial time optimises a plan started from ``plan0``.
    Returns the shortest trial time that reached the target and its plan.

    **Arguments:**

    - ``target``: the predicted worst-case 1σ error to reach, rad/s.
    - ``plan0``: the plan every trial starts from.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``model``: the model calibrated: a spec or an :class:`~diffgyro.model.ErrorModel`.
    - ``arw``: the white-noise density, rad/s/√Hz.
    - ``op``: the :class:`OperatingRange` the error is judged over.
    - ``lo``: the shortest test time tried, s.
    - ``hi``: the longest, s (it must reach the target).
    - ``iterations``: regula falsi steps.
    - ``**opt_kw``: options of :func:`optimise_plan`.
    """
    def err(x):
        res = optimise_plan(plan0, config, model, arw, op, budget=math.exp(x), **opt_kw)
        return math.log(float(res.prediction.worst)) - math.log(target), res

    b = math.log(hi)
    fb, best = err(b)
    if fb > 0:
        raise ValueError("the optimised plan misses the target even at the longest time")
    a = fa = None
    side = 0
    for _ in range(iterations):
        if a is None:
            x = max(b + 2.0 * fb, math.log(lo))
            if x >= b - 1e-6:
                break
        else:
            x = b - fb * (b - a) / (fb - fa)
        fx, res = err(x)
        if fx <= 0:
            b, fb, best = x, fx, res
            if side == -1:
                fa *= 0.5
            side = -1
        else:
            if a is not None and side == 1:
                fb *= 0.5
            a, fa = x, fx
            side = 1
    return math.exp(b), best


# --------------------------------------------------------------------------- simulation and Monte Carlo


def simulate_devices(plan: ChamberPlan, config: PlanConfig, model: ErrorModel | str, n_devices: int,
                     arw, norm: TempNorm, seed: int = 0, truth: Params | None = None,
                     param_spread: float = 0.2, tau_spread: float = 0.1, heating_spread: float = 0.5,
                     gm_sigma: float = 0.0, gm_tau: float = 300.0):
    """Devices with known truth run through ``plan``: (Batch, truth Params with a device axis).

    Each device has its own sensor lag (``tau_spread`` relative) and
    self-heating (``heating_spread`` °C), its own parameters (``truth``
    times ``1 + param_spread·N(0,1)``), white noise of density ``arw`` and
    optionally Gauss–Markov (AR(1)) noise of standard deviation ``gm_sigma``
    and correlation time ``gm_tau`` s. The fit sees the plan's reference
    rate and the sensor temperature.

    **Arguments:**

    - ``plan``: the :class:`ChamberPlan`.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``model``: the model calibrated: a spec or an :class:`~diffgyro.model.ErrorModel`.
    - ``n_devices``: how many devices.
    - ``arw``: the white-noise density, rad/s/√Hz.
    - ``norm``: the temperature normalisation of ``truth``.
    - ``seed``: the seed.
    - ``truth``: the nominal true parameters (default: :func:`default_truth`).
    - ``param_spread``: the parameters' relative spread.
    - ``tau_spread``: the sensor lag's relative spread.
    - ``heating_spread``: the self-heating's spread, °C.
    - ``gm_sigma``: Gauss–Markov noise σ, rad/s (0: none).
    - ``gm_tau``: its correlation time, s.
    """


    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    rng = np.random.default_rng(seed)
    truth = default_truth(model) if truth is None else truth
    d = n_devices
    tau = config.tau_sensor * np.exp(tau_spread * rng.standard_normal(d))
    heat = config.self_heating + heating_spread * rng.standard_normal(d)
    beta = np.asarray(truth.beta)[None] * (1 + param_spread * rng.standard_normal((d, 3, model.n_params)))
    theta = np.asarray(truth.theta)[None] + (param_spread * rng.standard_normal((d, model.n_nonlinear))
                                             if model.n_nonlinear else np.zeros((d, 0)))
    params = Params(beta=jnp.asarray(beta), theta=jnp.asarray(theta))

    env, clean = _simulate_clean(plan, config, model, norm, jnp.asarray(tau), jnp.asarray(heat),
                                 params)
    dt = float(env.dt[0])
    n = config.n_samples
    arw = np.broadcast_to(np.asarray(arw, float), (3,))
    noise = rng.standard_normal((d, n, 3)) * arw / math.sqrt(dt)
    if gm_sigma:
        rho = math.exp(-dt / gm_tau)
        drive = rng.standard_normal((d, n, 3)) * gm_sigma * math.sqrt(1 - rho**2)
        drive[:, 0] = rng.standard_normal((d, 3)) * gm_sigma  # start in steady state
        noise = noise + lfilter([1.0], [1.0, -rho], drive, axis=1)
    gyro = np.asarray(clean) + noise
    batch = Batch(t=np.asarray(env.t), gyro=gyro, mask=np.ones((d, n), bool),
                  n_valid=np.full(d, n), temp=np.asarray(env.temp), temp_ext=np.asarray(env.chamber),
                  accel=np.asarray(env.accel), rate=np.asarray(env.rate_ref),
                  devices=tuple(f"sim{seed}-{i:04d}" for i in range(d)), sources=(None,) * d)
    return batch, params


@eqx.filter_jit
def _simulate_clean(plan, config, model, norm, tau, heat, params):
    """Every device's environment and noiseless output (one program per plan shape and model)."""
    def one(tau, heat, pr):
        env = plan_environment(plan, config, tau, heat)
        sig = env_signals(env, norm, reference=False, dtemp_window=config.dtemp_window)
        return env, model.predict(pr, sig)

    return jax.vmap(one)(tau, heat, params)


class MonteCarlo(eqx.Module):
    """Compensation errors of simulated devices calibrated on a plan."""

    errors: Float[Array, "d m 3"]   # compensated minus true rate at every operating point
    status: Float[Array, " d"]

    @property
    def rms(self) -> Float[Array, "m 3"]:
        """RMS over devices at every operating point and axis (compare with Prediction.total)."""
        return jnp.sqrt(jnp.mean(self.errors**2, axis=0))

    @property
    def worst(self) -> Float[Array, ""]:
        """Worst case over the operating range of the RMS error: the criterion's counterpart."""
        return jnp.max(self.rms)

    @property
    def device_worst(self) -> Float[Array, " d"]:
        """Each device's largest |error| over the operating range and axes."""
        return jnp.max(jnp.abs(self.errors), axis=(1, 2))


def monte_carlo(plan: ChamberPlan, config: PlanConfig, model: ErrorModel | str, arw,
                op: OperatingRange, n_devices: int = 400, seed: int = 0, chunk: int = 100,
                truth: Params | None = None, fit_kw: dict | None = None, **sim_kw) -> MonteCarlo:
    """Simulate ``n_devices`` through ``plan``, calibrate each with :func:`~diffgyro.fit.fit`
    and measure its compensation error over the operating range.

    ``fit_kw`` goes to ``fit`` (e.g. ``path="direct"`` for the
    :func:`~diffgyro.fit.solve_device` path that the sensitivities differentiate).

    **Arguments:**

    - ``plan``: the :class:`ChamberPlan`.
    - ``config``: the :class:`PlanConfig` (table, reference, sampling, the nominal device).
    - ``model``: the model calibrated: a spec or an :class:`~diffgyro.model.ErrorModel`.
    - ``arw``: the white-noise density, rad/s/√Hz.
    - ``op``: the :class:`OperatingRange` the error is judged over.
    - ``n_devices``: how many devices.
    - ``seed``: the seed.
    - ``chunk``: devices simulated and fitted at a time.
    - ``truth``: the nominal true parameters.
    - ``fit_kw``: options of ``fit``.
    - ``**sim_kw``: options of :func:`simulate_devices`.
    """

    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    tt, rr = op.grid()
    ops = operating_signals(tt, rr, op.norm, op.dtemp)
    err_fn = jax.jit(jax.vmap(lambda f, t: compensation_error(model, f, ops, model, t)))
    errors, status = [], []
    for c, start in enumerate(range(0, n_devices, chunk)):
        m = min(chunk, n_devices - start)
        batch, true = simulate_devices(plan, config, model, m, arw, op.norm, seed=seed * 1000 + c,
                                       truth=truth, **sim_kw)
        res = fit(model, batch, norm=op.norm, **(fit_kw or {}))
        errors.append(err_fn(res.params, true))
        status.append(res.status)
    return MonteCarlo(errors=jnp.concatenate(errors), status=jnp.concatenate(status))
