"""The diagnosis as data: one candidate, one device, a batch; JSON records."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import equinox as eqx
import numpy as np

from .._jsonio import number, to_json_safe
from ..model import ErrorModel
from ._thresholds import Thresholds


class AllanCurves(eqx.Module):
    """Overlapping Allan deviation of the residuals: ``tau``, ``adev`` (devices, 3, k)."""

    tau: np.ndarray
    adev: np.ndarray


@dataclass
class Candidate:
    """One candidate of one device: held-out RMS of the model with the term added, and the test."""

    effect: str
    spec: str
    heldout_rms: float
    significant: bool
    gain: float          # held-out MSE gain / floor MSE
    closure: float       # share of (base held-out MSE − floor MSE) closed
    t: float             # paired t over the folds
    folds_improved: int
    rms: float           # in-sample RMS with the term
    tau: float | None = None  # chosen time constant (s), for nonlinear terms
    family: str | None = None
    stochastic: bool = False
    note: str = ""
    term: str = ""       # the term added or raised, as written in a spec (``scale_poly(1)``)

    def record(self) -> dict:
        out = {"effect": self.effect, "spec": self.spec, "heldout_rms": number(self.heldout_rms),
               "significant": bool(self.significant), "gain": number(self.gain),
               "closure": number(self.closure), "t": number(self.t),
               "folds_improved": self.folds_improved, "rms": number(self.rms)}
        if self.term:
            out["term"] = self.term
        if self.tau is not None:
            out["tau"] = number(self.tau)
        if self.family:
            out["family"] = self.family
        if self.note:
            out["note"] = self.note
        return out


@dataclass
class DeviceDiagnosis:
    device: str
    status: str
    rms: float
    heldout_rms: float
    white_noise_rms: float         # the level the decision uses (:func:`.floor.white_noise_rms`)
    white_noise_axes: list[float]
    floor_allan: float
    verdict: str
    candidates: list[Candidate]
    best: Candidate | None
    alternatives: list[Candidate]
    random_walk: Candidate | None
    allan_slope: float
    evidence: dict = field(default_factory=dict)
    explanation: str = ""
    skipped: dict = field(default_factory=dict)
    #: The model-free floor ``fit`` reports for the device (:mod:`diffgyro._noise`).
    noise_floor: float = math.nan
    noise_axes: list[float] = field(default_factory=list)
    #: The second term the next round is expected to add after ``best`` (:mod:`.greedy`),
    #: scored as the pair base + best + next against the base model; None when not needed.
    next: Candidate | None = None
    #: The base fit's status in words (:func:`diffgyro.status.explain`): why a device is not
    #: ``ok`` and, then, why its verdict is ``not_judged``.
    status_detail: str = ""
    #: The residual's stochastic model, the ``noise --json`` entry (:mod:`.noise_model`).
    noise: dict | None = None
    #: The process that entry holds: white, gauss_markov, random_walk or both; None unknown.
    noise_process: str | None = None

    @property
    def excess(self) -> float:
        """Held-out MSE above the white-noise level, as a fraction of it."""
        w2 = self.white_noise_rms**2
        return (self.heldout_rms**2 - w2) / max(w2, 1e-300)

    @property
    def verdict_detail(self) -> str:
        """The verdict in words: ``not_judged`` says why (the base fit's status)."""
        if self.verdict == "not_judged":
            return f"not judged: the base fit is not ok ({self.status_detail or self.status})"
        return self.verdict

    def record(self) -> dict:
        return {
            "device": self.device, "rms": number(self.rms), "heldout_rms": number(self.heldout_rms),
            "noise_floor": number(self.noise_floor), "verdict": self.verdict,
            "candidates": [c.record() for c in self.candidates],
            "status": self.status,
            "status_detail": self.status_detail or self.status,
            "verdict_detail": self.verdict_detail,
            "best": self.best.spec if self.best else None,
            "best_effect": self.best.effect if self.best else None,
            "best_term": self.best.term if self.best else None,
            "alternatives": [{"effect": c.effect, "spec": c.spec, "heldout_rms": number(c.heldout_rms)}
                             for c in self.alternatives],
            "noise_floor_axes": [number(v) for v in self.noise_axes],
            "white_noise_rms": number(self.white_noise_rms),
            "white_noise_rms_axes": [number(v) for v in self.white_noise_axes],
            "noise_floor_allan": number(self.floor_allan),
            "excess": number(self.excess),
            "allan_slope": number(self.allan_slope),
            "random_walk": self.random_walk.record() if self.random_walk else None,
            "next": self.next.record() if self.next else None,
            "evidence": self.evidence,
            "skipped": self.skipped,
            "explanation": self.explanation,
            "noise": self.noise,
            "noise_process": self.noise_process,
        }


@dataclass
class Diagnosis:
    """Diagnosis of every device of a batch against ``model``."""

    model: ErrorModel
    devices: list[DeviceDiagnosis]
    fit: object  # FitResult of the base model
    residuals: np.ndarray  # (d, n, 3), padding zeroed
    allan: object  # AllanCurves of the residuals (tau, adev), leading axes (d, 3)
    thresholds: Thresholds
    options: dict = field(default_factory=dict)
    #: Per-fold numbers behind every decision (re-decide with other thresholds: :func:`redecide`).
    raw: dict = field(default_factory=dict, repr=False)

    @property
    def spec(self) -> str:
        return self.model.spec

    def device(self, key: int | str) -> DeviceDiagnosis:
        if isinstance(key, int):
            return self.devices[key]
        for d in self.devices:
            if d.device == key:
                return d
        raise KeyError(key)

    def to_json(self) -> dict:
        """The ``diagnose --json`` object (extra keys per device)."""
        motion = getattr(self.fit, "motion", None)
        devices = [d.record() | {"motion": None if motion is None else motion.record(i)}
                   for i, d in enumerate(self.devices)]
        for d, params in zip(devices, self._params()):
            d["params"] = params
        channel = getattr(self.fit, "channel", "gyro")
        return to_json_safe({"model": self.spec, "devices": devices,
                       "thresholds": asdict(self.thresholds),
                       "dtemp_window": self.options.get("dtemp_window")}
                            | ({} if channel == "gyro" else {"channel": channel}))

    def _params(self) -> list[dict]:
        """Every device's base-fit coefficients as ``fit --json`` writes them (``params``)."""
        fit = self.fit
        if fit is None or not hasattr(fit, "param_dict"):
            return [{} for _ in self.devices]
        if fit.model.n_nonlinear:
            return [fit.param_dict(i) for i in range(len(self.devices))]
        labels = fit.model.param_labels()
        beta = np.asarray(fit.params.beta, float)
        return [{ax: {lab: float(v) for lab, v in zip(labels[k], beta[i, k])}
                 for k, ax in enumerate("xyz")} for i in range(len(self.devices))]

    def records(self) -> list[dict]:
        """One JSON-ready record per device (the ``devices`` list of :meth:`to_json`)."""
        return self.to_json()["devices"]

    def verdicts(self) -> dict[str, int]:
        out = {"adequate": 0, "missing_effect": 0, "not_judged": 0}
        for d in self.devices:
            out[d.verdict] += 1
        return out
