"""Are the loaded numbers plausible in the unit they were read in?

A signal whose unit nobody stated (no option, no unit in its header) is read
in SI: rad/s, m/s², °C, s. Numbers that only make sense in another unit are
caught here, from physics and data-sheet ranges, not from any simulator's
settings. The rule (docs/formats.md, "Units"):

* **refused** (:class:`DataError`, the option that passes it in the hint) when
  no instrument read in that unit could give the numbers: a gyro at rest
  biased by more than 1 rad/s (57 °/s) or noisier than 0.5 rad/s per sample, or
  rates beyond 100 rad/s (5700 °/s, over the full scale of MEMS and
  navigation gyros); an accelerometer at rest reading 0.8–1.25 (g) or
  800–1250 (mg) where gravity is 9.81 m/s²; a temperature held at 175–500 "°C"
  (kelvin; no IMU runs that hot); samples more than an hour apart.
* **warned** (numbers kept) when they are unusual but possible: a rest bias
  over 0.35 rad/s (20 °/s, the largest zero-rate offset of consumer MEMS data
  sheets), noise over 0.05 rad/s per sample or a noise density over 3·10⁻³
  rad/s/√Hz (0.17 °/s/√Hz, ten times a consumer MEMS gyro); an accelerometer
  at rest far from 9.81 m/s²; samples 60 s to an hour apart, or time steps
  of whole numbers of "seconds" (2, 5, 10 ... as ms ticks give) with which a
  gyro plausible in every other way has a noise density no gyro has.
* whole numbers (raw ADC counts, which the multi- and six-position recipes
  calibrate on purpose) are never refused: a refusal becomes a warning that
  says the numbers are kept as counts.

Rest is found without knowing the unit: the quietest windows of the
recording (a per-sample noise from first differences, so drifts and constant
rotation rates do not count as motion). Devices of fewer than
:data:`MIN_SAMPLES` samples are not checked (they say nothing of rest); long
recordings and large files are sampled (:data:`MAX_WINDOWS` windows per device,
:data:`MAX_DEVICES` devices per file) to keep the check's cost small.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..data import Recording
from ..errors import DataError
from ._reports import UnitNote
from ._units import UNIT_OPTION, UNITS

G0 = 9.80665  # standard gravity, m/s²
#: rad/s: beyond the full scale of any MEMS (≤ 4000 °/s) or navigation gyro.
RATE_PEAK = 100.0
#: rad/s at rest: (warn, refuse): 20 °/s, the largest consumer-MEMS zero-rate offset; 57 °/s.
REST_BIAS = (0.35, 1.0)
#: rad/s per sample at rest: (warn, refuse).
REST_NOISE = (0.05, 0.5)
#: rad/s/√Hz (σ·√dt): ten times the white noise of a consumer MEMS gyro (0.015 °/s/√Hz).
NOISE_DENSITY = 3e-3
#: |a| at rest read as m/s² that is gravity in g or in mg.
IN_G = (0.8, 1.25)
IN_MG = (800.0, 1250.0)
#: |a| at rest, m/s², that any accelerometer near the Earth's surface reads (warn outside).
REST_ACCEL = (7.0, 13.0)
#: °C: above this a temperature held throughout is kelvin (IMUs are rated to 125–175 °C).
HOT = 175.0
#: s between samples: (warn, refuse).
SLOW_STEP = (60.0, 3600.0)


@dataclass(frozen=True)
class _Finding:
    refuse: bool
    what: str            # the numbers, e.g. "a rest bias of 1.2 rad/s"


#: Samples a device needs to be checked: four windows of eight (fewer say nothing of rest).
MIN_SAMPLES = 32


#: Windows looked at per device, evenly spread (bounds the cost on long recordings).
MAX_WINDOWS = 512
#: Devices looked at per file, evenly spread (the file's verdict is their median).
MAX_DEVICES = 16


def _windows(x: np.ndarray) -> np.ndarray:
    """(channels, windows, w): non-overlapping windows of 8 to 64 samples (at most
    :data:`MAX_WINDOWS`, evenly spread), each channel contiguous (fast reductions)."""
    w = int(min(64, max(8, x.shape[0] // 64)))
    k = x.shape[0] // w
    win = x[: k * w].reshape(k, w, -1)
    if k > MAX_WINDOWS:
        win = win[np.linspace(0, k - 1, MAX_WINDOWS).astype(np.int64)]
    return np.ascontiguousarray(np.moveaxis(win, 2, 0))


def _rest(x: np.ndarray) -> tuple[float, np.ndarray]:
    """(per-sample noise σ, |mean| of each window at rest): σ is that of the first
    differences in the quietest tenth of the windows; windows within 3 σ of it are at
    rest or turning at a constant rate."""
    win = _windows(x)
    var = np.diff(win, axis=2).var(axis=2)                 # (channels, windows)
    sigma = np.sqrt(var.sum(axis=0) / (2 * win.shape[0]))  # per channel, per sample
    level = float(np.percentile(sigma, 10))
    quiet = sigma <= 3.0 * level if level > 0 else sigma <= level
    return level, np.sqrt((win[:, quiet].mean(axis=2) ** 2).sum(axis=0))


def _step(t: np.ndarray) -> float:
    """The median sample interval (of at most 10⁵ intervals, evenly spread)."""
    stride = max(1, (t.shape[0] - 1) // 100_000)
    return float(np.median((t[1:] - t[:-1])[::stride]))


def _whole(x: np.ndarray) -> bool:
    head = x[:2000]
    return bool(np.all(head == np.round(head)))


def _median(values) -> float:
    values = [v for v in values if np.isfinite(v)]
    return float(np.median(values)) if values else float("nan")


@dataclass(frozen=True)
class _GyroStats:
    """A file's gyro read as rad/s: medians over its devices."""

    noise: float    # per-sample σ at rest
    bias: float     # the 10th percentile of the rest windows' |mean| (not a constant turn)
    peak: float     # the 99th percentile of |ω| (a few spikes are not the unit's doing)
    step: float     # s between samples, as read

    @classmethod
    def of(cls, recs: Sequence[Recording], steps: list[float]) -> _GyroStats:
        rest = [_rest(r.gyro) for r in recs]
        return cls(noise=_median(s for s, _ in rest),
                   bias=_median(float(np.percentile(m, 10)) for _, m in rest),
                   peak=_median(math.sqrt(float(np.percentile(
                       np.einsum("ij,ij->i", r.gyro, r.gyro), 99, method="lower")))
                       for r in recs),
                   step=_median(steps))

    @property
    def density(self) -> float:
        """σ·√dt, rad/s/√Hz (nan for a time step no IMU has)."""
        return self.noise * math.sqrt(self.step) if 1e-5 <= self.step <= SLOW_STEP[0] \
            else float("nan")

    def plausible(self, k: float = 1.0, density: bool = True) -> bool:
        """Whether the numbers times ``k`` are plausible rad/s (the noise density too)."""
        return (self.peak * k <= RATE_PEAK and self.bias * k <= REST_BIAS[0]
                and self.noise * k <= REST_NOISE[0]
                and not (density and self.density * k > NOISE_DENSITY))


def _gyro(g: _GyroStats, time_ok: bool) -> tuple[list[_Finding], float]:
    """Findings on the gyro read as rad/s, and the factor to rad/s of a unit that fits
    (the noise density only where the time base is trusted, ``time_ok``)."""
    out = []
    if g.peak > RATE_PEAK:
        out.append(_Finding(True, f"rates up to {g.peak:.3g} rad/s"))
    if g.bias > REST_BIAS[0]:
        out.append(_Finding(g.bias > REST_BIAS[1], f"a rest bias of {g.bias:.3g} rad/s"))
    if g.noise > REST_NOISE[0]:
        out.append(_Finding(g.noise > REST_NOISE[1], f"a rest noise of {g.noise:.3g} rad/s"))
    elif time_ok and g.density > NOISE_DENSITY:
        out.append(_Finding(False, f"a noise density of {g.density:.3g} rad/s/√Hz (σ·√dt, "
                                   f"from {g.step:.3g} s between samples)"))
    factor = next((k for k in (math.pi / 180.0, math.pi / 180e3)
                   if g.plausible(k, density=time_ok)), float("nan"))
    return out, factor


def _accel(recs: Sequence[Recording]) -> tuple[list[_Finding], float]:
    mag = _median(float(np.median(_rest(r.accel)[1])) if r.accel is not None else float("nan")
                  for r in recs)
    if not np.isfinite(mag):
        return [], float("nan")
    if IN_G[0] <= mag <= IN_G[1]:
        return [_Finding(True, f"|a| = {mag:.4g} m/s² at rest (gravity is {G0} m/s²)")], G0
    if IN_MG[0] <= mag <= IN_MG[1]:
        return [_Finding(True, f"|a| = {mag:.4g} m/s² at rest (gravity is {G0} m/s²)")], G0 / 1e3
    if not REST_ACCEL[0] <= mag <= REST_ACCEL[1]:
        return [_Finding(False, f"|a| = {mag:.4g} m/s² at rest (gravity is {G0} m/s²)")], \
            float("nan")
    return [], float("nan")


def _temp(recs: Sequence[Recording]) -> list[_Finding]:
    temps = [r.temp for r in recs if r.temp is not None]
    if not temps:
        return []
    low = min(float(np.min(t)) for t in temps)
    if low > HOT:
        mid = _median(float(np.median(t[:: max(1, t.shape[0] // 100_000)])) for t in temps)
        return [_Finding(True, f"temperatures of {low:.4g} °C and above (median {mid:.4g} °C; "
                               f"{mid - 273.15:.3g} °C if kelvin)")]
    return []


def _time(steps: list[float], gyro: _GyroStats) -> list[_Finding]:
    """Samples too far apart; or whole-number steps of 2 s or more (ms ticks of a 500 Hz
    or slower clock) with which a gyro plausible in every other way has a noise density
    no gyro has: a clock 1000 times too slow (a slow logger in s keeps the density)."""
    step = _median(steps)
    if step > SLOW_STEP[0]:
        return [_Finding(step > SLOW_STEP[1], f"a median sample interval of {step:.4g} s")]
    if (step >= 2.0 and all(abs(m - round(m)) <= 1e-6 * m for m in steps)
            and gyro.density > NOISE_DENSITY and gyro.plausible(density=False)):
        return [_Finding(False, f"whole-number steps of {step:.6g} s (median), with which the "
                                f"gyro's noise density is {gyro.density:.3g} rad/s/√Hz, more "
                                f"than a gyro's ({gyro.density / math.sqrt(1e3):.3g} with ms)")]
    return []


_SI = {"gyro": "rad/s", "accel": "m/s²", "temp": "°C", "t": "s"}
_WHAT = {"gyro": "gyro", "accel": "accelerometer", "temp": "temperature", "t": "time"}


def _unit_for(sig: str, factor: float) -> str | None:
    for name, (scale, _) in UNITS[{"gyro": "rate", "accel": "accel"}[sig]].items():
        if math.isclose(scale, factor, rel_tol=1e-12):
            return {"mdeg/s": "mdps"}.get(name, name)
    return None


def check_plausible(recs: Sequence[Recording], file: str, assumed: set[str],
                    columns: dict[str, str]) -> list[UnitNote]:
    """Warnings on the signals of one file read in an assumed SI unit (``assumed``:
    ``"gyro"``, ``"accel"``, ``"temp"``, ``"t"``); a refusal raises :class:`DataError`
    naming the file, the column (``columns``: signal -> how messages name it) and the
    option that passes it.

    **Arguments:**

    - ``recs``: the file's recordings.
    - ``file``: the file's name, as messages give it.
    - ``assumed``: the signals read in an assumed SI unit.
    - ``columns``: signal -> how messages name its column.
    """
    recs = [r for r in recs if r.n >= MIN_SAMPLES]
    if not recs or not assumed & set(columns):
        return []
    if len(recs) > MAX_DEVICES:
        recs = [recs[int(i)] for i in np.linspace(0, len(recs) - 1, MAX_DEVICES)]
    steps = [_step(r.t) for r in recs]
    gyro = _GyroStats.of(recs, steps)
    notes, refused = [], []
    time_found = _time(steps, gyro) if "t" in assumed and "t" in columns else []
    for sig in ("t", "gyro", "accel", "temp"):
        if sig not in assumed or sig not in columns:
            continue
        factor = float("nan")
        if sig == "gyro":
            found, factor = _gyro(gyro, time_ok=not time_found)
        elif sig == "accel":
            found, factor = _accel(recs)
        elif sig == "temp":
            found = _temp(recs)
        else:
            found = time_found
        if not found:
            continue
        judged = _judge(sig, found, factor, recs, _median(steps), file, columns[sig])
        (notes if isinstance(judged, UnitNote) else refused).append(judged)
    if refused:  # every refused signal in one line, the first one's column named
        raise DataError("; ".join([refused[0].problem] + [f"column {r.column}: {r.problem}"
                                                          for r in refused[1:]]), file=file,
                        column=refused[0].column,
                        hint="give " + " and ".join(r.suggest for r in refused) + ", or "
                             + " and ".join(r.keep for r in refused)
                             + (" if the numbers really are in that unit" if len(refused) == 1
                                else " if the numbers really are in those units"))
    return notes


@dataclass(frozen=True)
class _Refusal:
    column: str
    problem: str
    suggest: str   # the option that fits the numbers, e.g. "--gyro-unit deg/s"
    keep: str      # the option that keeps them, e.g. "--gyro-unit rad/s"


def _judge(sig: str, found: list[_Finding], factor: float, recs, step: float, file: str,
           column: str) -> UnitNote | _Refusal:
    opt, si = UNIT_OPTION[sig], _SI[sig]
    what = ", ".join(f.what for f in found)
    unit = _unit_for(sig, factor) if np.isfinite(factor) else None
    if sig == "temp":
        unit = "K"
    elif sig == "t":  # ms ticks; beyond an hour, µs (a µs tick of an hour is 3.6 ms)
        unit = "ms" if step < SLOW_STEP[0] else "us" if step > SLOW_STEP[1] else "ms (or us)"
    counts = sig in ("gyro", "accel") and all(
        _whole(getattr(r, sig)) for r in recs)
    problem = f"{_WHAT[sig]} read as {si} gives {what}"
    if counts:
        return UnitNote(file, sig, "warning",
                        f"{column}: {problem}; the values are whole numbers (raw counts?), "
                        f"kept as they are (give {opt} if they are in a unit)")
    suggest = f"{opt} {unit}" if unit else f"{opt} with the unit of the file"
    if any(f.refuse for f in found):
        return _Refusal(column, f"{problem}: not plausible in {si}", suggest, f"{opt} {si}")
    plausible = f"plausible in {unit}: " if unit else ""
    return UnitNote(file, sig, "warning",
                    f"{column}: {problem}; {plausible}give {suggest}, or {opt} {si} to keep "
                    f"these numbers without this warning")
