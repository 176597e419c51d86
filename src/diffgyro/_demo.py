"""The model-discovery loop end to end, on a small simulated batch with a hidden effect.

:func:`run_demo` simulates four MEMS gyros in a thermal chamber whose bias
also follows dT/dt (``gradient``, hidden), fits the thermal polynomial alone,
diagnoses it (the residual separates heating from cooling and follows dT/dt),
adds the named effect, refits, and writes the HTML report with the ladder.
Sized to finish within a minute on a 2-core machine without a GPU, compile
included: 2 h at 1 Hz per device, one bucket length, two models.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

from .diagnose import diagnose_auto
from .report import write_report
from .simulate import demo_batch

#: The hidden truth and the model the demo starts from.
TRUTH = "bias_poly(2)+gradient"
BASE = "bias_poly(2)"


@dataclass
class DemoResult:
    ladder: object          # diffgyro.diagnose.Ladder
    batch: object           # the simulated Batch
    truth: object           # its simulate.Truth
    report: Path | None
    seconds: dict = field(default_factory=dict)

    @property
    def added(self) -> list[str]:
        return [s.added for s in self.ladder.steps if s.added]


def run_demo(out_dir: str | Path | None = "diffgyro-demo", n_devices: int = 4, seed: int = 3,
             progress=None) -> DemoResult:
    """Simulate, fit ``BASE``, diagnose, add the named effect, refit, write the report.

    ``progress(text)`` is called before each stage. Returns the ladder, the
    batch and truth, the report path (``None`` when ``out_dir`` is None) and
    the seconds each stage took.
    """

    say = progress or (lambda _t: None)
    secs: dict[str, float] = {}
    t0 = time.perf_counter()
    say(f"simulating {n_devices} gyros in a thermal chamber (hidden effect)")
    batch, truth = demo_batch(n_devices=n_devices, seed=seed, effects=TRUTH)
    secs["simulate"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ladder = diagnose_auto(BASE, batch, max_steps=3, progress=say)
    secs["fit + diagnose"] = time.perf_counter() - t0

    path = None
    if out_dir is not None:

        t0 = time.perf_counter()
        say(f"writing the report to {out_dir}/")
        write_report(ladder.first, batch, out_dir, ladder=ladder)
        path = Path(out_dir) / "index.html"
        secs["report"] = time.perf_counter() - t0
    return DemoResult(ladder=ladder, batch=batch, truth=truth, report=path, seconds=secs)


__all__ = ["BASE", "TRUTH", "DemoResult", "run_demo"]
