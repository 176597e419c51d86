"""The ``allan --json`` object of an :class:`~diffgyro.allan.AllanResult`: null where a
read-out is not shown, and why."""

from __future__ import annotations

import numpy as np

from .._jsonio import number
from ._curves import AllanResult


def to_json(result: AllanResult, devices, axes=("gx", "gy", "gz")) -> dict:
    """The ``allan --json`` object (NaN becomes null, and the axis' ``missing``
    says why; τ only where defined).

    **Arguments:**

    - ``result``: the :class:`AllanResult` (leading axes: devices, axes).
    - ``devices``: the devices' names.
    - ``axes``: the axes' labels.
    """
    tau = np.asarray(result.tau)
    adev = np.asarray(result.adev)
    ro = result.readouts
    arw, bi, rrw = (np.asarray(v) for v in (ro.arw, ro.bias_instability, ro.rrw))
    out = []
    for d, dev in enumerate(devices):
        ax = {}
        for a, name in enumerate(axes):
            keep = np.isfinite(adev[d, a])
            ax[name] = {
                "tau": [float(v) for v in tau[d, a][keep]],
                "adev": [float(v) for v in adev[d, a][keep]],
                "arw": number(arw[d, a]),
                "bias_instability": number(bi[d, a]),
                "rrw": number(rrw[d, a]),
            }
            missing = {k: _MISSING[k] if keep.any() else "no τ with a defined Allan deviation "
                       "(too few valid samples)" for k in _MISSING if ax[name][k] is None}
            if missing:  # why a read-out is null, in plain words
                ax[name]["missing"] = missing
        out.append({"device": dev, "axes": ax})
    return {"devices": out}


#: Why a read-out is null (the curve does not show its term; see the module notes).
_MISSING = {
    "arw": "the curve shows no white-noise (-1/2 slope) region at the measured τ",
    "bias_instability": "the curve shows no flat (slope 0) floor at the measured τ",
    "rrw": "the curve shows no rate-random-walk (+1/2 slope) region at the measured τ "
           "(a longer static recording may)",
}
