"""Why one device's data cannot support a candidate term (its ``skipped`` reason): the
device's own numbers for the signals the term reads (its temperature span, peak |dT/dt|,
whether it both heated and cooled, its peak true rate per axis, the spread of its
specific force, of temp − temp_ext, of an extra column), then what the term needs (its
``range_need``): "temperature spans only 0.3 °C (20.0 to 20.3 °C): bias_poly(2) needs a
temperature span of at least 2 °C"."""

from __future__ import annotations

import numpy as np

from ..data import AUX_PREFIX, Recording


def _range(x) -> tuple[float, float] | None:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    return (float(x.min()), float(x.max())) if x.size else None


def _axes(values, unit: str, names: str) -> str:
    return ", ".join(f"{v:.3g}" for v in values) + f" {unit} on {names}"


def _temperature(rec: Recording, name: str, need: float, dtemp, heating) -> list[str]:
    span = _range(rec.temp)
    if span is None:
        return ["no valid temperature sample"]
    lo, hi = span
    only = "only " if hi - lo < need else ""
    span_fact = (f"temperature constant at {lo:.1f} °C" if hi == lo else
                 f"temperature spans {only}{hi - lo:.3g} °C ({lo:.1f} to {hi:.1f} °C)")
    if name == "gradient" and dtemp is not None and np.isfinite(dtemp).any():
        return [f"|dT/dt| peaks at {60.0 * float(np.nanmax(np.abs(dtemp))):.3g} °C/min"]
    if name == "hysteresis" and heating is not None:
        h = np.asarray(heating, float)
        up, down = bool(np.any(h > 0)), bool(np.any(h < 0))
        return ["it only heats" if up and not down else "it only cools" if down and not up
                else "it neither heats nor cools (|dT/dt| under 0.05 °C/min)"]
    return [span_fact]


def _rate(rec: Recording, name: str) -> str:
    rate = np.where(np.isfinite(rec.rate), rec.rate, np.nan)
    if not np.isfinite(rate).any():
        return "no valid true rate (rx, ry, rz) sample"
    if name == "scale_asym":  # both signs on every axis
        both = np.minimum(np.nanmax(rate, axis=0), np.nanmax(-rate, axis=0))
        return "true rate of both signs reaches " + _axes(np.maximum(both, 0.0), "rad/s", "rx, ry, rz")
    return "true rate peaks at " + _axes(np.nanmax(np.abs(rate), axis=0), "rad/s", "rx, ry, rz")


def facts(term, rec: Recording, dtemp=None, heating=None) -> list[str]:
    """The device's numbers for the signals ``term`` reads (``dtemp`` in °C/s and
    ``heating`` (+1/−1/0) as the diagnosis computed them, where it did)."""
    reads = term.requires()
    name = getattr(term, "name", "")
    out: list[str] = []
    if "temp" in reads and rec.temp is not None:
        out += _temperature(rec, name, float(term.min_temp_span), dtemp, heating)
    if "rate" in reads and rec.rate is not None:
        out.append(_rate(rec, name))
    if "accel" in reads and rec.accel is not None:
        acc = np.where(np.isfinite(rec.accel), rec.accel, np.nan)
        if np.isfinite(acc).any():
            spread = np.nanmax(acc, axis=0) - np.nanmin(acc, axis=0)
            out.append("specific force varies by " + _axes(spread, "m/s²", "ax, ay, az"))
    if "temp_ext" in reads and rec.temp is not None and rec.temp_ext is not None:
        span = _range(np.asarray(rec.temp, float) - np.asarray(rec.temp_ext, float))
        if span is not None:
            out.append(f"temp − temp_ext varies by {span[1] - span[0]:.3g} °C")
    for key in sorted(r for r in reads if r.startswith(AUX_PREFIX)):
        col = key[len(AUX_PREFIX):]
        span = _range(rec.aux[col]) if col in rec.aux else None
        out.append(f"column {col!r} " + ("not logged" if col not in rec.aux else
                                          "has no valid sample" if span is None else
                                          f"constant at {span[0]:.4g}" if span[0] == span[1] else
                                          f"spans {span[0]:.4g} to {span[1]:.4g}"))
    return out


def reason(term, rec: Recording, dtemp=None, heating=None) -> str:
    """This device's ``skipped`` reason for ``term``: its numbers, then what the term needs."""
    found = "; ".join(facts(term, rec, dtemp, heating))
    need = f"{term.spec} needs {term.range_need()}"
    return f"{found}: {need}" if found else need
