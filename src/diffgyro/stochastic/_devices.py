"""Noise models of many devices' three gyro axes, as the ``noise --json`` entries.

One entry per device (``device``, ``status``, ``status_detail``, ``interval_level``,
``sample_interval``, ``axes``: x, y, z each with ``structure``, ``components``,
``rejected``, ``resolution``; :mod:`.resolution`). Any
(devices, samples, 3) rates serve: a batch's gyro (``diffgyro noise``) or the
residuals of a calibrated model (``Diagnosis.residuals``, padding zeroed, with the
batch's ``n_valid`` and ``t``), whose noise is what a filter must carry.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable

import numpy as np

from ..allan import sample_interval
from ._block_likelihood import PENALTY as SLOW_PENALTY
from ._identify import identify, load_ahead
from ._resolution import INTERVAL_LEVEL
from ._selection import PENALTY, catalogue

AXES = ("x", "y", "z")
#: Fewest samples for a model: 64 give 5 dyadic scales, enough for two or three parameters.
MIN_SAMPLES = 64


def axis_entry(res, *idx) -> dict:
    """One axis of a ``noise --json`` entry: the structure as reported (``fitted_structure``
    too where a process the sampling cannot resolve was merged into the white part), the
    components, the rejected candidates and what the record resolves."""
    out = {"structure": list(res.reported_structure(*idx))}
    if out["structure"] != list(res.structure(*idx)):
        out["fitted_structure"] = list(res.structure(*idx))
    out.update(components=res.components(*idx), rejected=res.rejected(*idx),
               resolution=res.resolution(*idx))
    return out


def identify_devices(values, n_valid, t, devices, *, motion=None, max_gm: int = 2,
                     penalty: float | None = None, progress=None, slow_part: bool = False):
    """(entries, {device index: (NoiseModels, row)}) for rates ``values`` (d, n, 3) in rad/s.

    ``motion``: per device None (static) or a one-line status detail saying why not
    (``in_motion: ...`` or ``rest_unverified: ...``: that status, no axes). Devices of equal length are identified together.
    ``progress`` is called with a line of text before each group of devices.

    **Arguments:**

    - ``values``: the rates (d, n, 3), rad/s.
    - ``n_valid``: each device's valid samples (d,).
    - ``t``: sample times (d, n), s.
    - ``devices``: the devices' names.
    - ``motion``: per device None (at rest) or why not, as above.
    - ``max_gm``: Gauss–Markov processes per structure at most.
    - ``penalty``: the criterion's factor per parameter (default:
      :data:`~.selection.PENALTY`).
    - ``progress``: called with a line of text before each group of devices.
    - ``slow_part``: choose the slow components again by the block means' exact likelihood
      (:func:`~.identify.identify`'s step 5).
    """

    pen = PENALTY if penalty is None else penalty
    motion = [None] * len(devices) if motion is None else motion
    entries, models, groups = [], {}, {}
    for i, dev in enumerate(devices):
        n = int(n_valid[i])
        entry = {"device": dev, "status": "ok", "status_detail": "ok",
                 "interval_level": INTERVAL_LEVEL, "axes": None}
        entries.append(entry)
        rates = np.asarray(values[i, :n], np.float64)
        if n < MIN_SAMPLES:  # the most basic problem first
            entry.update(status="too_short", status_detail=f"{n} samples; a noise model needs at "
                         f"least {MIN_SAMPLES} (static, at the full rate)")
        elif motion[i] is not None:
            entry.update(status=str(motion[i]).split(":", 1)[0], status_detail=str(motion[i]))
        elif not np.all(np.isfinite(rates)):
            entry.update(status="bad_data", status_detail="non-finite gyro samples")
        elif np.any(np.ptp(rates, axis=0) == 0):
            flat = ", ".join(ax for ax, p in zip(("gx", "gy", "gz"), np.ptp(rates, axis=0)) if p == 0)
            entry.update(status="bad_data", status_detail=f"constant {flat}: no noise to model")
        else:
            dt = sample_interval(np.asarray(t[i]), n)
            if not (math.isfinite(dt) and dt > 0):
                entry.update(status="bad_data", status_detail="no sampling interval")
            else:
                entry["sample_interval"] = dt
                groups.setdefault(n, []).append((i, dt))
    done, total = 0, sum(len(m) for m in groups.values())
    for n, members in groups.items():  # devices of one length identified together
        idx = [i for i, _ in members]
        if progress is not None:
            progress(f"identifying the noise models of devices {done + 1}-{done + len(idx)} "
                     f"of {total}")
        done += len(idx)
        y = np.stack([np.asarray(values[i, :n], np.float64).T for i in idx])  # (d, 3, n)
        dts = np.array([[dt] * 3 for _, dt in members])
        res = identify(y, dts, structures=catalogue(max_gm), penalty=pen,
                       slow_penalty=SLOW_PENALTY if slow_part else None)
        for j, i in enumerate(idx):
            models[i] = (res, j)
            entries[i]["axes"] = {ax: axis_entry(res, j, a) for a, ax in enumerate(AXES)}
    return entries, models


def identify_ahead(n_valid, max_gm: int = 2) -> Callable[[], None]:
    """Start loading the programs :func:`identify_devices` of devices with ``n_valid``
    samples each will run (every device long enough taken to be at rest, as most are):
    each group's program lowered here and read or compiled on a thread of its own
    (:func:`~.identify.load_ahead`), while the caller checks the devices for motion.
    Returns a function that waits for them; call it before :func:`identify_devices`.
    A device the checks then leave out only leaves a program loaded for nothing.

    **Arguments:**

    - ``n_valid``: each device's valid samples (d,).
    - ``max_gm``: Gauss–Markov processes per structure at most, as for
      :func:`identify_devices`.
    """
    lengths = Counter(int(n) for n in np.asarray(n_valid) if int(n) >= MIN_SAMPLES)
    threads = [t for n, d in lengths.items()
               for t in load_ahead(len(AXES) * d, n, catalogue(max_gm), lead=(d, len(AXES)))]

    def wait() -> None:
        for thread in threads:
            thread.join()

    return wait
