"""What a record can resolve: components below or beyond it, parameters it does not determine.

A record of n samples every dt seconds sees the rate at scales from dt to about
n·dt/4 (the longest dyadic scale). A fitted component is only as good as
those scales let it be:

* a first-order Gauss–Markov process of correlation time T below
  :data:`SHORT_SAMPLES` sample intervals decorrelates within a few samples:
  at this sampling it is white noise (or the sensor's own output filter). Over
  any scale a filter integrates (many samples), the sampled AR(1) process of
  stationary variance σ² and φ = exp(−dt/T) adds the white density
  ``σ²·dt·(1+φ)/(1−φ)`` (its spectrum at zero frequency; 2σ²T for T ≫ dt).
  The process is merged into the white part with that variance
  (:func:`merge_short`); its split from the white noise is what the record
  cannot give (the two fit the short scales almost alike, the white part's
  interval then spans dozens of decades);
* a correlation time beyond :data:`LONG_SHARE` of the record puts the peak of the
  process' Allan deviation (at τ ≈ 1.9 T) at or past the longest scale: the bias
  only rises over the record, which a random walk or ramp describes as well.
  Such candidates are left out of the structure choice (the compiled step of
  :mod:`.identify`);
* a parameter whose 95 % interval spans more than :data:`SPAN_LIMIT` (two
  decades) is ``not_identified``, with the reason;
* a random walk (or ramp) too small to raise the criterion by its penalty is not
  resolvable: :func:`.identify`'s limit ``K² = √penalty · se(K²)`` with se the
  standard error of a walk's power added to the chosen model at zero (the
  efficient weight of that model). A walk of that size lowers the objective by
  the penalty on average: about even odds of being chosen, a smaller one
  mostly unseen. It scales as the white density over the record length.

Units (one notation): the white density N in rad/s/√Hz and °/√h, the random walk
K in rad/s²/√Hz (= rad/s/√s) and °/h/√h (:data:`DISPLAY`).
"""

from __future__ import annotations

import math

import numpy as np

#: Level of every interval.
INTERVAL_LEVEL = 0.95
#: A Gauss–Markov correlation time below this many sample intervals is white noise.
SHORT_SAMPLES = 3.0
#: A Gauss–Markov correlation time beyond this share of the record is a random walk or ramp.
LONG_SHARE = 0.1
#: Ratio hi/lo of a 95 % interval beyond which a parameter is not identified.
SPAN_LIMIT = 100.0

_DEG = 180.0 / math.pi
#: Per parameter: (SI unit, the same unit otherwise written, display factor, display unit).
DISPLAY = {
    "arw": ("rad/s/√Hz", "rad/√s", _DEG * 60.0, "°/√h"),
    "q": ("rad", None, 1e6, "µrad"),
    "sigma": ("rad/s", None, _DEG * 3600.0, "°/h"),
    "tau": ("s", None, 1.0, "s"),
    "rrw": ("rad/s²/√Hz", "rad/s/√s", _DEG * 3600.0 * 60.0, "°/h/√h"),
    "r": ("rad/s²", None, _DEG * 3600.0**2, "°/h²"),
}


def gm_white_power(sigma2, tau, dt):
    """White density² (rad²/s) that a sampled Gauss–Markov process (σ², T) adds at long
    scales: σ²·dt·(1+φ)/(1−φ), φ = exp(−dt/T).

    **Arguments:**

    - ``sigma2``: the process' variance σ², (rad/s)².
    - ``tau``: its correlation time T, s.
    - ``dt``: the sampling interval, s.
    """
    a = dt / tau
    one_phi = -math.expm1(-a)
    return sigma2 * dt * (2.0 - one_phi) / one_phi


def short_limit(dt: float) -> float:
    """Shortest correlation time the record resolves (s)."""
    return SHORT_SAMPLES * dt


def long_limit(record: float) -> float:
    """Longest correlation time the record resolves (s)."""
    return LONG_SHARE * record


def merge_short(theta, cov, mask, dt):
    """(θ, cov, mask, merged) with every Gauss–Markov process of T below :func:`short_limit`
    merged into the white part: log N² ← log(N² + σ²dt(1+φ)/(1−φ)), its variance by the delta
    method on the log-parameters; ``merged``: (σ, T) of each process merged."""
    theta = np.array(theta, np.float64)
    cov = np.array(cov, np.float64)
    mask = np.array(mask, bool)
    merged = []
    for iv, it in ((2, 3), (4, 5)):
        if not (mask[iv] and mask[0]):
            continue
        tau = math.exp(theta[it])
        if not tau < short_limit(dt):
            continue
        n2, s2 = math.exp(theta[0]), math.exp(theta[iv])
        a = dt / tau
        one_phi = -math.expm1(-a)
        c = dt * (2.0 - one_phi) / one_phi
        total = n2 + s2 * c
        grad = np.zeros(len(theta))
        grad[0] = n2 / total
        grad[iv] = s2 * c / total
        # T·dc/dT = 2·dt·φ·(dt/T)/(1−φ)²
        grad[it] = s2 * 2.0 * dt * (1.0 - one_phi) * a / one_phi**2 / total
        jac = np.eye(len(theta))
        jac[0] = grad
        cov = jac @ cov @ jac.T
        theta[0] = math.log(total)
        mask[iv] = mask[it] = False
        cov[[iv, it], :] = 0.0
        cov[:, [iv, it]] = 0.0
        merged.append((math.sqrt(s2), tau))
    return theta, cov, mask, merged


def judge(name: str, p: dict) -> dict:
    """``p`` ({"value", "ci", "unit"}) with ``status`` (``identified`` or ``not_identified``
    and ``why``) and ``display`` (the value and interval in display units)."""
    _, same, k, unit = DISPLAY[name]
    lo, hi = p["ci"]
    v = p["value"]
    out = dict(p)
    if same:
        out["same_as"] = same
    sc = lambda x: None if x is None else x * k  # noqa: E731
    out["display"] = {"value": sc(v), "ci": [sc(lo), sc(hi)], "unit": unit}
    if v is None or lo is None or hi is None or not lo > 0:
        out.update(status="not_identified", why="no finite 95 % interval: the record does not "
                                                "determine it")
    elif hi / lo > SPAN_LIMIT:
        out.update(status="not_identified",
                   why=f"its 95 % interval [{lo:.3g}, {hi:.3g}] {p['unit']} spans "
                       f"{math.log10(hi / lo):.3g} decades (more than {math.log10(SPAN_LIMIT):g}): "
                       "the record does not determine it")
    else:
        out["status"] = "identified"
    return out


def fmt_time(t: float) -> str:
    """A time for a sentence: ms below 1 s, s below an hour, then h."""
    if t < 1.0:
        return f"{t * 1e3:.3g} ms"
    if t < 3600.0:
        return f"{t:.3g} s"
    return f"{t / 3600.0:.3g} h"


def notes(resolution: dict, structure: list[str]) -> list[str]:
    """The sentences of a ``resolution`` object: what was merged or left out and why, what
    this record cannot see."""
    out = []
    dt, record = resolution["sample_interval"], resolution["record_length"]
    lo, hi = resolution["gauss_markov_tau"]["min"], resolution["gauss_markov_tau"]["max"]
    for m in resolution["merged"]:
        out.append(f"a Gauss–Markov process of τ {fmt_time(m['tau'])} (σ {m['sigma']:.3g} rad/s) is "
                   f"below {SHORT_SAMPLES:g} sample intervals ({fmt_time(lo)}): white noise at "
                   f"{1.0 / dt:.4g} Hz, merged into the white part (σ²·dt·(1+φ)/(1−φ))")
    for e in resolution["excluded"]:
        out.append(f"{e['structure']} scores {e['better_by']:.3g} lower on the criterion but its "
                   f"Gauss–Markov τ {fmt_time(e['tau'])} is beyond {LONG_SHARE:g} of the {fmt_time(record)} "
                   "record: a bias that slow reads as a random walk or ramp here")
    k = resolution.get("random_walk_limit")
    if k is not None and "random_walk" not in structure:
        out.append(f"a random walk below K = {k['value']:.2g} rad/s²/√Hz (= rad/s/√s; "
                   f"{k['display']['value']:.2g} °/h/√h) is not resolvable in {fmt_time(record)}")
    r = resolution.get("rate_ramp_limit")
    if r is not None and "rate_ramp" not in structure:
        out.append(f"a rate ramp below R = {r['value']:.2g} rad/s² ({r['display']['value']:.2g} °/h²) "
                   f"is not resolvable in {fmt_time(record)}")
    for c in resolution.get("close", ()):
        out.append(f"{c['structure']} is within {c['likelihood_delta']:.2g} of the chosen structure on "
                   "the block means' likelihood criterion: this record hardly tells the two apart")
    out.append(f"a Gauss–Markov bias is resolvable only with τ between {fmt_time(lo)} and "
               f"{fmt_time(hi)}")
    return out


def limit_param(name: str, value: float) -> dict | None:
    """{"value", "unit", "display"} of a detection limit (None if not finite)."""
    if not (value is not None and math.isfinite(value) and value > 0):
        return None
    unit, same, k, dunit = DISPLAY[name]
    out = {"value": float(value), "unit": unit}
    if same:
        out["same_as"] = same
    out["display"] = {"value": float(value) * k, "unit": dunit}
    return out
