"""The Allan deviation's figure: one device's axes with intervals, lines and read-outs
(matplotlib, imported on use)."""

from __future__ import annotations

import math
import sys

import numpy as np

from ._curves import AllanResult
from ._readouts import FLICKER_FACTOR


def plot_allan(result: AllanResult, device: int = 0, axes=("gx", "gy", "gz"), ax=None, title=None):
    """Log-log Allan deviation of one device's axes with CIs, the −½, 0, +½ lines and read-outs.

    **Arguments:**

    - ``result``: the :class:`AllanResult`.
    - ``device``: the device's index.
    - ``axes``: the axes' labels.
    - ``ax``: a matplotlib axes to draw on (default: a new figure).
    - ``title``: the figure's title.
    """
    import matplotlib

    if ax is None:

        if "matplotlib.pyplot" not in sys.modules:  # a notebook keeps its own backend
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7.5, 5.0))
    else:
        fig = ax.figure
    tau = np.asarray(result.tau)[device]
    adev = np.asarray(result.adev)[device]
    lo = np.asarray(result.lo)[device]
    hi = np.asarray(result.hi)[device]
    ro = result.readouts
    colors = ("tab:blue", "tab:orange", "tab:green")
    for a, name in enumerate(axes):
        keep = np.isfinite(adev[a])
        if not keep.any():
            continue
        t, s = tau[a][keep], adev[a][keep]
        c = colors[a % 3]
        ax.fill_between(t, lo[a][keep], hi[a][keep], color=c, alpha=0.15, lw=0)
        arw = float(ro.arw[device, a])
        bi = float(ro.bias_instability[device, a])
        rrw = float(ro.rrw[device, a])
        label = (f"{name}: ARW {_fmt(arw)} rad/s/√Hz, BI {_fmt(bi)} rad/s, "
                 f"RRW {_fmt(rrw)} rad/s²/√Hz")
        ax.loglog(t, s, "o-", ms=2.5, lw=1.0, color=c, label=label)
        tt = np.array([t[0], t[-1]])
        if math.isfinite(arw):
            ax.loglog(tt, arw / np.sqrt(tt), "--", color=c, lw=0.8)
            ax.plot([1.0], [arw], "s", color=c, mfc="none")
        if math.isfinite(bi):
            ax.loglog(tt, np.full(2, bi * FLICKER_FACTOR), ":", color=c, lw=0.8)
        if math.isfinite(rrw):
            ax.loglog(tt, rrw * np.sqrt(tt / 3.0), "-.", color=c, lw=0.8)
            ax.plot([3.0], [rrw], "^", color=c, mfc="none")
    ax.set_xlabel("τ (s)")
    ax.set_ylabel("Allan deviation (rad/s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title or "Overlapping Allan deviation (−½: ARW at 1 s, 0: bias instability, +½: RRW at 3 s)",
                 fontsize=8)
    return fig


def _fmt(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.3g}"
