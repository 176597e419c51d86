"""Evidence (what the residual follows) and the explanation in words."""

from __future__ import annotations

import math

import numpy as np

from ..data import Recording, aux_key
from ..effects import parse_term, registry
from ._candidates import term_column
from ._results import DeviceDiagnosis
from ._thresholds import family_of


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float(np.dot(a, a)) * float(np.dot(b, b)))
    return float(np.dot(a, b) / den) if den > 0 else 0.0


#: Evidence signals no built-in term is linear in (products of signals): a residual that
#: follows one of them is an effect outside the vocabulary, not a random walk.
OUTSIDE = ("temp_dtemp", "dtemp2")


def evidence(residual: np.ndarray, rec: Recording, sig_dev: dict,
             floor_axes: np.ndarray | None = None) -> dict:
    """What the residual follows: correlations a person can check in the figures.

    ``residual`` (n, 3) of the base model; ``sig_dev`` the device's derived
    signals as numpy (dtemp, heating). Per signal: the largest |r| over the
    axes, its axis, and where helpful the residual's mean in two regimes. With
    the white-noise level per axis ``floor_axes``, each signal also gets
    ``explains``: the share of the residual's variance above that level a
    straight line in the signal explains on that axis (r² · var / (var − σ²)).

    **Arguments:**

    - ``residual``: the base model's residual (n, 3), rad/s.
    - ``rec``: the device's :class:`~diffgyro.data.Recording`.
    - ``sig_dev``: the device's derived signals as numpy (``dtemp``, ``heating``).
    - ``floor_axes``: the white-noise level per axis (3,); adds ``explains`` to each signal.
    """
    e = residual
    axes = [np.ascontiguousarray(e[:, i], float) for i in range(3)]  # a column's dot is strided
    out: dict = {}

    def add(name, s, per_axis=False, label=None):
        s = np.asarray(s, float)
        if s.ndim == 1 and (not np.all(np.isfinite(s)) or np.std(s) == 0):
            return
        rs = [_corr(axes[i], np.ascontiguousarray(s[:, i]) if per_axis else s) for i in range(3)]
        i = int(np.argmax(np.abs(rs)))
        out[name] = {"r": round(rs[i], 3), "axis": "xyz"[i], "label": label or name}
        if floor_axes is not None:
            var = float(np.var(axes[i]))
            gap = var - float(floor_axes[i]) ** 2
            out[name]["explains"] = round(min(rs[i] ** 2 * var / gap, 1.0), 3) if gap > 0 else 0.0

    t = rec.t - rec.t[0]
    add("time", t, label="time since start")
    add("early", np.exp(-t / max(t[-1] / 20.0, 1.0)), label="the first minutes after power-on")
    if rec.temp is not None:
        add("temp", rec.temp, label="temperature")
        dtemp = sig_dev.get("dtemp")
        if dtemp is not None:
            add("dtemp", dtemp, label="dT/dt")
            tc = rec.temp - np.mean(rec.temp)
            add("temp_dtemp", tc * dtemp, label="T·dT/dt (T centred)")
            add("dtemp2", dtemp**2, label="(dT/dt)²")
        heat = sig_dev.get("heating")
        if heat is not None and np.any(heat > 0) and np.any(heat < 0):
            add("heating", heat, label="heating vs cooling")
            up, down = heat > 0, heat < 0
            i = int(np.argmax(np.abs(e[up].mean(0) - e[down].mean(0))))
            out["heating"]["mean_heating"] = float(e[up, i].mean())
            out["heating"]["mean_cooling"] = float(e[down, i].mean())
        if rec.temp_ext is not None:
            add("temp_diff", rec.temp - rec.temp_ext, label="temp − temp_ext")
    if rec.rate is not None and np.max(np.abs(rec.rate)) > 1e-3:
        add("rate", rec.rate, per_axis=True, label="input rate")
        add("abs_rate", np.abs(rec.rate), per_axis=True, label="|input rate|")
        add("rate3", rec.rate**3, per_axis=True, label="rate³")
        out.update(_rate_regimes(e, rec.rate))
    if rec.accel is not None and np.ptp(rec.accel, axis=0).max() > 1.0:
        out["accel"] = _accel_fit(e, rec.accel)
    for name, x in rec.aux.items():  # extra logged columns, as aux:NAME
        key = aux_key(name)
        add(key, x, label=f"`{name}`")
        if key in out:  # any function of the column, not only a line
            etas = _eta(e, np.asarray(x, float))
            i = int(np.argmax(etas))
            out[key].update(eta=round(float(etas[i]), 3), eta_axis="xyz"[i])
    return out


def _rate_regimes(e: np.ndarray, rate: np.ndarray) -> dict:
    """The other axes' rate the residual follows most (cross_rate), and the residual's RMS
    above and below the median |rate| of the moving samples."""
    out: dict = {}
    cross = [(abs(_corr(e[:, i], rate[:, j])), _corr(e[:, i], rate[:, j]), i, j)
             for i in range(3) for j in range(3) if i != j and np.std(rate[:, j]) > 0]
    if cross:
        _, r, i, j = max(cross)
        out["cross_rate"] = {"r": round(r, 3), "axis": "xyz"[i],
                             "label": f"the {'xyz'[j]} input rate"}
    moving = np.abs(rate) > 1e-3
    if np.any(moving):
        hi = np.abs(rate) > np.median(np.abs(rate[moving]))
        out["high_rate_rms"] = float(np.sqrt(np.mean(e[hi] ** 2))) if hi.any() else None
        out["low_rate_rms"] = float(np.sqrt(np.mean(e[~hi] ** 2))) if (~hi).any() else None
    return out


def _accel_fit(e: np.ndarray, f: np.ndarray) -> dict:
    """The best axis's multiple correlation of the residual with the specific force."""
    n = e.shape[0]
    best = (0.0, 0)
    for i in range(3):
        a = np.column_stack([f - f.mean(0), np.ones(n)])
        coef, *_ = np.linalg.lstsq(a, e[:, i], rcond=None)
        pred = a @ coef
        r2 = 1 - np.sum((e[:, i] - pred) ** 2) / max(np.sum((e[:, i] - e[:, i].mean()) ** 2), 1e-300)
        if r2 > best[0]:
            best = (r2, i)
    return {"r": round(math.sqrt(max(best[0], 0.0)), 3), "axis": "xyz"[best[1]],
            "label": "specific force"}


def _eta(e: np.ndarray, s: np.ndarray, bins: int = 32) -> np.ndarray:
    """Correlation ratio η per axis: the share (as a root) of the residual's variance its
    mean over ``bins`` quantile bins of the signal explains, whatever the function."""
    edges = np.unique(np.quantile(s, np.linspace(0.0, 1.0, bins + 1)[1:-1]))
    k = np.searchsorted(edges, s, side="right")
    cnt = np.bincount(k, minlength=edges.size + 1).astype(float)
    ok = cnt > 0
    out = np.zeros(3)
    for i in range(3):
        x = e[:, i] - e[:, i].mean()
        var = float(np.mean(x * x))
        m = np.bincount(k, weights=x, minlength=cnt.size)[ok] / cnt[ok]
        out[i] = math.sqrt(min(float(np.sum(cnt[ok] * m * m)) / x.size / var, 1.0)) if var > 0 else 0.0
    return out


def _term_column(c) -> str | None:
    """The extra column a candidate's term reads (``aux(vdd)``: vdd), or None."""

    try:
        return term_column(parse_term(c.term)) if c.term and "(" in c.term else None
    except Exception:  # a term of several parts or an unregistered one: no column
        return None


def _named(c) -> str:
    """How the explanation names a candidate: its effect, or its term when that names a column."""
    return c.term if _term_column(c) else c.effect


def _fmt(x) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.2g}"


#: Where the README shows how to add a term of one's own.
REGISTER_HINT = "see the README's `@register` example, \"A new effect from outside the package\""


def _strength(v: dict) -> float:
    """How closely the residual follows a signal: |r|, or η (any function) for a column."""
    return max(abs(v["r"]), v.get("eta", 0.0))


def followed_most(ev: dict) -> tuple[str, dict] | None:
    """The evidence signal the residual follows most (|r|, or η for an extra column; time
    itself left out), or None."""
    sigs = [(k, v) for k, v in ev.items() if isinstance(v, dict) and "r" in v and k != "time"]
    return max(sigs, key=lambda kv: _strength(kv[1])) if sigs else None


def _outside(ev: dict) -> str:
    """The end of a missing-effect explanation that names no term: the signal the residual
    follows most, and how to add a term for it."""
    top = followed_most(ev)
    if top is None or _strength(top[1]) < 0.3:
        return ("several effects may be missing at once, or one outside the vocabulary that no "
                f"logged signal shows: register a term for it; {REGISTER_HINT}.")
    name, v = top
    if v.get("eta", 0.0) > abs(v["r"]) + 0.2:  # a column, followed but not along a line
        return (f"no term of the vocabulary follows it, but the residual follows {v['label']} "
                f"most, not along a line (η = {v['eta']:.2f} on axis {v['eta_axis']}, "
                f"r = {v['r']:+.2f}): an effect outside the vocabulary: try a higher order of "
                f"`aux({name.split(':', 1)[1]},k)` or register a term whose column is that "
                f"function of it; {REGISTER_HINT}.")
    share = f", {100 * v['explains']:.0f} % of the excess" if "explains" in v else ""
    return (f"no term of the vocabulary follows it, but the residual follows {v['label']} most "
            f"(r = {v['r']:+.2f} on axis {v['axis']}{share}): an effect outside the vocabulary "
            f"(or several at once): register a term whose column follows {v['label']}; "
            f"{REGISTER_HINT}.")


def explain(d: DeviceDiagnosis) -> str:
    """A short explanation in words naming the evidence.

    **Arguments:**

    - ``d``: the device's :class:`DeviceDiagnosis`.
    """
    white = max(d.white_noise_rms, 1e-300)
    floor = f"white-noise RMS {_fmt(d.white_noise_rms)} rad/s"
    if d.verdict == "adequate":
        text = (f"{d.device}: adequate — held-out RMS {_fmt(d.heldout_rms)} rad/s against a "
                f"{floor} ({100 * (d.heldout_rms / white - 1):+.0f} %)")
        near = [c for c in d.candidates if c.closure > 0.1][:1]
        if near:
            c = near[0]
            text += (f"; best candidate `{_named(c)}` would give {_fmt(c.heldout_rms)} "
                     f"(closes {100 * max(c.closure, 0):.0f} % of a small gap: not material)")
        return text + "."
    b = d.best
    if b is None:
        near = [c for c in d.candidates if c.closure > 0 and not c.stochastic][:3]
        text = (f"{d.device}: missing effect — held-out RMS {_fmt(d.heldout_rms)} rad/s is "
                f"{d.heldout_rms / white:.1f}× the {floor}, and no single term "
                f"closes enough of the gap")
        if near:
            text += " (best: " + ", ".join(f"`{c.spec}` {_fmt(c.heldout_rms)}, closes "
                                           f"{100 * c.closure:.0f} %" for c in near) + ")"
        text += ": " + _outside(d.evidence)
        rw = d.random_walk
        if rw is not None and rw.closure > 0.5:
            text += (f" A random-walk smoother would also follow this residual (held-out "
                     f"{_fmt(rw.heldout_rms)}), but it would not calibrate future data.")
        return text
    cls = registry().get(b.effect)
    sig_name = cls.follows if cls is not None else None
    phrase = (cls.evidence_phrase if cls is not None else None) or f"follows the `{b.effect}` term"
    column = _term_column(b)
    if column is not None:
        sig_name, phrase = aux_key(column), f"follows `{column}`"
    ev = d.evidence.get(sig_name) if sig_name else None
    what = f"residual {phrase}"
    if ev is not None and sig_name != "time":
        what += f" (r = {ev['r']:+.2f} on axis {ev['axis']}"
        what += ")" if column is not None else f" with {ev['label']})"
        if sig_name == "heating" and "mean_heating" in ev:
            what += (f"; mean {_fmt(ev['mean_heating'])} rad/s heating vs "
                     f"{_fmt(ev['mean_cooling'])} cooling")
    if b.stochastic:
        what += f"; Allan slope of the residual at long τ {d.allan_slope:+.2f} (+½ for a random walk)"
    if family_of(b.effect) == "rate-dependent scale factor" and d.evidence.get("high_rate_rms"):
        what += (f"; residual RMS {_fmt(d.evidence['high_rate_rms'])} at high rates vs "
                 f"{_fmt(d.evidence.get('low_rate_rms'))} at low")
    tau = f" (τ ≈ {b.tau:.0f} s)" if b.tau else ""
    text = (f"{d.device}: {what}: add `{b.term or b.effect}`{tau}; held-out RMS "
            f"{_fmt(d.heldout_rms)} → {_fmt(b.heldout_rms)} rad/s, {floor}.")
    if d.alternatives:
        alts = ", ".join(f"`{c.term or c.effect}` {_fmt(c.heldout_rms)}" for c in d.alternatives)
        fam = family_of(b.effect)
        same = fam is not None and all(family_of(c.effect) == fam for c in d.alternatives)
        text += f" Close alternatives{f' ({fam} family)' if same else ''}: {alts}."
    if d.next is not None:
        text += (f" Two effects are missing: `{_named(b)}` alone closes {100 * b.closure:.0f} % "
                 f"of the gap, and the next round is expected to add `{d.next.term}` (with both: "
                 f"held-out {_fmt(d.next.heldout_rms)}, {100 * d.next.closure:.0f} % closed).")
    if not b.stochastic and d.random_walk is not None and d.random_walk.closure > 0.5:
        text += (f" A random-walk smoother would also follow this residual (held-out "
                 f"{_fmt(d.random_walk.heldout_rms)}), but `{_named(b)}` explains it with a "
                 f"physical signal and calibrates future data.")
    if d.floor_allan and abs(d.floor_allan / white - 1) > 0.2:
        text += (f" Note: the short-τ Allan deviation of the residual ({_fmt(d.floor_allan)}) "
                 f"disagrees with the white-noise RMS (spikes, steps or correlated samples).")
    return text
