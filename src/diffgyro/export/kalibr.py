"""Kalibr / OpenVINS / VINS ``imu.yaml`` from Allan-deviation read-outs.

Kalibr's IMU noise model (its wiki, "IMU Noise Model") takes continuous-time
densities, the IEEE Std 952 read-outs of ``diffgyro allan``:

* ``gyroscope_noise_density`` σ_g [rad/s/√Hz] = ARW N (Allan σ at τ = 1 s on
  the −½ line); per sample at ``update_rate`` f: σ_gd = σ_g·√f;
* ``gyroscope_random_walk`` σ_bg [rad/s²/√Hz] = RRW K (Allan σ at τ = 3 s on
  the +½ line); per sample: σ_bgd = σ_bg/√f;
* the accelerometer likewise in m/s²/√Hz and m/s³/√Hz.

One number per sensor: the largest of the three axes (the conservative choice
for a filter's noise). A read-out that no axis shows is an error, never a
guessed number; so is a missing accelerometer (Kalibr reads all four keys),
unless its two values are given. See docs/export.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..allan import STOP_RATIO, allan, default_m, sample_interval, to_json
from ..errors import DataError
from . import refuse_not_ok

__all__ = ["from_allan", "write", "ImuNoise", "allan_of", "NAME"]

NAME = "kalibr"
_KEYS = (("arw", "noise density"), ("rrw", "random walk"))


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time densities of one IMU (SI units) and its sampling rate."""

    device: str
    gyro_noise_density: float
    gyro_random_walk: float
    update_rate: float
    accel_noise_density: float | None = None
    accel_random_walk: float | None = None


def _worst(axes: dict, key: str, what: str, device: str, report: list[str],
           required: bool = True) -> float | None:
    vals = {name: ax.get(key) for name, ax in axes.items()}
    got = {k: float(v) for k, v in vals.items() if v is not None and math.isfinite(float(v))}
    if not got and not required:
        report.append(f"warning: device {device}: the Allan curves show no {key} ({what})")
        return None
    if not got:
        raise DataError(f"the Allan curves show no {key} ({what}) on any axis; Kalibr needs it",
                        device=device, hint="record the device static for longer "
                        "(the +1/2 line of a random walk appears at τ of minutes to hours)"
                        if key == "rrw" else "record the device static at its full rate")
    missing = sorted(set(vals) - set(got))
    if missing:
        report.append(f"warning: device {device}: no {key} on {', '.join(missing)}; "
                      f"{what} from {', '.join(sorted(got))}")
    return max(got.values())


def _rate(axes: dict, device: str) -> float:
    taus = [ax["tau"][0] for ax in axes.values() if ax.get("tau")]
    if not taus or not min(taus) > 0:
        raise DataError("the Allan curves have no τ to take the sampling rate from", device=device,
                        hint="pass --rate HZ")
    return 1.0 / min(taus)


def from_allan(doc: dict, device: str | None, rate: float | None,
               accel: dict | None = None, force: bool = False) -> tuple[ImuNoise, list[str]]:
    """Densities of one device from an ``allan --json`` object (gyro; ``accel``: the same
    object for the accelerometer, or None). A device whose read-outs are not a sensor's
    noise (status ``in_motion``) is refused unless ``force``; the report's first lines
    then say so.

    **Arguments:**

    - ``doc``: the gyro's ``allan --json`` object.
    - ``device``: the device (None: the only one).
    - ``rate``: the IMU's rate, Hz (default: from the object).
    - ``accel``: the accelerometer's ``allan --json`` object, or None.
    - ``force``: write a device whose read-outs are not a sensor's noise.
    """
    devs = doc.get("devices") if isinstance(doc, dict) else None
    if not isinstance(devs, list) or not devs or not all(
            isinstance(d, dict) and isinstance(d.get("axes"), dict) for d in devs):
        raise DataError("not an 'allan --json' object (devices[].axes)")
    names = [str(d.get("device")) for d in devs]
    if device is None and len(devs) > 1:
        raise DataError(f"the Allan read-outs hold {len(devs)} devices; imu.yaml is for one",
                        hint=f"choose one with --device ({', '.join(names[:10])})")
    if device is not None and device not in names:
        raise DataError(f"device {device!r} is not in the Allan read-outs",
                        hint=f"it has {', '.join(names[:10])}")
    pick = names.index(device) if device is not None else 0
    name, axes = names[pick], devs[pick]["axes"]

    report: list[str] = refuse_not_ok([(name, str(devs[pick].get("status", "ok")),
                                        str(devs[pick].get("status_detail", "")))], force)
    nd, rw = (_worst(axes, k, "gyroscope " + w, name, report) for k, w in _KEYS)
    acc = [None, None]
    if accel is not None:
        a_axes = accel["devices"][pick]["axes"]
        acc = [_worst(a_axes, k, "accelerometer " + w, name, report, required=False)
               for k, w in _KEYS]
    f = float(rate) if rate is not None else _rate(axes, name)
    return ImuNoise(name, nd, rw, f, acc[0], acc[1]), report


def allan_of(batch, which: str = "gyro", motion=None) -> dict:
    """``allan --json`` object of a batch's gyro, or of its accelerometer (m/s² for rad/s);
    with ``motion`` (:class:`diffgyro.motion.Motion`) a device that moved gets status
    ``in_motion``, one whose rest cannot be shown ``rest_unverified``.

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch`.
    - ``which``: ``"gyro"`` or ``"accel"``.
    - ``motion``: the batch's motion check, or None.
    """

    y = np.moveaxis(np.asarray(getattr(batch, which), np.float64), -1, 1)
    nv = np.asarray(batch.n_valid, np.int64)
    dt = np.array([sample_interval(batch.t[i], nv[i]) for i in range(batch.n_devices)])
    m = default_m(int(nv.max()), 10, STOP_RATIO)
    res = allan(y, dt[:, None], m, nv[:, None].repeat(3, axis=1))
    doc = to_json(res, batch.devices)
    if motion is not None:

        for i, dev in enumerate(doc["devices"]):
            if not motion.at_rest(i):
                dev["status"] = motion.status(i)
                dev["status_detail"] = motion.status_detail(i)
    return doc


def write(noise: ImuNoise, topic: str = "/imu0", notes: list[str] = ()) -> str:
    """The imu.yaml text (continuous-time values, SI units, comments name them).

    **Arguments:**

    - ``noise``: the densities (:func:`from_allan`).
    - ``topic``: the IMU's ROS topic.
    - ``notes``: comment lines.
    """
    if noise.accel_noise_density is None or noise.accel_random_walk is None:
        missing = [k for k, v in (("accelerometer_noise_density", noise.accel_noise_density),
                                  ("accelerometer_random_walk", noise.accel_random_walk))
                   if v is None]
        raise DataError(f"Kalibr's imu.yaml needs {' and '.join(missing)}, which these read-outs "
                        "do not give", device=noise.device, hint="an 'allan --json' file holds the "
                        "gyro only: export from a static recording with ax, ay, az columns long "
                        "enough to show the accelerometer's random walk, or pass "
                        "--accel-noise-density and --accel-random-walk (m/s²/√Hz, m/s³/√Hz, "
                        "e.g. from the datasheet)")
    f = noise.update_rate
    lines = [
        f"# IMU noise of device {noise.device} written by diffgyro export --format kalibr",
        "# continuous-time densities (IEEE Std 952 Allan read-outs); per sample at update_rate f:",
        f"#   gyro white noise {noise.gyro_noise_density * math.sqrt(f):.3e} rad/s (= density*sqrt(f)),",
        f"#   gyro bias step {noise.gyro_random_walk / math.sqrt(f):.3e} rad/s (= random walk/sqrt(f))",
        "#Accelerometers",
        f"accelerometer_noise_density: {noise.accel_noise_density:.6e}   # m/s^2/sqrt(Hz)",
        f"accelerometer_random_walk: {noise.accel_random_walk:.6e}   # m/s^3/sqrt(Hz)",
        "#Gyroscopes",
        f"gyroscope_noise_density: {noise.gyro_noise_density:.6e}   # rad/s/sqrt(Hz) (ARW)",
        f"gyroscope_random_walk: {noise.gyro_random_walk:.6e}   # rad/s^2/sqrt(Hz) (RRW)",
        f"rostopic: {topic}",
        f"update_rate: {f:.6g}   # Hz",
    ]
    lines[1:1] = [f"# {ln}" for ln in notes]
    return "\n".join(lines) + "\n"
