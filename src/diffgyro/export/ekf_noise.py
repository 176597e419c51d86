"""An identified noise model (``diffgyro noise --json``) as filter parameters.

A navigation filter that carries the gyro bias as a random walk takes two
numbers per sensor: the white rate noise and the bias walk. Both autopilots
add them per prediction step of length Δt (their own code is the definition):

* PX4 EKF2 (src/modules/ekf2/EKF/covariance.cpp, ``Ekf::predictCovariance``):
  delta-angle variance ``(Δt · EKF2_GYR_NOISE)²`` and gyro-bias variance
  ``(Δt · EKF2_GYR_B_NOISE)²`` per step, Δt the filter period
  ``EKF2_PREDICT_US`` (default 10 000 µs); units rad/s and rad/s².
* ArduPilot EKF3 (libraries/AP_NavEKF3/AP_NavEKF3_core.cpp,
  ``CovariancePrediction``): delta-angle variance ``(Δt · EK3_GYRO_P_NSE)²``
  and delta-angle-bias variance ``(Δt² · EK3_GBIAS_P_NSE)²`` per step (its bias
  state is the rate bias times Δt), Δt the filter step, at least
  ``EKF_TARGET_DT`` = 12 ms (AP_NavEKF3_core.h); units rad/s and rad/s².

A white rate noise of density N (rad/s/√Hz) puts ``N²·Δt`` into the angle
over Δt, and a random walk K (rad/s/√s) puts ``K²·Δt`` into the bias, so the
parameters are ``N/√Δt`` and ``K/√Δt``. Kalibr's imu.yaml takes N and K
themselves (``gyroscope_noise_density``, ``gyroscope_random_walk``;
:mod:`.kalibr`).

None of these filters models a first-order Gauss–Markov bias. Over a step
short against its correlation time T, a Gauss–Markov bias of stationary σ
changes by a variance ``2σ²(1 − e^{−Δt/T}) ≈ 2σ²Δt/T``: the random walk
``K² = 2σ²/T`` that grows the bias uncertainty as fast. It is added to the
identified random walk (reported on stderr), which keeps the filter's bias
uncertainty from collapsing; on the worst of the three axes, as
:mod:`.kalibr` does.
"""

from __future__ import annotations

import math

from ..errors import DataError
from ._thermal import fmt_f32
from .px4 import TYPE_FLOAT32

__all__ = ["device_densities", "axis_densities", "px4_parameters", "ardupilot_parameters",
           "write_px4", "write_ardupilot", "PX4_DT", "ARDUPILOT_DT"]

#: PX4 EKF2's default prediction period, s (EKF2_PREDICT_US = 10000).
PX4_DT = 0.010
#: ArduPilot EKF3's target step, s (EKF_TARGET_DT).
ARDUPILOT_DT = 0.012


def axis_densities(axis: dict) -> tuple[float | None, float | None, list[str]]:
    """(N, K, notes) of one axis of ``noise --json``: the white-noise density and the random
    walk, Gauss–Markov processes folded into K as ``2σ²/T``."""
    n = k2 = None
    notes = []
    for c in axis.get("components", []):
        p = c.get("params", {})
        if c.get("kind") == "white":
            n = p["arw"]["value"]
        elif c.get("kind") == "random_walk":
            k2 = (k2 or 0.0) + p["rrw"]["value"] ** 2
        elif c.get("kind") == "gauss_markov":
            s, t = p["sigma"]["value"], p["tau"]["value"]
            k2 = (k2 or 0.0) + 2.0 * s * s / t
            notes.append(f"Gauss–Markov σ {s:.3g} rad/s, τ {t:.3g} s as the random walk "
                         f"√(2σ²/τ) = {math.sqrt(2 * s * s / t):.3g} rad/s/√s")
    return n, (None if k2 is None else math.sqrt(k2)), notes


def device_densities(doc: dict, device: str | None) -> tuple[str, float, float, list[str]]:
    """(device, N, K, report lines) of one device of a ``noise --json`` object: the worst axis."""
    devs = doc.get("devices") if isinstance(doc, dict) else None
    if not isinstance(devs, list) or not devs:
        raise DataError("not a 'noise --json' object (devices[].axes.*.components)")
    names = [str(d.get("device")) for d in devs]
    if device is None and len(devs) > 1:
        raise DataError(f"the noise models hold {len(devs)} devices; the parameters are for one",
                        hint=f"choose one with --device ({', '.join(names[:10])})")
    if device is not None and device not in names:
        raise DataError(f"device {device!r} is not in the noise models", hint=f"it has {', '.join(names[:10])}")
    d = devs[names.index(device) if device is not None else 0]
    name = str(d.get("device"))
    if d.get("status") != "ok" or not isinstance(d.get("axes"), dict):
        raise DataError(f"no noise model: {d.get('status_detail') or d.get('status')}", device=name)
    ns, ks, report = [], [], []
    for ax, a in d["axes"].items():
        try:
            n, k, notes = axis_densities(a)
        except (KeyError, TypeError, ValueError, ZeroDivisionError, AttributeError):
            raise DataError(f"axis {ax}: a component without its parameters' values "
                            "(kind, params.NAME.value)", device=name) from None
        report += [f"device {name} axis {ax}: {t}" for t in notes]
        if n is not None:
            ns.append(n)
        if k is not None:
            ks.append(k)
    if not ns:
        raise DataError("the noise models hold no white noise", device=name)
    if not ks:
        raise DataError("the noise models hold no random walk or Gauss–Markov bias", device=name,
                        hint="record the device static for longer (a bias process shows at τ of "
                             "minutes to hours)")
    return name, max(ns), max(ks), report


def px4_parameters(n: float, k: float, dt: float = PX4_DT) -> dict[str, float]:
    """EKF2_GYR_NOISE (rad/s) and EKF2_GYR_B_NOISE (rad/s²) for densities N, K and period Δt."""
    return {"EKF2_GYR_NOISE": n / math.sqrt(dt), "EKF2_GYR_B_NOISE": k / math.sqrt(dt)}


def ardupilot_parameters(n: float, k: float, dt: float = ARDUPILOT_DT) -> dict[str, float]:
    """EK3_GYRO_P_NSE (rad/s) and EK3_GBIAS_P_NSE (rad/s²) for densities N, K and step Δt."""
    return {"EK3_GYRO_P_NSE": n / math.sqrt(dt), "EK3_GBIAS_P_NSE": k / math.sqrt(dt)}


def write_px4(params: dict[str, float], device: str, dt: float) -> str:
    """QGroundControl parameter file (the layout of :mod:`.px4`): float32 values."""

    lines = ["# Onboard parameters for Vehicle 1", "#",
             f"# gyro noise of device {device} written by diffgyro export --format px4-ekf",
             f"# EKF2_PREDICT_US = {dt * 1e6:.0f}: parameter = density / sqrt(period)", "#",
             "# Vehicle-Id Component-Id Name Value Type"]
    lines += [f"1\t1\t{k}\t{fmt_f32(v)}\t{TYPE_FLOAT32}" for k, v in params.items()]
    return "\n".join(lines) + "\n"


def write_ardupilot(params: dict[str, float], device: str, dt: float) -> str:
    """Mission Planner parameter file (``NAME,VALUE``, the layout of :mod:`.ardupilot`)."""

    lines = [f"# gyro noise of device {device} written by diffgyro export --format ardupilot-ekf",
             f"# EKF3 step {dt:g} s: parameter = density / sqrt(step)"]
    lines += [f"{k},{fmt_f32(v)}" for k, v in params.items()]
    return "\n".join(lines) + "\n"
