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

A number the model does not stand behind is not written (:func:`unsupported`): a
parameter the identification marks ``not_identified`` (its interval spans more than
two decades), or a Gauss–Markov process shorter than a few sample intervals (white
noise at that sampling: as a walk √(2σ²/T) it would set a bias noise hundreds of
times too large). The export is refused, naming the axis, the parameter and why,
unless ``--force``, and then the file says so.
"""

from __future__ import annotations

import math

from ..errors import DataError
from ..stochastic import SHORT_SAMPLES, SPAN_LIMIT
from ._thermal import fmt_f32
from .px4 import TYPE_FLOAT32

__all__ = ["device_densities", "axis_densities", "unsupported", "px4_parameters", "ardupilot_parameters",
           "write_px4", "write_ardupilot", "PX4_DT", "ARDUPILOT_DT"]

#: PX4 EKF2's default prediction period, s (EKF2_PREDICT_US = 10000).
PX4_DT = 0.010
#: ArduPilot EKF3's target step, s (EKF_TARGET_DT).
ARDUPILOT_DT = 0.012


def unsupported(axis: dict, dt: float | None = None) -> list[str]:
    """What the filter parameters of one axis would carry that the model does not stand
    behind: each parameter they use that is ``not_identified`` (its ``why``), and a
    Gauss–Markov process shorter than the axis' ``resolution.gauss_markov_tau.min`` (else
    :data:`~diffgyro.stochastic.SHORT_SAMPLES` sample intervals ``dt``): white noise at that
    sampling, not a bias (a model written before the identification merged it).

    **Arguments:**

    - ``axis``: one axis of ``noise --json``.
    - ``dt``: the sampling interval, s.
    """
    used = {"white": ("arw",), "random_walk": ("rrw",), "gauss_markov": ("sigma", "tau")}
    out = []
    shortest = ((axis.get("resolution") or {}).get("gauss_markov_tau") or {}).get("min")
    if not isinstance(shortest, (int, float)) and dt:  # a model written before the resolution
        shortest = SHORT_SAMPLES * dt
    for c in axis.get("components", []):
        kind = c.get("kind")
        p = c.get("params", {})
        for name in used.get(kind, ()):
            status, why = p[name].get("status"), p[name].get("why", "no reason given")
            if status is None:  # a model written before the judgement: its interval's span
                lo, hi = (p[name].get("ci") or [None, None])[:2]
                if not (isinstance(lo, (int, float)) and isinstance(hi, (int, float)) and lo > 0
                        and hi / lo <= SPAN_LIMIT):
                    status = "not_identified"
                    why = f"its 95 % interval [{lo}, {hi}] spans more than two decades or is missing"
            if status == "not_identified":
                out.append(f"{kind} {name} is not identified ({why})")
        if kind == "gauss_markov" and isinstance(shortest, (int, float)) \
                and p["tau"]["value"] < shortest:
            s, t = p["sigma"]["value"], p["tau"]["value"]
            out.append(f"gauss_markov tau {t:.3g} s is below the shortest correlation time the "
                       f"sampling resolves ({shortest:.3g} s): white noise, not a bias (as a walk "
                       f"it would be √(2σ²/τ) = {math.sqrt(2 * s * s / t):.3g} rad/s²/√Hz)")
    return out


def axis_densities(axis: dict) -> tuple[float | None, float | None, list[str]]:
    """(N, K, notes) of one axis of ``noise --json``: the white-noise density and the random
    walk, Gauss–Markov processes folded into K as ``2σ²/T``.

    **Arguments:**

    - ``axis``: one axis of ``noise --json``.
    """
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
                         f"√(2σ²/τ) = {math.sqrt(2 * s * s / t):.3g} rad/s²/√Hz")
    return n, (None if k2 is None else math.sqrt(k2)), notes


def _walk_limit(d: dict) -> str:
    """The record's random-walk detection limit (the largest over its axes), as a phrase."""
    lims = [((a or {}).get("resolution") or {}).get("random_walk_limit") for a in d["axes"].values()]
    vals = [x["value"] for x in lims if isinstance(x, dict) and x.get("value")]
    if not vals:
        return ""
    return (f"; this record cannot see a random walk below K = {max(vals):.2g} rad/s²/√Hz, "
            "so it cannot say the walk is absent either")


def device_densities(doc: dict, device: str | None, force: bool = False
                     ) -> tuple[str, float, float, list[str]]:
    """(device, N, K, report lines) of one device of a ``noise --json`` object: the worst axis.

    A parameter the model does not stand behind (:func:`unsupported`) is refused, a
    DataError naming the axis, the parameter and why, unless ``force``: the report's first
    lines then say ``WARNING: written with --force: ...``.

    **Arguments:**

    - ``doc``: the ``noise --json`` object.
    - ``device``: the device (None: the only one).
    - ``force``: write parameters the model does not stand behind.
    """
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
    ns, ks, report, bad = [], [], [], []
    dt = d.get("sample_interval")
    dt = float(dt) if isinstance(dt, (int, float)) and dt > 0 else None
    for ax, a in d["axes"].items():
        try:
            n, k, notes = axis_densities(a)
            bad += [f"axis {ax}: {why}" for why in unsupported(a, dt)]
        except (KeyError, TypeError, ValueError, ZeroDivisionError, AttributeError):
            raise DataError(f"axis {ax}: a component without its parameters' values "
                            "(kind, params.NAME.value)", device=name) from None
        report += [f"device {name} axis {ax}: {t}" for t in notes]
        if n is not None:
            ns.append(n)
        if k is not None:
            ks.append(k)
    if bad and not force:
        raise DataError("refusing to write filter parameters the noise model does not identify: "
                        + "; ".join(bad), device=name,
                        hint="record the device at rest for longer (or at its full rate), or pass "
                             "--force to write them anyway (the file then says so)")
    report = [f"WARNING: written with --force: device {name} {why}" for why in bad] + report
    if not ns:
        raise DataError("the noise models hold no white noise", device=name)
    if not ks:
        raise DataError("the noise models hold no random walk or Gauss–Markov bias" + _walk_limit(d),
                        device=name, hint="record the device static for longer (a bias process "
                        "shows at τ of minutes to hours)")
    return name, max(ns), max(ks), report


def px4_parameters(n: float, k: float, dt: float = PX4_DT) -> dict[str, float]:
    """EKF2_GYR_NOISE (rad/s) and EKF2_GYR_B_NOISE (rad/s²) for densities N, K and period Δt.

    **Arguments:**

    - ``n``: the white-noise density N, rad/s/√Hz.
    - ``k``: the bias random walk K, rad/s/√s.
    - ``dt``: the filter's period, s.
    """
    return {"EKF2_GYR_NOISE": n / math.sqrt(dt), "EKF2_GYR_B_NOISE": k / math.sqrt(dt)}


def ardupilot_parameters(n: float, k: float, dt: float = ARDUPILOT_DT) -> dict[str, float]:
    """EK3_GYRO_P_NSE (rad/s) and EK3_GBIAS_P_NSE (rad/s²) for densities N, K and step Δt.

    **Arguments:**

    - ``n``: the white-noise density N, rad/s/√Hz.
    - ``k``: the bias random walk K, rad/s/√s.
    - ``dt``: the filter's step, s.
    """
    return {"EK3_GYRO_P_NSE": n / math.sqrt(dt), "EK3_GBIAS_P_NSE": k / math.sqrt(dt)}


def write_px4(params: dict[str, float], device: str, dt: float, notes: list[str] = ()) -> str:
    """QGroundControl parameter file (the layout of :mod:`.px4`): float32 values; ``notes``
    (the --force warnings) as comments.

    **Arguments:**

    - ``params``: the parameters by name.
    - ``device``: the device, as the comments name it.
    - ``dt``: the filter's period, s.
    - ``notes``: comment lines.
    """

    lines = ["# Onboard parameters for Vehicle 1", "#",
             f"# gyro noise of device {device} written by diffgyro export --format px4-ekf",
             f"# EKF2_PREDICT_US = {dt * 1e6:.0f}: parameter = density / sqrt(period)",
             *(f"# {ln}" for ln in notes), "#",
             "# Vehicle-Id Component-Id Name Value Type"]
    lines += [f"1\t1\t{k}\t{fmt_f32(v)}\t{TYPE_FLOAT32}" for k, v in params.items()]
    return "\n".join(lines) + "\n"


def write_ardupilot(params: dict[str, float], device: str, dt: float, notes: list[str] = ()) -> str:
    """Mission Planner parameter file (``NAME,VALUE``, the layout of :mod:`.ardupilot`);
    ``notes`` (the --force warnings) as comments.

    **Arguments:**

    - ``params``: the parameters by name.
    - ``device``: the device, as the comments name it.
    - ``dt``: the filter's step, s.
    - ``notes``: comment lines.
    """

    lines = [f"# gyro noise of device {device} written by diffgyro export --format ardupilot-ekf",
             f"# EKF3 step {dt:g} s: parameter = density / sqrt(step)",
             *(f"# {ln}" for ln in notes)]
    lines += [f"{k},{fmt_f32(v)}" for k, v in params.items()]
    return "\n".join(lines) + "\n"
