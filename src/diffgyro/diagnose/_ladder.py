"""The auto ladder (``diagnose --auto``): add the named effect until every device is adequate."""

from __future__ import annotations

import html as _html
from dataclasses import dataclass

import numpy as np

from .._jsonio import number
from .._temperature import suggest_dtemp_window
from ..data import Batch, Recording, as_batch
from ..model import ErrorModel
from ._candidates import added_term
from ._decision import NOT_JUDGED
from ._results import Diagnosis
from ._run import diagnose
from ._thresholds import Thresholds


@dataclass
class LadderStep:
    """One rung: the model, the effect added to reach it, and per-device numbers."""

    spec: str
    added: str | None
    heldout_rms: list[float]
    noise_floor: list[float]
    rms: list[float]
    verdicts: list[str]

    def record(self, devices) -> dict:
        return {"spec": self.spec, "added": self.added,
                "devices": [{"device": dev, "heldout_rms": number(h), "rms": number(r),
                             "noise_floor": number(f), "verdict": v}
                            for dev, h, r, f, v in zip(devices, self.heldout_rms, self.rms,
                                                       self.noise_floor, self.verdicts)]}


@dataclass
class Ladder:
    """Held-out RMS as terms are added, from the base model to an adequate one."""

    devices: list[str]
    steps: list[LadderStep]
    first: Diagnosis   # diagnosis of the base model
    final: Diagnosis   # diagnosis of the last deterministic model

    @property
    def spec(self) -> str:
        return self.steps[-1].spec

    def records(self) -> list[dict]:
        return [s.record(self.devices) for s in self.steps]

    def table_rows(self) -> list[tuple[str, str, float, float, int]]:
        """(added, spec, median held-out, median floor, adequate count) per rung."""
        return [(s.added or "(base)", s.spec, float(np.median(s.heldout_rms)),
                 float(np.median(s.noise_floor)), sum(v == "adequate" for v in s.verdicts))
                for s in self.steps]

    def html_table(self) -> str:

        rows = "".join(
            f"<tr><td class=l>{_html.escape(a)}</td><td class=l><code>{_html.escape(sp)}</code></td>"
            f"<td>{h:.3g}</td><td>{f:.3g}</td><td>{k}/{len(self.devices)}</td></tr>"
            for a, sp, h, f, k in self.table_rows())
        return ("<table><tr><th class=l>added</th><th class=l>model</th><th>median held-out RMS</th>"
                f"<th>median noise floor</th><th>adequate</th></tr>{rows}</table>")


def _step(diag: Diagnosis, added: str | None) -> LadderStep:
    return LadderStep(spec=diag.spec, added=added,
                      heldout_rms=[d.heldout_rms for d in diag.devices],
                      noise_floor=[d.noise_floor for d in diag.devices],
                      rms=[d.rms for d in diag.devices], verdicts=[d.verdict for d in diag.devices])


def choose_effect(diag: Diagnosis) -> tuple[str, str] | None:
    """(effect, spec) to add for a batch: the effect named best by most devices missing one
    (ties: the lower median held-out RMS), in the spec most of those devices chose.

    **Arguments:**

    - ``diag``: the batch's :class:`Diagnosis`.
    """
    votes: dict[str, list[tuple[float, str]]] = {}
    for d in diag.devices:
        if d.verdict == "missing_effect" and d.best is not None:
            votes.setdefault(d.best.effect, []).append(
                (d.best.heldout_rms / max(d.white_noise_rms, 1e-300), d.best.spec))
    if not votes:
        return None
    effect = min(votes, key=lambda k: (-len(votes[k]), float(np.median([v for v, _ in votes[k]]))))
    specs = [sp for _, sp in votes[effect]]
    return effect, max(dict.fromkeys(specs), key=specs.count)


def diagnose_auto(
    model: ErrorModel | str,
    batch: Batch | Recording | list[Recording],
    candidates: list[str] | None = None,
    *,
    max_steps: int = 6,
    thresholds: Thresholds | None = None,
    progress=None,
    **fit_options,
) -> Ladder:
    """Repeat "add the best significant candidate" until every device is adequate.

    One model for the whole batch: each rung adds the effect that most
    devices missing an effect name as their best. A random walk ends the
    ladder (its rung reports the smoother's held-out numbers). ``progress``
    is called with a line of text before each diagnosis and each of its stages.

    **Arguments:**

    - ``model``: the starting model: a spec string or an
      :class:`~diffgyro.model.ErrorModel`.
    - ``batch``: a Batch, one Recording or a list of them.
    - ``candidates``: the effects tried (default: every registered effect the data
      supports).
    - ``max_steps``: rungs at most.
    - ``thresholds``: the decision's :class:`Thresholds`.
    - ``progress``: called with a line of text before each diagnosis and each of its stages.
    - ``**fit_options``: fit options, as for :func:`diagnose`.
    """

    if isinstance(model, str):
        model = ErrorModel.from_spec(model)
    batch = as_batch(batch)
    th = thresholds or Thresholds()
    if "dtemp_window" not in fit_options:
        fit_options["dtemp_window"] = suggest_dtemp_window(batch)
    say = progress or (lambda _text: None)
    say(f"diagnosing {model.spec}")
    diag = diagnose(model, batch, candidates, thresholds=th, progress=progress, **fit_options)
    first = diag
    steps = [_step(diag, None)]
    for _ in range(max_steps):
        choice = choose_effect(diag)
        if choice is None:
            break
        effect, spec = choice
        if ErrorModel.from_spec(spec).noise is not None:  # the walk: the last rung
            rws = [d.random_walk for d in diag.devices]
            h = [c.heldout_rms if c is not None else d.heldout_rms for c, d in zip(rws, diag.devices)]
            w = [d.white_noise_rms for d in diag.devices]
            verdicts = [d.verdict if d.verdict == NOT_JUDGED
                        else "adequate" if (hh**2 - ww**2) / max(ww**2, 1e-300) < th.excess_min
                        else "missing_effect" for hh, ww, d in zip(h, w, diag.devices)]
            steps.append(LadderStep(spec=spec, added=effect,
                                    heldout_rms=h, noise_floor=[d.noise_floor for d in diag.devices],
                                    rms=[c.rms if c is not None else d.rms for c, d in zip(rws, diag.devices)],
                                    verdicts=verdicts))
            break
        added = added_term(diag.spec, spec)
        say(f"adding {added}: diagnosing {spec}")
        diag = diagnose(spec, batch, candidates, thresholds=th, progress=progress, **fit_options)
        steps.append(_step(diag, added))
    return Ladder(devices=[d.device for d in first.devices], steps=steps, first=first, final=diag)
