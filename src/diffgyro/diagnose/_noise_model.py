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
(``noise="auto"``) it runs only on residuals that are not white: those the
decision could not explain (no deterministic term named: the random walk best,
or nothing) and those it read ``adequate`` whose held-out error is still
``excess_min`` or more above the white-noise level (a coloured noise no term
should follow, :func:`not_white`). ``noise=True`` identifies every judged
device, ``False`` none.

A device whose residual holds a Gauss–Markov process, with no deterministic
term significant and the correlation time well inside the record (at most
:data:`TAU_SHARE` of it, where a slow deterministic drift cannot pass for it),
and no logged signal that the residual follows closely (an effect outside the
vocabulary, :mod:`.evidence`) reads ``adequate``: the deterministic model is
right, and what is left is noise the filter must carry. A random walk alone keeps today's verdict (the
walk is best, ``missing_effect``): its smoother is scored on held-out folds.

The deterministic candidates, and where none closes the gap the terms synthesised
from the recording's signals (:mod:`.synthesis`), are then scored against the
identified noise, not the white floor alone (on a device read ``adequate`` against the
white floor, the synthesised terms only): no deterministic term predicts a Gauss–Markov bias whose
correlation time is far shorter than a fold block, so the held-out error of the right
model is the white floor plus the process' stationary variance σ². The decision is
re-run with that floor (per axis, white² + Σσ² of the Gauss–Markov processes inside
:data:`TAU_SHARE` of the record): a term must close the gap above the noise the
residual really holds. Where that decision names a deterministic term, it replaces
the white-floor one: a missing effect smaller than the bias' variance, which closes
too little of the gap above the white floor to count there, is named. Where it names
none, the rules above give the verdict (a slow effect that the identified process
partly absorbs is then not declared adequate by the raised floor alone). A product of
logged signals that closes the gap (temperature × specific force: a g-sensitivity that
changes with temperature, which the identification alone reads as a Gauss–Markov
process of minutes) is so proposed as a term, never named noise.
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
    """No deterministic term named and the residual not white."""
    return d.verdict == "missing_effect" and (d.best is None or d.best.stochastic)


def not_white(d: DeviceDiagnosis, excess_min: float) -> bool:
    """The auto rule: no term explains a residual that is not white, or the verdict is
    ``adequate`` while the held-out MSE is ``excess_min`` (a fraction of the white level's)
    or more above the white-noise level: the residual holds coloured noise."""
    if _unexplained(d):
        return True
    return d.verdict == "adequate" and math.isfinite(d.excess) and d.excess >= excess_min


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


def _ci(p: dict) -> str:
    lo, hi = p.get("ci") or (None, None)
    return "" if lo is None or hi is None else f" [{lo:.3g}, {hi:.3g}]"


def _words(entry: dict) -> str:
    """The Gauss–Markov processes of an entry, per axis: σ and τ with their intervals
    (the entry's ``interval_level``), as the JSON's ``noise`` object holds them."""
    out = []
    for ax, axis in (entry.get("axes") or {}).items():
        for c in axis["components"]:
            if c["kind"] == "gauss_markov":
                s, t = c["params"]["sigma"], c["params"]["tau"]
                if s["value"] is None or t["value"] is None:
                    out.append(f"{ax}: not identified")
                    continue
                out.append(f"{ax}: σ {s['value']:.3g}{_ci(s)} rad/s, τ {t['value']:.3g}{_ci(t)} s")
    if not out:
        return ""
    level = entry.get("interval_level")
    return "; ".join(out) + (f" ({level:.0%} intervals)" if level else "")


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


def residual_floor(e, t, white_axes) -> np.ndarray:
    """Per axis, the floor² (rad²/s²) of a residual ``e`` (n, 3) at times ``t``: the white
    level ``white_axes`` (3,) squared plus the power of the Gauss–Markov processes its
    identified noise holds inside :data:`TAU_SHARE` of the record (none: the white level)."""
    n = e.shape[0]
    tt = np.asarray(t, np.float64)[:n]
    entries, _ = identify_devices(np.asarray(e, np.float64)[None], [n], tt[None], ["residual"])
    gm = gauss_markov_power(entries[0], float(tt[-1] - tt[0])) if entries[0]["status"] == "ok" \
        else np.zeros(3)
    return np.square(np.asarray(white_axes, np.float64)) + gm


def not_identified(device: str, why: str) -> dict:
    """The ``noise`` object of a device whose residual was not identified."""
    return {"device": device, "status": "not_identified", "status_detail": why, "axes": None}


def attach_noise(devices: list[DeviceDiagnosis], residuals, n_valid, t, mode="auto",
                 rescore=None, excess_min: float = 0.15) -> None:
    """Identify the residual noise of the devices ``mode`` selects and set each device's
    ``noise`` (the ``noise --json`` entry), ``noise_process`` and, where a Gauss–Markov
    process explains what no term closes, the verdict (module docstring). ``rescore(i,
    floor_axes, builtin)``: device i's decision with the per-axis floor given, a synthesised
    term tried where no built-in term closes the gap (None: not re-run; ``builtin`` False
    for a device read adequate: its decision kept unless a term is synthesised, else None);
    ``excess_min``: the auto rule's excess (:func:`not_white`)."""

    if mode is False or mode is None:
        pick = []
    elif mode is True:
        pick = [i for i, d in enumerate(devices) if d.verdict != "not_judged"]
    else:
        pick = [i for i, d in enumerate(devices) if not_white(d, excess_min)]
    for i, d in enumerate(devices):
        if i not in pick:
            why = ("the base fit is not ok" if d.verdict == "not_judged" else
                   "not asked (diagnose(noise=False))" if mode is False or mode is None else
                   "a term explains the residual or it is white: the noise model is identified "
                   "only where no term does and the residual is not white (diagnose --noise, "
                   "diagnose(noise=True), for every device)")
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
        # read adequate against the white floor: the built-in terms are not scored again (on
        # noise-only devices a raised floor let a term of the thermal family through), only
        # a synthesised product judged against the noise it leaves can replace the verdict
        builtin = d.verdict != "adequate"
        process, tau, tau_hi = _process(entry)
        n = int(nv[k])
        total = float(tt[k, n - 1] - tt[k, 0])
        gm = gauss_markov_power(entry, total)
        if rescore is not None and gm.any() and not _follows_a_signal(d):
            alt = rescore(i, np.sqrt(np.square(d.white_noise_axes) + gm), builtin)
            if alt is not None and alt.best is not None and not alt.best.stochastic:
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
        else:
            d.explanation += " " + noise_sentence(entry, process, d.best is not None)


def noise_sentence(entry: dict, process: str, term_named: bool) -> str:
    """The sentence an explanation ends with: the residual's noise model in words (σ and τ
    of every Gauss–Markov process with their intervals)."""
    whose = "the base model's residual" if term_named else "the residual"
    if process == "white":
        return f"Noise model of {whose}: white (no correlated noise resolved)."
    words = _words(entry)
    name = " + ".join({"gauss_markov": "Gauss–Markov", "random_walk": "random walk"}[k]
                      for k in process.split("+"))
    return (f"Noise model of {whose}: {name}"
            + (f" ({words})." if words else "."))


def _against_noise(white: DeviceDiagnosis, d: DeviceDiagnosis) -> DeviceDiagnosis:
    """The decision re-run against the identified noise (``d``, which names a deterministic
    term), keeping what the white-floor decision reported of the device: its white level and
    model-free floor (the greedy pair is not re-scored)."""
    d.white_noise_rms, d.white_noise_axes = white.white_noise_rms, white.white_noise_axes
    d.noise_floor, d.noise_axes = white.noise_floor, white.noise_axes
    d.explanation += (" Scored against the residual's identified noise (white + Gauss–Markov), "
                      "not the white floor alone.")
    return d
