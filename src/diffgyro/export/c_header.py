"""A C header for firmware: one device's coefficients and an inline compensation function.

The function is the formula of :mod:`diffgyro.apply` for the terms that act
sample by sample and linearly in the true rate Ω, so that it is exact in one
3×3 solve::

    T'     = clamp(T, T_lo, T_hi),   Ts = (T' − centre) / scale
    gyro   = A(Ts) · Ω + o(Ts, a, T_ext)
    A      = I + diag(Σ_j s_ij Ts^j) + misalignment (x: y, z; y: x, z; z: x, y)
    o_i    = Σ_j c_ij Ts^j + g_i · a + d_i · (T' − T_ext)
    Ω      = A⁻¹ (gyro − o)

(``bias_poly``, ``scale_poly``, ``misalignment``, ``g_sens``, ``temp_diff``).
Terms that need a history (``gradient``, ``hysteresis``, ``thermal_lag``,
``warmup``) or are nonlinear in Ω (``scale_asym``, ``scale_nonlin``) are refused.
Coefficients are written as double literals that read back to the same double.
"""

from __future__ import annotations

import re

from ..calibration import Calibration
from ..errors import DataError

__all__ = ["write", "SUPPORTED", "NAME"]

NAME = "c-header"
SUPPORTED = ("bias_poly", "scale_poly", "misalignment", "g_sens", "temp_diff")


def _ident(device: str) -> str:
    s = re.sub(r"[^0-9a-zA-Z]+", "_", device).strip("_").lower() or "device"
    return "diffgyro_" + s


def _term_code(term, start: int) -> list[str]:
    """C statements (inside the loop over axis i) for one term's columns from ``start``."""
    b = f"beta[i][{start}"
    if term.name in ("bias_poly", "scale_poly"):
        target = "o[i]" if term.name == "bias_poly" else "A[i][i]"
        return ["p = 1.0;",
                f"for (j = 0; j <= {term.order}; j++) {{ {target} += beta[i][{start} + j] * p; "
                f"p *= ts; }}"]
    if term.name == "misalignment":
        return [f"A[i][others[i][0]] += {b}];", f"A[i][others[i][1]] += {b} + 1];"]
    if term.name == "g_sens":
        return [f"o[i] += {b}] * accel[0] + {b} + 1] * accel[1] + {b} + 2] * accel[2];"]
    return [f"o[i] += {b}] * (t - temp_ext);"]   # temp_diff


def _check(cal: Calibration, device: str) -> list:
    terms = cal.model_info.terms
    for t in terms:
        if t.name not in SUPPORTED:
            raise DataError(f"term {t.spec} cannot be written as a c-header: the header implements "
                            f"{', '.join(SUPPORTED)} (sample-wise, linear in the rate)",
                            device=device, hint="refit without it, or apply it with diffgyro.apply")
    dev = cal.device(device)
    if dev.status != "ok":
        raise DataError(f"calibration has status {dev.status}; refusing to export it", device=device)
    return terms


def _literal(x: float) -> str:
    return repr(float(x))


def write(cal: Calibration, device: str) -> str:
    """The header's text for one device of ``cal``.

    **Arguments:**

    - ``cal``: the :class:`~diffgyro.calibration.Calibration`.
    - ``device``: the device written.
    """
    terms = _check(cal, device)
    dev = cal.device(device)
    need = cal.model_info.requires()
    ident = _ident(device)
    guard = ident.upper() + "_H"
    p = len(dev.beta[0])
    args = (["double temp"] if "temp" in need else []) + (
        ["double temp_ext"] if "temp_ext" in need else []) + (
        ["const double accel[3]"] if "accel" in need else [])
    lo, hi = dev.temp_range or (None, None)
    clamp = ("t = temp;" if lo is None else
             f"t = temp < {_literal(lo)} ? {_literal(lo)} : (temp > {_literal(hi)} ? "
             f"{_literal(hi)} : temp);")
    body, start = [], 0
    for t in terms:
        body += ["        " + line for line in _term_code(t, start)]
        start += t.n_params
    rows = ",\n".join("    {" + ", ".join(_literal(x) for x in row) + "}" for row in dev.beta)
    temp_lines = ([f"    {clamp}", f"    ts = (t - {_literal(dev.temp_centre)}) / "
                   f"{_literal(dev.temp_scale)};"] if "temp" in need else
                  ["    (void)t;"])
    return "\n".join([
        f"/* diffgyro calibration of device {device!r} (model {cal.model}), written by"
        .replace("*/", "* /"),
        " * diffgyro export --format c-header. Rates in rad/s, temperatures in °C,",
        " * specific force in m/s². Formula: docs/export.md and diffgyro/apply.py. */",
        f"#ifndef {guard}", f"#define {guard}", "",
        f"static const double {ident}_beta[3][{p}] = {{", rows, "};", "",
        "/* True rate omega from measured gyro: solves gyro = A(Ts) omega + o for omega. */",
        f"static inline void {ident}_compensate({', '.join(args + ['const double gyro[3]', 'double omega[3]'])})",
        "{",
        f"    const double (*beta)[{p}] = {ident}_beta;",
        "    static const int others[3][2] = {{1, 2}, {0, 2}, {0, 1}};",
        "    double A[3][3] = {{1.0, 0.0, 0.0}, {0.0, 1.0, 0.0}, {0.0, 0.0, 1.0}};",
        "    double o[3] = {0.0, 0.0, 0.0}, r[3], det, t = 0.0, ts = 0.0, p;",
        "    int i, j;",
        *temp_lines,
        "    (void)others; (void)p; (void)j; (void)ts;",
        "    for (i = 0; i < 3; i++) {", *body, "    }",
        "    for (i = 0; i < 3; i++) r[i] = gyro[i] - o[i];",
        "    det = A[0][0] * (A[1][1] * A[2][2] - A[1][2] * A[2][1])",
        "        - A[0][1] * (A[1][0] * A[2][2] - A[1][2] * A[2][0])",
        "        + A[0][2] * (A[1][0] * A[2][1] - A[1][1] * A[2][0]);",
        "    omega[0] = (r[0] * (A[1][1] * A[2][2] - A[1][2] * A[2][1])",
        "        - A[0][1] * (r[1] * A[2][2] - A[1][2] * r[2])",
        "        + A[0][2] * (r[1] * A[2][1] - A[1][1] * r[2])) / det;",
        "    omega[1] = (A[0][0] * (r[1] * A[2][2] - A[1][2] * r[2])",
        "        - r[0] * (A[1][0] * A[2][2] - A[1][2] * A[2][0])",
        "        + A[0][2] * (A[1][0] * r[2] - r[1] * A[2][0])) / det;",
        "    omega[2] = (A[0][0] * (A[1][1] * r[2] - r[1] * A[2][1])",
        "        - A[0][1] * (A[1][0] * r[2] - r[1] * A[2][0])",
        "        + r[0] * (A[1][0] * A[2][1] - A[1][1] * A[2][0])) / det;",
        "}", "", f"#endif /* {guard} */", ""])
