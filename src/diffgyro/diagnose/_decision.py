"""The decision of one device from its per-fold numbers: significance, ranking, verdict."""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass

import numpy as np

from ..model import ErrorModel
from ._candidates import added_term
from ._evidence import OUTSIDE, explain
from ._results import Candidate, DeviceDiagnosis
from ._thresholds import Thresholds, family_of


@dataclass
class _Scorer:
    """Scores a candidate's per-fold held-out SSE against the base model's (one device)."""

    cnt: np.ndarray          # (f,) held-out samples per fold
    base_fold: np.ndarray    # (f, 3) base held-out SSE
    f2: float                # floor MSE
    n_valid: int
    th: Thresholds
    blocks: dict | None
    base_spec: str | None

    def __post_init__(self):
        self.n_held = max(float(np.sum(self.cnt)), 1.0)
        self.mse_b = self.base_fold.sum(-1) / np.maximum(3 * self.cnt, 1.0)  # (f,)
        self.hb2 = float(self.base_fold.sum() / (3 * self.n_held))
        self.gap = self.hb2 - self.f2
        self.excess = self.gap / self.f2

    def local(self, j) -> bool:
        """Material where it happens: in the blocks the candidate improves most."""
        th, f2, blocks = self.th, self.f2, self.blocks
        if blocks is None or j is None:
            return False
        bc, bb, cb = blocks["cnt"], blocks["base"], blocks["cand"][j]
        if not (np.all(np.isfinite(cb)) and bc.sum() > 0):
            return False
        k = max(2, int(math.ceil(th.local_share * len(bc))))
        top = np.argsort(bb - cb)[-k:]
        nb = max(3.0 * float(bc[top].sum()), 1.0)
        mb, mc = float(bb[top].sum()) / nb, float(cb[top].sum()) / nb
        return (mb - f2) / f2 >= th.local_excess and (mb - mc) / max(mb - f2, 1e-300) >= th.local_closure

    def score(self, effect, spec, fold_sse, full_sse, tau=None, stochastic=False, j=None) -> Candidate:
        th, f2, gap, hb2 = self.th, self.f2, self.gap, self.hb2
        mse_c = fold_sse.sum(-1) / np.maximum(3 * self.cnt, 1.0)
        hc2 = float(fold_sse.sum() / (3 * self.n_held))
        diff = self.mse_b - mse_c
        sd = float(np.std(diff, ddof=1)) if diff.size > 1 else 0.0
        mean = float(np.mean(diff))
        t = mean / (sd / math.sqrt(diff.size)) if sd > 0 else (math.inf if mean > 0 else 0.0)
        gain = (hb2 - hc2) / f2
        closure = (hb2 - hc2) / gap if gap > 0.01 * f2 else 0.0
        steady = mean > 0 and (t >= th.t_min or float(np.min(diff)) >= -th.consistency * mean)
        material = self.excess >= th.excess_min and closure >= th.closure_min and gain >= th.gain_min
        if (not material and not stochastic and gain >= th.local_gain_min
                and closure >= th.local_closure_min):
            material = self.local(j)
        sig = bool(math.isfinite(hc2) and steady and material)
        n = 3 * max(self.n_valid, 1)
        return Candidate(effect=effect, spec=spec, heldout_rms=math.sqrt(max(hc2, 0.0)),
                         significant=sig, gain=gain, closure=closure, t=t,
                         folds_improved=int(np.sum(diff > 0)),
                         rms=math.sqrt(max(float(full_sse.sum()) / n, 0.0)),
                         tau=tau, family=family_of(effect), stochastic=stochastic,
                         term=added_term(self.base_spec, spec) if self.base_spec else effect)


SLOW_EDGE = "time constant at the slow end of the search: a slow drift rather than a transient"


def _walk_competes(closure: float, rw_c: Candidate, th: Thresholds) -> bool:
    """The random walk competes unless the physical term(s) close ``rw_prefer`` of the gap or
    leave less than ``rw_ratio`` times the gap the walk leaves."""
    return closure < th.rw_prefer and 1.0 - closure > th.rw_ratio * (1.0 - rw_c.closure)


def outside_share(ev: dict) -> float:
    """The largest share of the gap a signal outside the vocabulary explains (evidence)."""
    return max((float(ev[k].get("explains", 0.0)) for k in OUTSIDE if k in ev), default=0.0)


def _rank(det: list[Candidate], rw_c: Candidate | None, excess: float, slope: float,
          th: Thresholds, pair: tuple[str, Candidate] | None = None, ev: dict | None = None):
    """The candidates shown (sorted by held-out RMS), the best, its close alternatives, the
    verdict and the expected next term; the random walk competes only when no physical
    term, nor the best one followed by ``pair`` = (its spec, second term), closes the gap
    (a pair must close ``rw_prefer`` of it: with twice the freedom to follow a wandering
    residual, it is not offered the ``rw_ratio`` alternative)."""
    det_sig = [c for c in det if c.significant]
    # a term whose time constant ran to the slow end of its search fits a drift, not physics
    physical = [c for c in det_sig if c.note != SLOW_EDGE]
    best_phys = min(physical, key=lambda c: c.heldout_rms) if physical else None
    best_det = min(det_sig, key=lambda c: c.heldout_rms) if det_sig else None
    in_contention = rw_c is not None and (best_phys is None
                                          or _walk_competes(best_phys.closure, rw_c, th))
    nxt = None
    if (in_contention and pair is not None and best_phys is not None
            and pair[0] == best_phys.spec and pair[1].closure >= th.rw_prefer):
        in_contention, nxt, best_det = False, pair[1], best_phys  # the pair closes the gap
    ev = ev or {}
    outside = False
    if rw_c is not None:
        rw_c.significant = bool(rw_c.significant and in_contention and excess >= th.rw_excess_min
                                and math.isfinite(slope) and slope >= th.rw_slope_min)
        # the residual follows a signal no term is linear in: an unknown effect, not a walk
        outside = rw_c.significant and outside_share(ev) >= th.outside_share
        rw_c.significant = rw_c.significant and not outside
    shown = det + ([rw_c] if in_contention else [])
    shown.sort(key=lambda c: (c.heldout_rms if math.isfinite(c.heldout_rms) else math.inf))
    sig_all = [c for c in shown if c.significant]
    best = rw_c if rw_c is not None and rw_c.significant else best_det
    # far above the floor with no single term closing it: still not adequate
    verdict = ("missing_effect" if sig_all or outside or excess >= th.unexplained_excess
               else "adequate")
    alts = []
    if best is not None:
        alts = [c for c in sig_all if c is not best and c.closure >= th.alt_share * best.closure]
    return shown, best, alts, verdict, nxt


def decide(name: str, status: str, base_fold: np.ndarray, cnt: np.ndarray, base_full: np.ndarray,
           names: list[str], specs: list[str], cand_fold: np.ndarray, cand_full: np.ndarray,
           ok: np.ndarray, taus, rw_spec: str | None, rw_fold: np.ndarray, rw_full: np.ndarray,
           floor_axes: np.ndarray, floor_allan: float, slope: float, n_valid: int,
           th: Thresholds, ev: dict, blocks: dict | None = None,
           edge: np.ndarray | None = None, base_spec: str | None = None,
           pair=None, why: dict[int, str] | None = None) -> DeviceDiagnosis:
    """Scores, significance, ranking and verdict of one device from its per-fold numbers;
    ``pair`` (:class:`.greedy.Pair`): the best term followed by the best second term;
    ``why``: the reason this device's data cannot support candidate ``j`` (``skipped``),
    where ``ok[j]`` is false (a candidate not in it is left out of ``skipped``)."""
    floor = float(np.sqrt(np.mean(floor_axes**2)))
    sc = _Scorer(cnt=cnt, base_fold=base_fold, f2=max(floor**2, 1e-300), n_valid=n_valid, th=th,
                 blocks=blocks, base_spec=base_spec)
    rms_b = math.sqrt(max(float(np.sum(base_full)) / (3 * max(n_valid, 1)), 0.0))
    det: list[Candidate] = []
    skipped: dict = {}
    for j, (effect, spec) in enumerate(zip(names, specs)):
        if not ok[j]:
            if why and j in why:
                skipped[effect] = why[j]
            continue
        if not np.all(np.isfinite(cand_fold[j])):
            skipped[effect] = "the fit failed"
            continue
        det.append(sc.score(effect, spec, cand_fold[j], cand_full[j], tau=taus[j], j=j))
        if edge is not None and bool(edge[j]):
            det[-1].note = SLOW_EDGE
    rw_c = None
    if rw_spec:
        walk = ErrorModel.from_spec(rw_spec).noise.name  # random_walk, or a user's subclass of it
        rw_c = sc.score(walk, rw_spec, rw_fold, rw_full, stochastic=True)
        rw_c.note = ("local-level smoother of the residual; walk variance by maximum likelihood on "
                     "the training blocks")
    pair_c = None
    if pair is not None:
        sec = pair.second
        pair_c = sc.score(sec.effect, sec.spec, pair.fold_sse, pair.full_sse, tau=sec.tau)
        pair_c.term = sec.term
        pair_c.note = f"held-out numbers of the pair: the best term, then `{sec.term}`"
    shown, best, alts, verdict, nxt = _rank(
        det, rw_c, sc.excess, slope, th, None if pair_c is None else (pair.first, pair_c), ev)
    d = DeviceDiagnosis(
        device=name, status=status, rms=rms_b, heldout_rms=math.sqrt(max(sc.hb2, 0.0)),
        white_noise_rms=floor, white_noise_axes=[float(v) for v in floor_axes],
        floor_allan=floor_allan,
        verdict=verdict, candidates=shown, best=best, alternatives=alts, random_walk=rw_c,
        allan_slope=slope, evidence=ev, skipped=skipped, next=nxt)
    d.explanation = explain(d)
    return d


#: The verdict of a device whose base fit is not ``ok``: nothing is judged against a fit
#: the data do not support (too few samples, no range, collinear terms, motion ...).
NOT_JUDGED = "not_judged"
VERDICTS = ("adequate", "missing_effect", NOT_JUDGED)


def not_judged(name: str, status: str, status_detail: str, floor_axes: np.ndarray,
               rms: float = math.nan, heldout_rms: float = math.nan) -> DeviceDiagnosis:
    """A device whose base fit is not ``ok``: no verdict, no candidate, the reason said."""
    floor = float(np.sqrt(np.mean(floor_axes**2)))
    d = DeviceDiagnosis(
        device=name, status=status, rms=rms, heldout_rms=heldout_rms,
        white_noise_rms=floor, white_noise_axes=[float(v) for v in floor_axes],
        floor_allan=float("nan"), verdict=NOT_JUDGED,
        candidates=[], best=None, alternatives=[], random_walk=None, allan_slope=float("nan"),
        status_detail=status_detail)
    d.explanation = (f"{name}: not judged — the base fit is not ok ({status_detail}); no effect "
                     f"is named against a fit the data do not support: fix the recording or "
                     f"simplify the model (see `diffgyro fit`).")
    return d


def allan_slope(adev: np.ndarray, tau: np.ndarray, total: float) -> float:
    """Log-log slope of the residual's (axis-pooled) Allan deviation at long τ (T/100 .. T/8)."""
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        a2 = np.nanmean(adev**2, axis=0)
    t = tau[0]
    sel = np.isfinite(a2) & (a2 > 0) & (t >= total / 100.0) & (t <= total / 8.0)
    if sel.sum() < 3:
        return float("nan")
    return float(np.polyfit(np.log(t[sel]), 0.5 * np.log(a2[sel]), 1)[0])


def _edge_from_theta(r: dict):
    """Older saved rows: a time constant at a quarter of the record or more counts as the edge."""
    th = r.get("cand_theta")
    if th is None:
        return None
    total = float(r["n_valid"]) * 0.5
    return np.array([bool(np.isfinite(t[0]) and np.exp(t[0]) >= 0.2 * total) for t in th])


def redecide(row: dict, thresholds: Thresholds, rw_key: str = "rw_interp") -> dict:
    """Re-run the decision of one device from its saved per-fold numbers (threshold tuning).

    ``row`` holds ``raw`` (one device's slice of :attr:`Diagnosis.raw`),
    ``cand_names``, ``cand_specs`` and ``diag`` (its record). Returns the record
    the device would get with ``thresholds``. The greedy pair (:mod:`.greedy`) is not
    re-scored: its numbers are not saved, so this is the one-term rule.

    **Arguments:**

    - ``row``: one device's saved numbers: ``raw``, ``cand_names``, ``cand_specs`` and
      ``diag``.
    - ``thresholds``: the :class:`Thresholds` to decide with.
    - ``rw_key``: the key of the random walk's held-out error in ``raw``.
    """
    r = row["raw"]
    names, specs = row["cand_names"], row["cand_specs"]
    d = decide(row["diag"]["device"], row["diag"]["status"], r["base_sse"], r["cnt"], r["base_full"],
                names, specs, r["cand_sse"], r["cand_full"], r["ok"], [None] * len(names),
                row["diag"]["random_walk"]["spec"] if row["diag"].get("random_walk") else None,
                r[rw_key], r["rw_full"], r["floors"], float(r["floor_allan"]), float(r["slope"]),
                int(r["n_valid"]), thresholds, row["diag"].get("evidence", {}),
                blocks={"cnt": r["blk_cnt"], "base": r["base_blk"], "cand": r["cand_blk"]}
                if "blk_cnt" in r else None, edge=r.get("cand_edge", _edge_from_theta(r)),
                why={j: row["diag"]["skipped"][n] for j, n in enumerate(names)
                     if n in row["diag"].get("skipped", {})})
    d.noise_floor = row["diag"].get("noise_floor", math.nan)
    d.noise_axes = row["diag"].get("noise_floor_axes", [])
    return d.record()
