"""The noise the residual holds: the stochastic model of each device's base residual.

The random-walk check (:mod:`.random_walk`) asks one question of a residual
that is not white: does a local level follow it? A first-order Gauss–Markov
bias (a correlation time of seconds to minutes, the "bias instability" of a
MEMS datasheet) answers yes as well, or breaks the long-τ slope test and
leaves an excess no term closes. Here the residual's stochastic model is
identified (:mod:`diffgyro.stochastic`, the ``noise --json`` entry) and the
noise verdict names what it holds: ``white``, ``gauss_markov``,
``random_walk`` or ``gauss_markov+random_walk``.

The identification compiles once and costs seconds per device, so by default
(``noise="auto"``) it runs only on the residuals the decision could not
explain: no deterministic term named (the random walk best, or nothing).
``noise=True`` identifies every judged device, ``False`` none.

A device whose residual holds a Gauss–Markov process, with no deterministic
term significant and the correlation time well inside the record (at most
:data:`TAU_SHARE` of it, where a slow deterministic drift cannot pass for it),
and no logged signal that the residual follows closely (an effect outside the
vocabulary, :mod:`.evidence`) reads ``adequate``: the deterministic model is
right, and what is left is noise the filter must carry. A random walk alone keeps today's verdict (the
walk is best, ``missing_effect``): its smoother is scored on held-out folds.

The deterministic candidates are then scored against the identified noise, not the
white floor alone: no deterministic term predicts a Gauss–Markov bias whose
correlation time is far shorter than a fold block, so the held-out error of the right
model is the white floor plus the process' stationary variance σ². The decision is
re-run with that floor (per axis, white² + Σσ² of the Gauss–Markov processes inside
:data:`TAU_SHARE` of the record): a term must close the gap above the noise the
residual really holds. Where that decision names a deterministic term, it replaces
the white-floor one: a missing effect smaller than the bias' variance, which closes
too little of the gap above the white floor to count there, is named. Where it names
none, the rules above give the verdict (a slow effect that the identified process
partly absorbs is then not declared adequate by the raised floor alone).
"""

from __future__ import annotations

import math

import numpy as np

from ..stochastic import identify_devices
from ._evidence import followed_most
from ._results import DeviceDiagnosis

#: Longest Gauss–Markov correlation time, as a share of the record, that counts as noise:
#: longer, a slow deterministic drift fits the wavelet variance as well.
TAU_SHARE = 0.05
#: A logged signal the residual follows this closely (|r|, or η for a column) is an effect
#: outside the vocabulary, not noise: the decision stands.
FOLLOWED = 0.6
#: The values of ``noise_process``.
PROCESSES = ("white", "gauss_markov", "random_walk", "gauss_markov+random_walk")


def _unexplained(d: DeviceDiagnosis) -> bool:
    """No deterministic term named and the residual not white (the auto rule)."""
    return d.verdict == "missing_effect" and (d.best is None or d.best.stochastic)


def _follows_a_signal(d: DeviceDiagnosis) -> bool:
    """The residual follows a logged signal closely (:data:`FOLLOWED`) or one explains most
    of its excess (the evidence, :mod:`.evidence`)."""

    top = followed_most(d.evidence or {})
    if top is None:
        return False
    v = top[1]
    return max(abs(v["r"]), v.get("eta", 0.0)) >= FOLLOWED or v.get("explains", 0.0) >= 0.5


def _process(entry: dict) -> tuple[str, float | None, float | None]:
    """(process, longest Gauss–Markov τ and the upper end of its interval) over the three
    axes of one ``noise --json`` entry."""
    gm = rw = False
    tau, tau_hi = None, None
    for axis in (entry.get("axes") or {}).values():
        for c in axis["components"]:
            if c["kind"] == "gauss_markov":
                gm = True
                v, hi = c["params"]["tau"]["value"], c["params"]["tau"]["ci"][1]
                if v is not None and (tau is None or v > tau):
                    tau, tau_hi = v, hi
            elif c["kind"] in ("random_walk", "rate_ramp"):
                rw = True
    name = "gauss_markov+random_walk" if gm and rw else "gauss_markov" if gm else (
        "random_walk" if rw else "white")
    return name, tau, tau_hi


def _words(entry: dict) -> str:
    """The Gauss–Markov processes of an entry, per axis: σ and τ with τ's interval."""
    out = []
    for ax, axis in (entry.get("axes") or {}).items():
        for c in axis["components"]:
            if c["kind"] == "gauss_markov":
                s, t = c["params"]["sigma"], c["params"]["tau"]
                lo, hi = t["ci"]
                ci = "" if lo is None or hi is None else f" [{lo:.3g}, {hi:.3g}]"
                out.append(f"{ax}: σ {s['value']:.3g} rad/s, τ {t['value']:.3g} s{ci}")
    return "; ".join(out)


def gauss_markov_power(entry: dict, total: float) -> np.ndarray:
    """Per axis (x, y, z): Σσ² (rad²/s²) of the entry's Gauss–Markov processes whose correlation
    time is at most :data:`TAU_SHARE` of the record ``total`` (s); longer ones are drift."""
    out = np.zeros(3)
    for k, ax in enumerate("xyz"):
        for c in ((entry.get("axes") or {}).get(ax) or {}).get("components", []):
            if c["kind"] == "gauss_markov":
                s, tau = c["params"]["sigma"]["value"], c["params"]["tau"]["value"]
                if s is not None and tau is not None and tau <= TAU_SHARE * total:
                    out[k] += s * s
    return out


def not_identified(device: str, why: str) -> dict:
    """The ``noise`` object of a device whose residual was not identified."""
    return {"device": device, "status": "not_identified", "status_detail": why, "axes": None}


def attach_noise(devices: list[DeviceDiagnosis], residuals, n_valid, t, mode="auto",
                 rescore=None) -> None:
    """Identify the residual noise of the devices ``mode`` selects and set each device's
    ``noise`` (the ``noise --json`` entry), ``noise_process`` and, where a Gauss–Markov
    process explains what no term closes, the verdict (module docstring). ``rescore(i,
    floor_axes)``: device i's decision with the per-axis floor given (None: not re-run)."""

    if mode is False or mode is None:
        pick = []
    elif mode is True:
        pick = [i for i, d in enumerate(devices) if d.verdict != "not_judged"]
    else:
        pick = [i for i, d in enumerate(devices) if _unexplained(d)]
    for i, d in enumerate(devices):
        if i not in pick:
            why = ("the base fit is not ok" if d.verdict == "not_judged" else
                   "not asked (diagnose(noise=False))" if mode is False or mode is None else
                   "a term explains the residual or it is white: the noise model is identified "
                   "only where no term does (diagnose(noise=True) for every device)")
            d.noise = not_identified(d.device, why)
    if not pick:
        return
    values = np.asarray(residuals)[pick]
    nv = np.asarray(n_valid)[pick]
    tt = np.asarray(t)[pick]
    entries, _ = identify_devices(values, nv, tt, [devices[i].device for i in pick])
    for i, entry, k in zip(pick, entries, range(len(pick))):
        d = devices[i]
        d.noise = entry
        if entry["status"] != "ok":
            continue
        process, tau, tau_hi = _process(entry)
        n = int(nv[k])
        total = float(tt[k, n - 1] - tt[k, 0])
        gm = gauss_markov_power(entry, total)
        if rescore is not None and gm.any() and not _follows_a_signal(d):
            alt = rescore(i, np.sqrt(np.square(d.white_noise_axes) + gm))
            if alt.best is not None and not alt.best.stochastic:
                devices[i] = d = _against_noise(d, alt)
                d.noise = entry
        d.noise_process = process
        det_sig = any(c.significant and not c.stochastic for c in d.candidates)
        inside = tau is not None and tau_hi is not None and math.isfinite(tau_hi) \
            and tau <= TAU_SHARE * total
        if process == "gauss_markov" and inside and not det_sig and not _follows_a_signal(d):
            if d.random_walk is not None:
                d.random_walk.significant = False
            d.best, d.alternatives, d.verdict = None, [], "adequate"
            d.explanation = (
                f"{d.device}: adequate — the residual above the white-noise level is a "
                f"Gauss–Markov bias ({_words(entry)}), not a missing effect: no term closes "
                f"it and none is needed. Carry it in the filter's bias model (`diffgyro noise`, "
                f"`diffgyro export`).")
        elif process != "white":
            d.explanation += f" The residual's noise model: {process.replace('+', ' + ')}" + (
                f" ({_words(entry)})." if "gauss_markov" in process else ".")


def _against_noise(white: DeviceDiagnosis, d: DeviceDiagnosis) -> DeviceDiagnosis:
    """The decision re-run against the identified noise (``d``, which names a deterministic
    term), keeping what the white-floor decision reported of the device: its white level and
    model-free floor (the greedy pair is not re-scored)."""
    d.white_noise_rms, d.white_noise_axes = white.white_noise_rms, white.white_noise_axes
    d.noise_floor, d.noise_axes = white.noise_floor, white.noise_axes
    d.explanation += (" Scored against the residual's identified noise (white + Gauss–Markov), "
                      "not the white floor alone.")
    return d
