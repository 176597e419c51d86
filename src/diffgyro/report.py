"""Figures and self-contained HTML reports of a diagnosis.

Per device: the residual of the base model against time, temperature
(heating and cooling coloured), dT/dt, input rate and specific force (when
the data has them); the residual of the base model and of the model with the
named term, against time and against the signal that term follows (its
effect's ``follows``: dT/dt, temperature, temp − temp_ext, the reference rate,
an extra column), so the drop is seen; the Allan deviation of the residual with the noise
floor; the candidates' held-out RMS against the base model and the floor;
and the model ladder when the diagnosis came from ``--auto``. A batch gets a
summary page: how many devices are adequate, the distribution of every
coefficient across devices and the outlier devices.

Images are embedded as base64 PNG, so each page is one file that can be
mailed or archived; every file is written atomically (a temporary file in
the same folder, then renamed).

A diagnosis of the accelerometer channel (:mod:`diffgyro.channel`) is drawn on what was
fitted (the accelerometer less its gravity reference, or its rests with gravity along each
face the input), its pages and figures in m/s² and its axes ``ax, ay, az``.
"""

from __future__ import annotations

import base64
import contextvars
import html
import io
import math
import os
import re
import sys
from pathlib import Path

import numpy as np

from ._jsonio import atomic_write_text as write_atomic  # the one atomic write (jsonio)
from .channel import UNITS, fitted_batch
from .data import Batch
from .effects import product_of
from .fit import fit
from .model import ErrorModel
from .motion import describe

AXES = ("x", "y", "z")
COLORS = ("tab:blue", "tab:orange", "tab:green")
#: Most points drawn per scatter (the rest are thinned evenly; bin means are drawn on top).
MAX_POINTS = 3000


#: The channel whose report is being written (its units and axis names in every text).
_CHANNEL: contextvars.ContextVar[str] = contextvars.ContextVar("report_channel", default="gyro")
_IMAGE = re.compile(r"(data:image/png;base64,[A-Za-z0-9+/=]*)")
_GYRO_AXIS = re.compile(r"\bg([xyz])\b")

# --------------------------------------------------------------------------- plumbing


def in_units(text: str, channel: str | None = None) -> str:
    """``text`` (a label or a page, its embedded images untouched) in the units of
    ``channel`` (default: the report being written): the gyro's wording as it is, the
    accelerometer's in m/s² with axes ``ax, ay, az`` and gravity as its input.

    **Arguments:**

    - ``text``: a label or a page.
    - ``channel``: ``gyro`` or ``accel`` (default: the report being written).
    """
    channel = _CHANNEL.get() if channel is None else channel
    if channel == "gyro":
        return text
    unit = UNITS[channel]

    def words(part: str) -> str:
        part = part.replace("rad/s²", "m/s³").replace("rad/s", unit)
        part = part.replace("input rate", "input (gravity on the face)")
        return _GYRO_AXIS.sub(r"a\1", part)

    return "".join(p if i % 2 else words(p) for i, p in enumerate(_IMAGE.split(text)))



def _plt():

    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:  # a notebook keeps its own backend
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_png(fig) -> str:
    """A matplotlib figure as a base64 PNG string (the figure is closed).

    **Arguments:**

    - ``fig``: the matplotlib figure.
    """
    if _CHANNEL.get() != "gyro":  # every text artist: labels, titles, legends, ticks
        for text in fig.findobj(lambda a: hasattr(a, "get_text") and hasattr(a, "set_text")):
            text.set_text(in_units(text.get_text()))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    _plt().close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _thin(n: int) -> np.ndarray:
    step = max(1, n // MAX_POINTS)
    return np.arange(0, n, step)


def _binned(x, y, bins=60):
    """Mean of ``y`` in equal-count bins of ``x`` (for a readable trend over a cloud)."""
    order = np.argsort(x)
    xs, ys = x[order], y[order]
    k = max(1, len(xs) // bins)
    m = len(xs) // k * k
    if m == 0:
        return xs, ys
    return xs[:m].reshape(-1, k).mean(1), ys[:m].reshape(-1, k).mean(1)


def _moving_mean(t, y, segments=150):
    """Means of ``y`` (and ``t``) over ``segments`` consecutive runs of samples."""
    m = max(1, len(t) // segments)
    cut = len(t) // m * m
    return t[:cut].reshape(-1, m).mean(1), y[:cut].reshape(-1, m).mean(1)


def _scatter_vs(ax, x, e, xlabel, color_by=None):
    idx = _thin(len(x))
    for i in range(3):
        if color_by is None:
            ax.plot(x[idx], e[idx, i], ".", ms=1.5, alpha=0.25, color=COLORS[i])
        bx, by = _binned(x, e[:, i])
        ax.plot(bx, by, "-", lw=1.5, color=COLORS[i], label=f"g{AXES[i]} (bin mean)")
    if color_by is not None:
        for val, col, lab in ((1.0, "tab:red", "heating"), (-1.0, "tab:blue", "cooling")):
            sel = idx[color_by[idx] == val]
            ax.plot(x[sel], e[sel].mean(1), ".", ms=1.5, alpha=0.3, color=col, label=lab)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("residual (rad/s)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, markerscale=4)


# --------------------------------------------------------------------------- figures


def device_figures(diagnosis, batch: Batch, i: int, ladder=None, named=None) -> dict[str, str]:
    """The figures of device ``i`` as {title: base64 PNG}; ``named`` is this device's entry of
    :func:`named_term_residuals` (the residual with the named term, drawn over the base's).

    **Arguments:**

    - ``diagnosis``: the :class:`~diffgyro.diagnose.Diagnosis`.
    - ``batch``: the data diagnosed.
    - ``i``: the device's index.
    - ``ladder``: the batch's :class:`~diffgyro.diagnose.Ladder` (``diagnose --auto``), or
      None.
    - ``named``: this device's entry of :func:`named_term_residuals`, or None.
    """
    d = diagnosis.devices[i]
    n = int(batch.n_valid[i])
    rec = batch.recording(i)
    e = np.asarray(diagnosis.residuals[i, :n])
    sig = diagnosis.fit.signals(batch)
    heating = None if sig.heating is None else np.asarray(sig.heating[i, :n])
    dtemp = None if sig.dtemp is None else np.asarray(sig.dtemp[i, :n])
    out: dict[str, str] = {"Residual against time": _time_png(diagnosis, d, rec, e)}
    if named is not None:
        new_spec, e_new = named
        fig = residual_drop_figure(diagnosis.model, new_spec, rec, e, e_new, dtemp)
        out[f"The residual without and with {_added(diagnosis.spec, new_spec)}"] = figure_png(fig)
    if rec.temp is not None:
        out["Residual against temperature and dT/dt"] = _thermal_png(rec, e, heating, dtemp)
    motion = _motion_png(rec, e)
    if motion is not None:
        out["Residual against input rate and specific force"] = motion
    if not math.isfinite(d.heldout_rms):  # without a base fit there is nothing more to draw
        return out
    out["Allan deviation of the residual"] = _allan_png(diagnosis.allan, d, i)
    if d.candidates:
        out["Candidates: held-out RMS with each term added"] = _candidates_png(diagnosis, d)
    if ladder is not None and len(ladder.steps) > 1:
        out["Model ladder"] = ladder_png(ladder, device=i)
    return out


def _time_png(diagnosis, d, rec, e) -> str:
    """Residual against time (thinned points and moving means), temperature on a twin axis."""
    plt = _plt()
    n = len(e)
    t = rec.t - rec.t[0]
    fig, ax = plt.subplots(figsize=(9, 3.2))
    idx = _thin(n)
    for k in range(3):
        ax.plot(t[idx] / 60.0, e[idx, k], ".", ms=1.2, alpha=0.25, color=COLORS[k])
        ax.plot(*_moving_mean(t / 60.0, e[:, k]), lw=1.4, color=COLORS[k],
                label=f"g{AXES[k]} (moving mean)")
    ax.axhline(d.noise_floor, color="k", ls=":", lw=0.8, label="± noise floor")
    ax.axhline(-d.noise_floor, color="k", ls=":", lw=0.8)
    ax.set_xlabel("time (min)")
    ax.set_ylabel("residual (rad/s)")
    ax.set_title(f"{d.device}: residual of {diagnosis.spec}", fontsize=9)
    ax.grid(alpha=0.3)
    if rec.temp is not None:
        ax2 = ax.twinx()
        ax2.plot(t[idx] / 60.0, rec.temp[idx], color="0.5", lw=0.8)
        ax2.set_ylabel("temp (°C)", color="0.4")
    ax.legend(fontsize=7, loc="upper left")
    return figure_png(fig)


def _thermal_png(rec, e, heating, dtemp) -> str:
    """Residual against temperature (heating red, cooling blue) and against dT/dt."""
    fig, axs = _plt().subplots(1, 2, figsize=(11, 3.4))
    _scatter_vs(axs[0], rec.temp, e, "temperature (°C)", color_by=heating)
    axs[0].set_title("residual vs temperature (heating red, cooling blue)", fontsize=9)
    if dtemp is not None:
        _scatter_vs(axs[1], dtemp * 60.0, e, "dT/dt (°C/min)")
        axs[1].set_title("residual vs dT/dt", fontsize=9)
    return figure_png(fig)


def _motion_png(rec, e) -> str | None:
    """Residual against the input rate (own axis) and the specific-force direction; None
    when the record neither turns nor changes its attitude."""
    moving = rec.rate is not None and np.max(np.abs(rec.rate)) > 1e-3
    varying_f = rec.accel is not None and np.ptp(rec.accel, axis=0).max() > 1.0
    if not (moving or varying_f):
        return None
    fig, axs = _plt().subplots(1, 2, figsize=(11, 3.4))
    idk = _thin(len(e))
    panels = []
    if moving:
        panels.append((axs[0], rec.rate, "r{}", "input rate (rad/s)",
                       "residual vs input rate (own axis)"))
    else:
        axs[0].set_axis_off()
    if varying_f:
        fn = np.linalg.norm(rec.accel, axis=1)
        panels.append((axs[1], rec.accel / np.maximum(fn, 1e-9)[:, None], "a{}/|a|",
                       "specific force direction (a/|a|)", "residual vs specific force"))
    else:
        axs[1].set_axis_off()
    for ax, x, name, xlabel, title in panels:
        for k in range(3):
            ax.plot(x[idk, k], e[idk, k], ".", ms=1.5, alpha=0.3, color=COLORS[k],
                    label=f"g{AXES[k]} vs {name.format(AXES[k])}")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("residual (rad/s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, markerscale=4)
        ax.set_title(title, fontsize=9)
    return figure_png(fig)


def _allan_png(al, d, i: int) -> str:
    """Allan deviation of the residual per axis, with white noise at the floor."""
    tau = np.asarray(al.tau)[i]
    adev = np.asarray(al.adev)[i]
    fig, ax = _plt().subplots(figsize=(6.5, 4.2))
    for k in range(3):
        ok = np.isfinite(adev[k])
        ax.loglog(tau[k][ok], adev[k][ok], "o-", ms=2.5, lw=1, color=COLORS[k], label=f"g{AXES[k]}")
    ok = np.isfinite(tau[0])
    if ok.any():
        dt = float(tau[0][ok][0])
        tt = tau[0][ok]
        ax.loglog(tt, d.noise_floor * np.sqrt(dt / tt), "k--", lw=1,
                  label=f"white noise at the floor ({d.noise_floor:.2g} rad/s)")
    ax.set_xlabel("τ (s)")
    ax.set_ylabel("Allan deviation of residual (rad/s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.set_title(f"long-τ slope {d.allan_slope:+.2f} (−½ white, 0 flicker, +½ random walk)", fontsize=9)
    ax.legend(fontsize=7)
    return figure_png(fig)


def _candidates_png(diagnosis, d) -> str:
    """Held-out RMS of the base and of each candidate added, significant ones in red."""
    fig, ax = _plt().subplots(figsize=(8, 0.6 + 0.28 * (len(d.candidates) + 1)))
    labels = [f"{diagnosis.spec} (base)"] + [c.effect for c in d.candidates]
    vals = [d.heldout_rms] + [c.heldout_rms for c in d.candidates]
    cols = ["0.6"] + ["tab:red" if c.significant else "tab:gray" for c in d.candidates]
    y = np.arange(len(labels))[::-1]
    ax.barh(y, vals, color=cols)
    ax.set_yticks(y, labels, fontsize=7)
    ax.axvline(d.noise_floor, color="k", ls="--", lw=1, label="noise floor")
    ax.set_xlabel("held-out RMS (rad/s); red = significant")
    ax.set_xlim(0, max(vals + [d.noise_floor]) * 1.05 if vals else 1)
    ax.legend(fontsize=7)
    return figure_png(fig)


# --------------------------------------------------------------------------- the drop with the named term


def named_term_residuals(diagnosis, batch: Batch, ladder=None) -> dict[int, tuple[str, np.ndarray]]:
    """Device index -> (the model with its named term, that model's residual (n, 3)).

    For every device whose diagnosis names a deterministic term: one fit per
    distinct model over the devices that name it, with the base fit's options
    (the ladder's last fit is reused when it is that model).

    **Arguments:**

    - ``diagnosis``: the :class:`~diffgyro.diagnose.Diagnosis`.
    - ``batch``: the data diagnosed.
    - ``ladder``: the batch's :class:`~diffgyro.diagnose.Ladder` (``diagnose --auto``), or
      None.
    """

    groups: dict[str, list[int]] = {}
    for i, d in enumerate(diagnosis.devices):
        if d.best is not None and not d.best.stochastic and math.isfinite(d.heldout_rms):
            groups.setdefault(d.best.spec, []).append(i)
    out: dict[int, tuple[str, np.ndarray]] = {}
    for spec, idx in groups.items():
        if ladder is not None and ladder.final.spec == spec:
            e, rows = np.asarray(ladder.final.fit.residuals(batch)), idx
        else:
            sub = batch.select(np.asarray(idx))
            e = np.asarray(fit(spec, sub, options=diagnosis.fit.options).residuals(sub))
            rows = range(len(idx))
        for i, r in zip(idx, rows):
            e_i = e[r, : int(batch.n_valid[i])]
            if np.all(np.isfinite(e_i)):
                out[i] = (spec, e_i)
    return out


def _added(base_spec: str, new_spec: str) -> str:

    old = {t.spec for t in ErrorModel.from_spec(base_spec).terms}
    return "+".join(t.spec for t in ErrorModel.from_spec(new_spec).terms if t.spec not in old)


def _most_correlated(cols: np.ndarray, y: np.ndarray, among=(0, 1, 2)) -> int:
    """The column of ``cols`` (n, m), among ``among``, that ``y`` follows most (|r|)."""
    def r(j):
        c = np.corrcoef(cols[:, j], y)[0, 1]
        return abs(c) if np.isfinite(c) else -1.0
    return max(among, key=r)


def followed_signal(name: str | None, rec, dtemp, k: int, delta: np.ndarray):
    """(x (n,), axis label) of the signal ``name`` (an effect's ``follows``) of ``rec`` as it
    bears on gyro axis ``k``; ``delta`` (the named term's fitted contribution on that axis)
    picks the component of a vector signal. None when the data lack it or it is time.

    **Arguments:**

    - ``name``: the signal's name (an effect's ``follows``).
    - ``rec``: the device's :class:`~diffgyro.data.Recording`.
    - ``dtemp``: its dT/dt (n,), °C/s.
    - ``k``: the gyro axis.
    - ``delta``: the named term's fitted contribution on that axis (n,).
    """
    temp, ext, rate, acc = rec.temp, rec.temp_ext, rec.rate, rec.accel
    if name in ("temp", "heating") and temp is not None:
        return temp, "temperature (°C)"
    if name == "dtemp" and dtemp is not None:
        return dtemp * 60.0, "dT/dt (°C/min)"
    if name == "temp_diff" and temp is not None and ext is not None:
        return temp - ext, "temp − temp_ext (°C)"
    if name in ("rate", "abs_rate", "rate3") and rate is not None:
        return rate[:, k], f"reference rate r{AXES[k]} (rad/s)"
    if name == "cross_rate" and rate is not None:
        j = _most_correlated(rate, delta, [j for j in range(3) if j != k])
        return rate[:, j], f"reference rate r{AXES[j]} (rad/s)"
    if name == "accel" and acc is not None:
        j = _most_correlated(acc, delta)
        return acc[:, j], f"specific force a{AXES[j]} (m/s²)"
    if name is not None and name.startswith("term:"):  # a grammar term: its product

        x = product_of(name[5:], rec, dtemp, k)
        return None if x is None else (x, name[5:])
    if name is not None and name.startswith("aux:"):
        x = getattr(rec, "aux", {}).get(name[4:])
        return None if x is None else (np.asarray(x), name[4:])
    return None


def _signal_of_term(base_spec: str, new_spec: str, rec, dtemp, k: int, delta):
    """The signal the added term follows; for a term that names none (a user effect),
    the one among the data's signals that its contribution follows most."""

    old = {t.spec for t in ErrorModel.from_spec(base_spec).terms}
    added = [t for t in ErrorModel.from_spec(new_spec).terms if t.spec not in old]
    names = [t.followed_signal() for t in added]
    if names and names[0] is not None:
        return followed_signal(names[0], rec, dtemp, k, delta)
    tries = ["temp", "dtemp", "temp_diff", "rate", "accel",
             *(f"aux:{c}" for c in getattr(rec, "aux", {}))]
    found = [s for s in (followed_signal(nm, rec, dtemp, k, delta) for nm in tries) if s is not None]
    found = [s for s in found if np.ptp(s[0]) > 0]
    if not found:
        return None
    return max(found, key=lambda s: abs(np.nan_to_num(np.corrcoef(s[0], delta)[0, 1])))


def residual_drop_figure(base_model, new_spec: str, rec, e_base: np.ndarray, e_new: np.ndarray,
                         dtemp: np.ndarray | None = None):
    """Residual of ``base_model`` and of ``new_spec`` on the axis where they differ most,
    against time and against the signal the added term follows (a matplotlib figure).

    Each model is drawn as thinned samples, labelled ``"<spec>: RMS <value> rad/s"`` (the
    RMS of every sample on that axis), and a moving or bin mean in the same colour.

    **Arguments:**

    - ``base_model``: the base :class:`~diffgyro.model.ErrorModel`.
    - ``new_spec``: the spec with the added term.
    - ``rec``: the device's :class:`~diffgyro.data.Recording`.
    - ``e_base``: the base model's residual (n, 3), rad/s.
    - ``e_new``: the new model's residual (n, 3), rad/s.
    - ``dtemp``: the device's dT/dt (n,), °C/s, where known.
    """
    plt = _plt()
    base_spec = getattr(base_model, "spec", base_model)
    k = int(np.argmax(np.mean(e_base**2, 0) - np.mean(e_new**2, 0)))
    delta = e_base[:, k] - e_new[:, k]
    signal = _signal_of_term(base_spec, new_spec, rec, dtemp, k, delta)
    ncol = 1 if signal is None else 2
    fig, axs = plt.subplots(1, ncol, figsize=(5.5 * ncol + (3 if ncol == 1 else 0), 3.6), squeeze=False)
    t = (rec.t - rec.t[0]) / 60.0
    idx = _thin(len(t))
    for e, spec, col in ((e_base, base_spec, "0.5"), (e_new, new_spec, "tab:red")):
        y = e[:, k]
        label = f"{spec}: RMS {math.sqrt(float(np.mean(y**2))):.3g} rad/s"
        axs[0, 0].plot(t[idx], y[idx], ".", ms=1.5, alpha=0.3, color=col, label=label)
        axs[0, 0].plot(*_moving_mean(t, y), "-", lw=1.5, color=col)
        if signal is not None:
            x = signal[0]
            axs[0, 1].plot(x[idx], y[idx], ".", ms=1.5, alpha=0.3, color=col, label=label)
            axs[0, 1].plot(*_binned(x, y), "-", lw=1.5, color=col)
    axs[0, 0].set_xlabel("time (min)")
    axs[0, 0].set_title(f"g{AXES[k]} residual against time (lines: moving mean)", fontsize=9)
    if signal is not None:
        axs[0, 1].set_xlabel(signal[1])
        axs[0, 1].set_title(f"g{AXES[k]} residual against {signal[1]} (lines: bin mean)", fontsize=9)
    for ax in axs.flat:
        ax.set_ylabel("residual (rad/s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, markerscale=4)
    fig.tight_layout()
    return fig


def ladder_png(ladder, device: int | None = None) -> str:
    """Held-out RMS as terms are added (one line per device, or one device).

    **Arguments:**

    - ``ladder``: the :class:`~diffgyro.diagnose.Ladder`.
    - ``device``: one device's index, or None for all.
    """
    plt = _plt()
    fig, ax = plt.subplots(figsize=(7, 3.6))
    specs = [s.spec for s in ladder.steps]
    x = np.arange(len(specs))
    h = np.array([s.heldout_rms for s in ladder.steps])  # (steps, devices)
    fl = np.array([s.noise_floor for s in ladder.steps])
    devs = range(h.shape[1]) if device is None else [device]
    for k in devs:
        ax.plot(x, h[:, k], "o-", lw=1.2, label=ladder.devices[k] if device is not None or h.shape[1] <= 8 else None)
        ax.plot(x, fl[:, k], ":", color="0.4", lw=0.8)
    ax.set_xticks(x, [s.added or "base" for s in ladder.steps], rotation=20, fontsize=8)
    ax.set_ylabel("held-out RMS (rad/s)")
    ax.set_yscale("log")
    ax.grid(alpha=0.3, which="both")
    ax.set_title("model ladder (dotted: noise floor)", fontsize=9)
    if device is not None or h.shape[1] <= 8:
        ax.legend(fontsize=7)
    return figure_png(fig)


# --------------------------------------------------------------------------- pages

_CSS = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;color:#222}
h1{font-size:1.4em}h2{font-size:1.15em;margin-top:1.6em}table{border-collapse:collapse;font-size:.85em}
td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}th{background:#f3f3f3}
td.l,th.l{text-align:left}.adequate{color:#1a7f37}.missing_effect{color:#b42318}
.not_judged{color:#9a6700}.pass{color:#1a7f37}.fail{color:#b42318}
.expl{background:#f7f7f7;border-left:4px solid #888;padding:.6em 1em}img{max-width:100%}"""


def _page(title: str, body: str) -> str:
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{_CSS}</style></head><body>{body}</body></html>")


def _fmt(x) -> str:
    return "—" if x is None or not math.isfinite(float(x)) else f"{float(x):.3g}"


def _limits_html(record: dict | None) -> str:
    """A device's pass/fail against a limits file, with every limit it broke."""
    if not record or "limits" not in record:
        return ""
    lim = record["limits"]
    res = lim["result"]
    rows = "".join(
        f"<tr><td class=l>{html.escape(b['limit'])}</td><td>{html.escape(_num(b.get('value')))}</td>"
        f"<td>{html.escape(_num(b.get('min')))}</td><td>{html.escape(_num(b.get('max')))}</td>"
        f"<td>{html.escape(_num(b.get('by')))}</td>"
        f"<td class=l>{html.escape(b.get('detail', ''))}</td></tr>" for b in lim["broken"])
    table = ("<table><tr><th class=l>limit</th><th>value</th><th>min</th><th>max</th><th>by</th>"
             f"<th class=l>why</th></tr>{rows}</table>") if rows else ""
    return f"<h2>Limits: <span class={res}>{res}</span></h2>{table}"


def _num(x) -> str:
    if x is None:
        return "—"
    return f"{x:.4g}" if isinstance(x, (int, float)) and not isinstance(x, bool) else str(x)


def _limits_summary_html(summary: dict | None) -> str:
    """The batch's yield against a limits file and the rejected units."""
    if not summary:
        return ""
    y = summary["yield"]
    rejected = ", ".join(html.escape(str(r)) for r in summary["rejected"]) or "none"
    return (f"<h2>Limits {html.escape(str(summary['name']))}</h2><p>File "
            f"<code>{html.escape(str(summary['file']))}</code>: {summary['passed']} of "
            f"{summary['passed'] + summary['failed']} devices pass"
            + ("" if y is None else f" (yield {100 * y:.1f} %)")
            + f"; rejected: {rejected}.</p>")


def _motion_line(diagnosis, i: int) -> str:
    """Whether device ``i`` was at rest (the fit's motion check), as a paragraph."""
    motion = getattr(diagnosis.fit, "motion", None)
    if motion is None:
        return ""

    return f"<p class=motion>Motion check: {html.escape(describe(motion.record(i)))}.</p>"


def device_page(diagnosis, batch: Batch, i: int, ladder=None, named=None, limits=None) -> str:
    """One device's page; ``limits``: its record with the --limits result.

    **Arguments:**

    - ``diagnosis``: the :class:`~diffgyro.diagnose.Diagnosis`.
    - ``batch``: the data diagnosed.
    - ``i``: the device's index.
    - ``ladder``: the batch's :class:`~diffgyro.diagnose.Ladder` (``diagnose --auto``), or
      None.
    - ``named``: this device's entry of :func:`named_term_residuals`, or None.
    - ``limits``: the device's record with its ``--limits`` result, or None.
    """
    d = diagnosis.devices[i]
    rows = "".join(
        f"<tr><td class=l>{html.escape(c.effect)}</td><td class=l>{html.escape(c.spec)}</td>"
        f"<td>{_fmt(c.heldout_rms)}</td><td>{_fmt(c.closure * 100)} %</td><td>{_fmt(c.t)}</td>"
        f"<td>{'yes' if c.significant else 'no'}</td></tr>" for c in d.candidates)
    skipped = "".join(f"<li>{html.escape(k)}: {html.escape(v)}</li>" for k, v in d.skipped.items())
    body = [
        f"<h1>{html.escape(d.device)} — <span class={d.verdict}>{d.verdict}</span></h1>",
        f"<p>Model <code>{html.escape(diagnosis.spec)}</code>; fit status "
        f"{_text(d.status_detail or d.status)}. "
        f"RMS {_fmt(d.rms)}, held-out RMS {_fmt(d.heldout_rms)}, noise floor {_fmt(d.noise_floor)} "
        f"rad/s (short-τ Allan {_fmt(d.floor_allan)}).</p>",
        f"<p class=expl>{_text(d.explanation)}</p>",
        _limits_html(limits),
        _motion_line(diagnosis, i),
        "<h2>Candidates (best first)</h2><table><tr><th class=l>effect</th><th class=l>model</th>"
        "<th>held-out RMS</th><th>gap closed</th><th>paired t</th><th>significant</th></tr>"
        f"{rows}</table>",
    ]
    if skipped:
        body.append(f"<p>Not tried:</p><ul>{skipped}</ul>")
    body.append(_noise_html(d.noise))
    for title, png in device_figures(diagnosis, batch, i, ladder, named).items():
        body.append(f"<h2>{html.escape(title)}</h2><img alt='{html.escape(title)}' "
                    f"src='data:image/png;base64,{png}'>")
    body.append("<p><a href='index.html'>batch summary</a></p>")
    return _page(f"diffgyro diagnosis: {d.device}", "".join(body))


def _noise_html(entry: dict | None) -> str:
    """The residual's noise model as ``diagnose --json``'s ``noise`` holds it: per axis each
    component's parameters with their intervals (nothing where it was not identified)."""
    if not entry or entry.get("status") != "ok" or not entry.get("axes"):
        return ""
    level = entry.get("interval_level")
    rows = []
    for ax, axis in entry["axes"].items():
        for c in axis["components"]:
            for name, par in c["params"].items():
                lo, hi = par.get("ci") or (None, None)
                ci = "—" if lo is None or hi is None else f"[{_fmt(lo)}, {_fmt(hi)}]"
                rows.append(f"<tr><td class=l>{html.escape(ax)}</td><td class=l>"
                            f"{html.escape(c['kind'].replace('_', '-'))}</td><td class=l>"
                            f"{html.escape(name)}</td><td>{_fmt(par.get('value'))}</td>"
                            f"<td>{ci}</td><td class=l>{html.escape(str(par.get('unit', '')))}</td></tr>")
    head = (f"<h2>Noise model of the residual</h2><p>Identified on the base model's residual "
            f"(as <code>diffgyro noise</code>); intervals at "
            f"{'—' if level is None else f'{level:.0%}'}.</p>")
    return (head + "<table><tr><th class=l>axis</th><th class=l>component</th>"
            "<th class=l>parameter</th><th>value</th><th>interval</th><th class=l>unit</th></tr>"
            + "".join(rows) + "</table>")


def _coefficients(fit) -> dict[str, np.ndarray]:
    """Every coefficient label -> values across devices."""
    out: dict[str, list] = {}
    for i in range(fit.n_devices):
        for ax, vals in fit.param_dict(i).items():
            for lab, v in vals.items():
                out.setdefault(f"{ax}: {lab}" if ax != "shared" else lab, []).append(v)
    return {k: np.asarray(v, float) for k, v in out.items()}


def outliers(diagnosis, z: float = 5.0) -> list[tuple[str, str]]:
    """Devices far from the batch: robust z (median/MAD) of held-out/floor or of a coefficient.

    **Arguments:**

    - ``diagnosis``: the :class:`~diffgyro.diagnose.Diagnosis`.
    - ``z``: the robust z beyond which a device is far from the batch.
    """
    out = []
    devs = [d.device for d in diagnosis.devices]
    if len(devs) < 4:
        return out
    ratio = np.array([d.heldout_rms / max(d.noise_floor, 1e-300) for d in diagnosis.devices])
    series = {"held-out RMS / noise floor": ratio, **_coefficients(diagnosis.fit)}
    for name, v in series.items():
        med = np.nanmedian(v)
        mad = 1.4826 * np.nanmedian(np.abs(v - med))
        if not np.isfinite(mad) or mad <= 0:
            continue
        for k in np.flatnonzero(np.abs(v - med) > z * mad):
            out.append((devs[k], f"{name} = {v[k]:.3g} (batch median {med:.3g})"))
    return out


#: Robust z (median/MAD) past which a device is an outlier of the batch.
OUTLIER_Z = 5.0
#: Panels of the coefficient figure with more devices than this are histograms.
STRIP_MAX = 20


def _text(text: str) -> str:
    """Message text as HTML: escaped, and its `term` quotes set as code."""

    return re.sub(r"`([^`]+)`", r"<code>\1</code>", html.escape(text))


def coefficient_unit(model, label: str) -> str:
    """The unit of a coefficient label (``bias_poly(2).c1`` -> ``rad/s per T_s``;
    a shared time constant ``thermal_lag.tau`` -> ``s``). ``T_s``: the scaled temperature
    (dimensionless, about [-1, 1] over the calibrated range).

    **Arguments:**

    - ``model``: the :class:`~diffgyro.model.ErrorModel`.
    - ``label``: the coefficient's label.
    """

    spec, _, name = label.rpartition(".")
    if name == "tau" or name.startswith("tau"):
        return "s"
    term = next((t for t in model.parts if t.spec == spec), None)
    unit = getattr(term, "unit", "") or ""
    j = re.search(r"([0-9]+)$", name)
    if "^j" in unit:
        k = int(j.group(1)) if j else 1
        base, _, per = unit.partition(" per ")
        var = per.split("^j")[0]
        tail = per.split("^j", 1)[1]
        unit = base + tail if k == 0 else f"{base} per {var}" + ("" if k == 1 else f"^{k}") + tail
    return unit


def coefficients_figure(fit, devices: list[str], z: float = OUTLIER_Z):
    """Each coefficient across the devices: a strip of named dots for a few devices, a
    histogram for many; devices farther than ``z`` robust standard deviations from the
    median are drawn red and named. Returns (figure, {panel: outlier device names}).

    **Arguments:**

    - ``fit``: the :class:`~diffgyro.fit.FitResult`.
    - ``devices``: the devices' names.
    - ``z``: the robust z beyond which a device is an outlier.
    """
    plt = _plt()
    coefs = _coefficients(fit)
    names = list(coefs)
    ncol = min(3, len(names))
    nrow = math.ceil(len(names) / ncol)
    fig, axs = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 2.9 * nrow), squeeze=False,
                            layout="constrained")
    named: dict[str, list[str]] = {}
    for ax, name in zip(axs.flat, names):
        v = coefs[name]
        ok = np.isfinite(v)
        med = np.median(v[ok]) if ok.any() else np.nan
        mad = 1.4826 * np.median(np.abs(v[ok] - med)) if ok.any() else np.nan
        far = ok & (np.abs(v - med) > z * mad) if np.isfinite(mad) and mad > 0 else np.zeros_like(ok)
        if ok.sum() > STRIP_MAX:
            inner = v[ok & ~far]
            ax.hist(inner, bins=min(40, max(10, int(np.sqrt(inner.size)))), color="tab:blue")
            ax.set_ylabel("devices")
            order = np.flatnonzero(far)[np.argsort(-np.abs(v[far] - med))]
            lo, hi = (inner.min(), inner.max()) if inner.size else (med, med)
            pad = 0.08 * (hi - lo or abs(med) or 1.0)
            ax.set_xlim(lo - pad, hi + pad)  # the batch's spread, outliers at the edges
            top = ax.get_ylim()[1]
            for rank, k in enumerate(order):
                right = v[k] > med
                edge = hi + pad if right else lo - pad
                ax.plot([edge], [top * (0.9 - 0.13 * min(rank, 4))], ">" if right else "<",
                        color="tab:red", ms=6, clip_on=False)
                if rank < 4:  # name the farthest; the page lists every one
                    ax.annotate(f"{devices[k]} = {v[k]:.3g}",
                                (edge, top * (0.9 - 0.13 * rank)), fontsize=7, color="tab:red",
                                ha="right" if right else "left", va="center",
                                xytext=(-6 if right else 6, 0), textcoords="offset points")
            if order.size > 4:
                ax.text(0.99, 0.02, f"+{order.size - 4} more outliers", transform=ax.transAxes,
                        ha="right", fontsize=7, color="tab:red")
        else:  # a few devices: each a named dot
            idx = np.flatnonzero(ok)
            y = np.linspace(-0.8, 0.8, idx.size) if idx.size > 1 else np.zeros(1)
            ax.scatter(v[idx], y, s=16, color=np.where(far[idx], "tab:red", "tab:blue"))
            for yy, k in zip(y, idx):
                ax.annotate(devices[k], (v[k], yy), fontsize=6, xytext=(3, 0),
                            textcoords="offset points", va="center")
            ax.set_ylim(-1, 1)
            ax.set_yticks([])
            ax.set_ylabel("devices")
        unit = coefficient_unit(fit.model, name.split(": ")[-1])
        ax.set_title(name, fontsize=9)
        ax.set_xlabel(f"value ({unit})" if unit else "value", fontsize=8)
        ax.tick_params(labelsize=8)
        ax.ticklabel_format(axis="x", style="sci", scilimits=(-4, 5))
        ax.locator_params(axis="x", nbins=5)
        named[name] = [devices[k] for k in np.flatnonzero(far)]
    for ax in list(axs.flat)[len(names):]:
        ax.set_axis_off()
    return fig, named


def summary_page(diagnosis, ladder=None, limits=None) -> str:
    """The batch page; ``limits``: (records, summary) of --limits.

    **Arguments:**

    - ``diagnosis``: the :class:`~diffgyro.diagnose.Diagnosis`.
    - ``ladder``: the batch's :class:`~diffgyro.diagnose.Ladder` (``diagnose --auto``), or
      None.
    - ``limits``: (records, summary) of ``--limits``, or None.
    """
    plt = _plt()
    devs = diagnosis.devices
    counts = diagnosis.verdicts()
    body = [f"<h1>diffgyro diagnosis of {len(devs)} device(s)</h1>",
            f"<p>Model <code>{html.escape(diagnosis.spec)}</code>: {counts['adequate']} adequate, "
            f"{counts['missing_effect']} missing an effect, {counts['not_judged']} not judged "
            f"(base fit not ok).</p>", _limits_summary_html(None if limits is None else limits[1])]
    best: dict[str, int] = {}
    for d in devs:
        if d.best is not None:
            best[d.best.effect] = best.get(d.best.effect, 0) + 1
    fig, axs = plt.subplots(1, 2, figsize=(10, 3), layout="constrained")
    axs[0].bar(list(counts), list(counts.values()), color=["tab:green", "tab:red", "tab:olive"])
    axs[0].set_title("verdicts", fontsize=9)
    for ax in axs:
        ax.set_ylabel("devices")
    if best:
        axs[1].bar(list(best), list(best.values()), color="tab:red")
        axs[1].tick_params(axis="x", rotation=20, labelsize=8)
    axs[1].set_title("missing effect named (best candidate)", fontsize=9)
    body.append(f"<img src='data:image/png;base64,{figure_png(fig)}'>")

    rows = "".join(
        f"<tr><td class=l><a href='{_slug(d.device)}.html'>{html.escape(d.device)}</a></td>"
        f"<td class='l {d.verdict}'>{d.verdict}</td>"
        f"<td class=l>{_text(d.status_detail or d.status)}</td><td>{_fmt(d.heldout_rms)}</td>"
        f"<td>{_fmt(d.noise_floor)}</td><td class=l>{html.escape(d.best.effect if d.best else '')}</td>"
        f"<td class=l>{html.escape(', '.join(c.effect for c in d.alternatives))}</td>"
        + ("" if limits is None else f"<td class='l {limits[0][k]['limits']['result']}'>"
                                     f"{limits[0][k]['limits']['result']}</td>")
        + "</tr>" for k, d in enumerate(devs))
    table = ("<h2>Devices</h2>" + ("<div style='max-height:36em;overflow:auto'>" if len(devs) > 40
                                   else "<div>")
             + "<table><tr><th class=l>device</th><th class=l>verdict</th>"
             "<th class=l>fit status</th>"
             "<th>held-out RMS (rad/s)</th><th>noise floor (rad/s)</th><th class=l>add</th>"
             "<th class=l>close alternatives</th>"
             + ("" if limits is None else "<th class=l>limits</th>") + f"</tr>{rows}</table></div>")

    fit = ladder.final.fit if ladder is not None else diagnosis.fit
    if fit.n_devices > 1 and _coefficients(fit):
        fig, named = coefficients_figure(fit, [d.device for d in devs])
        links = ", ".join(f"<a href='{_slug(n)}.html'>{html.escape(n)}</a>"
                          for n in dict.fromkeys(n for ns in named.values() for n in ns))
        body.append(f"<h2>Coefficients across devices (<code>{html.escape(fit.model.spec)}</code>)</h2>"
                    "<p>One panel per coefficient and axis: its value (unit under the panel) "
                    "against the number of devices with it; red, at the panel's edge with their value: "
                    f"devices farther than {OUTLIER_Z:g} robust standard deviations from the batch "
                    "median."
                    + (f" Their pages: {links}." if links else "") + "</p>"
                    f"<img alt='coefficients across devices' src='data:image/png;base64,"
                    f"{figure_png(fig)}'>")
    out = outliers(diagnosis)
    body.append("<h2>Outlier devices</h2>" + (
        "<ul>" + "".join(f"<li><a href='{_slug(a)}.html'>{html.escape(a)}</a>: {html.escape(b)}</li>"
                         for a, b in out) + "</ul>"
        if out else "<p>None (robust z ≤ 5 on held-out/floor and on every coefficient).</p>"))
    body.append(table)  # after the batch's picture: at hundreds of devices it is long
    if ladder is not None and len(ladder.steps) > 1:
        body.append("<h2>Model ladder</h2>" + ladder.html_table()
                    + f"<img src='data:image/png;base64,{ladder_png(ladder)}'>")
    return _page("diffgyro diagnosis summary", "".join(body))


def _slug(name: str) -> str:
    keep = "".join(ch if ch.isalnum() or ch in "-_." else "_" for ch in name)
    return keep or "device"


def write_report(diagnosis, batch: Batch, directory: str | os.PathLike, ladder=None,
                 limits=None) -> list[Path]:
    """Write ``index.html`` (batch summary) and one page per device into ``directory``.

    ``limits``: (records, summary) of a limits file (:mod:`diffgyro.limits`): each page
    says pass or fail and the limits broken, the summary the yield and the rejected units.
    Returns the paths written. Each page embeds its figures (base64 PNG).

    **Arguments:**

    - ``diagnosis``: the :class:`~diffgyro.diagnose.Diagnosis`.
    - ``batch``: the data diagnosed.
    - ``directory``: where the pages go.
    - ``ladder``: the batch's :class:`~diffgyro.diagnose.Ladder` (``diagnose --auto``), or
      None.
    - ``limits``: (records, summary) of a limits file, or None.
    """
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    channel = getattr(diagnosis.fit, "channel", "gyro")
    batch = fitted_batch(diagnosis.fit, batch)
    token = _CHANNEL.set(channel)
    try:
        paths = []
        seen: set[str] = set()
        named = named_term_residuals(diagnosis, batch, ladder)
        for i, d in enumerate(diagnosis.devices):
            slug = _slug(d.device)
            while slug in seen:
                slug += "_"
            seen.add(slug)
            page = device_page(diagnosis, batch, i, ladder, named.get(i),
                               None if limits is None else limits[0][i])
            paths.append(write_atomic(directory / f"{slug}.html", in_units(page)))
        paths.insert(0, write_atomic(directory / "index.html",
                                     in_units(summary_page(diagnosis, ladder, limits))))
    finally:
        _CHANNEL.reset(token)
    return paths


__all__ = ["coefficient_unit", "coefficients_figure", "device_figures",
           "device_page", "figure_png", "followed_signal", "in_units", "ladder_png",
           "named_term_residuals", "outliers", "residual_drop_figure", "summary_page",
           "write_atomic", "write_report"]
