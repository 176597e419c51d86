"""Figures a limit may ask for that a device record does not hold by default.

* ``allan``: the Allan read-outs of the fit *residual* (the sensor's noise once the
  model is removed), per axis and the worst axis: ``arw`` (rad/s/√Hz),
  ``bias_instability`` (rad/s), ``rrw`` (rad/s²/√Hz), from
  :func:`diffgyro.allan.allan` (IEEE 952 read-outs, ``method="fit"``). A read-out
  the curve does not show is null (the record of the axis says why).
* ``bias_range``: the largest |bias| over the device's calibrated temperature range,
  per axis and worst (rad/s), from the ``bias_poly`` coefficients: a datasheet's
  zero-rate offset over temperature.
* ``bias_tempco``: the largest |d bias / dT| over that range (rad/s/K): the
  datasheet's zero-rate offset temperature coefficient.
* ``temp_range``: ``min``, ``max`` and ``span`` of the temperatures the device was
  calibrated over (°C): the range check of a thermal test.

The first three groups hold ``x``, ``y``, ``z`` and ``worst`` (the largest over the axes that
have a value; null when none has).
"""

from __future__ import annotations

import math

import numpy as np

from .._jsonio import number
from ..allan import allan, sample_interval

AXES = ("x", "y", "z")
#: Points of the temperature range the bias polynomial is evaluated on.
TEMP_POINTS = 201


def _group(per_axis: dict[str, dict | float | None], key: str | None = None) -> float | None:
    vals = [(v.get(key) if key else v) for v in per_axis.values()]
    vals = [float(v) for v in vals if v is not None and math.isfinite(float(v))]
    return max(vals) if vals else None


def residual_allan(residuals: np.ndarray, t: np.ndarray, n_valid: np.ndarray) -> list[dict]:
    """The ``allan`` group of every device from its fit residual ``(devices, n, 3)`` (padding
    after ``n_valid``), time stamps ``t`` (devices, n) in s.

    **Arguments:**

    - ``residuals``: the fit residuals (devices, n, 3), rad/s.
    - ``t``: sample times (devices, n), s.
    - ``n_valid``: each device's valid samples.
    """

    res = np.asarray(residuals, np.float64)
    n_dev = res.shape[0]
    nv = np.asarray(n_valid, np.int64)
    dt = np.array([sample_interval(t[i], nv[i]) for i in range(n_dev)])
    y = np.nan_to_num(np.moveaxis(res, -1, 1))  # (d, 3, n)
    out = allan(y, dt[:, None], None, np.repeat(nv[:, None], 3, axis=1), per_decade=8)
    ro = out.readouts
    groups = []
    for i in range(n_dev):
        axes = {ax: {"arw": number(ro.arw[i, a]), "bias_instability": number(ro.bias_instability[i, a]),
                     "rrw": number(ro.rrw[i, a])} for a, ax in enumerate(AXES)}
        groups.append({**{k: _group(axes, k) for k in ("arw", "bias_instability", "rrw")}, **axes})
    return groups


def bias_figures(params: dict | None, centre: float | None, scale: float | None,
                 temp_range) -> dict:
    """``bias_range`` and ``bias_tempco`` of one device from its labelled coefficients
    (``params`` as ``fit --json`` writes them) and temperature normalisation.

    **Arguments:**

    - ``params``: the device's labelled coefficients (None: not fitted).
    - ``centre``: their temperature centre, °C.
    - ``scale``: their temperature half-range, °C.
    - ``temp_range``: the device's temperature span, °C.
    """
    empty = {"bias_range": dict.fromkeys((*AXES, "worst")),
             "bias_tempco": dict.fromkeys((*AXES, "worst"))}
    if not params:
        return empty
    rng = None if temp_range is None else [float(v) for v in temp_range]
    ok_temp = (rng is not None and all(math.isfinite(v) for v in rng) and centre is not None
               and scale is not None and math.isfinite(centre) and math.isfinite(scale)
               and scale > 0)
    ts = (np.linspace(rng[0], rng[1], TEMP_POINTS) - centre) / scale if ok_temp else None
    brange, slope = {}, {}
    for ax in AXES:
        coeffs = _bias_coeffs(params.get(ax) or {})
        if coeffs is None or any(c is None for c in coeffs):
            brange[ax] = slope[ax] = None
            continue
        c = np.asarray(coeffs, float)
        if len(c) == 1:  # a constant bias: no temperature needed, no temperature coefficient
            brange[ax], slope[ax] = abs(float(c[0])), (0.0 if ok_temp else None)
            continue
        if ts is None:
            brange[ax] = slope[ax] = None
            continue
        poly = np.polynomial.polynomial
        brange[ax] = float(np.max(np.abs(poly.polyval(ts, c))))
        slope[ax] = float(np.max(np.abs(poly.polyval(ts, poly.polyder(c))))) / scale
    return {"bias_range": {**brange, "worst": _group(brange)},
            "bias_tempco": {**slope, "worst": _group(slope)}}


def _bias_coeffs(axis_params: dict) -> list | None:
    """c0..ck of the model's ``bias_poly(k)`` term on one axis, or None without one."""
    for label in axis_params:
        if label.startswith("bias_poly(") and label.endswith(".c0"):
            term = label[: -len(".c0")]
            k = int(term[len("bias_poly("):-1])
            return [axis_params.get(f"{term}.c{j}") for j in range(k + 1)]
    return None


def add_figures(record: dict, wanted, *, allan: dict | None = None, centre=None, scale=None,
                temp_range=None) -> dict:
    """``record`` with the computed groups in ``wanted`` added (``allan``: the device's
    :func:`residual_allan` group, None where it has none).

    **Arguments:**

    - ``record``: the device's record.
    - ``wanted``: the groups of figures the limits read.
    - ``allan``: the device's Allan figures, where computed.
    - ``centre``: the temperature centre of its coefficients, °C.
    - ``scale``: their temperature half-range, °C.
    - ``temp_range``: the device's temperature span, °C.
    """
    out = dict(record)
    if "allan" in wanted:
        out["allan"] = allan if allan is not None else {
            **dict.fromkeys(("arw", "bias_instability", "rrw")),
            **{ax: dict.fromkeys(("arw", "bias_instability", "rrw")) for ax in AXES}}
    if "temp_range" in wanted:
        lo, hi = (None, None) if temp_range is None else (number(temp_range[0]), number(temp_range[1]))
        out["temp_range"] = {"min": lo, "max": hi,
                             "span": None if lo is None or hi is None else hi - lo}
    if wanted & {"bias_range", "bias_tempco"}:
        figs = bias_figures(record.get("params"), centre, scale, temp_range)
        for k in ("bias_range", "bias_tempco"):
            if k in wanted:
                out[k] = figs[k]
    return out
