"""The random-walk check on a block-averaged residual changes no verdict on the test catalogue.

``diagnose`` smooths the base residual on segment means once a record is
longer than ``diffgyro.diagnose.random_walk.RW_POINTS`` samples (see
docs/diagnose.md). This script diagnoses every problem of the catalogue of
``tests/test_diagnose.py`` (recordings of ``tests/hidden_effects.py``, 2 Hz,
a few thousand to tens of thousands of samples) twice, sample by sample
(``RW_POINTS`` past every record's length) and with ``RW_POINTS`` at
``--points`` (default: its value in diffgyro), and compares the verdicts,
the effect named and the random walk's held-out RMS.

    python benchmarks/diagnose_block_average.py --out results/x.json
"""

from __future__ import annotations

import argparse
import math
import sys
import time
import zlib
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def _groups():
    """The catalogue of tests/test_diagnose.py, grouped by (plan, base) in batches of 16."""
    import hidden_effects as H
    from test_diagnose import _problems

    groups: dict[tuple[str, str], list] = {}
    for plan, base, eff, k in _problems():
        seed = zlib.crc32(f"{plan}|{base}|{eff}|{k}".encode())
        rng = np.random.default_rng(seed)
        noise = H.draw_noise(rng)
        size = float(np.exp(rng.uniform(math.log(0.5), math.log(3.0))))
        h = H.make_recording(plan, eff, base, seed, size=size, noise=noise, device=f"{plan}-{eff}-{k}")
        groups.setdefault((plan, base), []).append(h)
    for (_plan, base), hs in groups.items():
        for start in range(0, len(hs), 16):
            yield base, hs[start:start + 16]


def _summary(d) -> dict:
    rw = d.random_walk
    return {"device": d.device, "verdict": d.verdict, "best": d.best.effect if d.best else None,
            "heldout_rms": d.heldout_rms, "rw_heldout_rms": rw.heldout_rms if rw else None,
            "rw_significant": bool(rw.significant) if rw else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, help="RW_POINTS of the second run (default: diffgyro's)")
    ap.add_argument("--out", type=Path, help="results JSON")
    args = ap.parse_args(argv)

    import diffgyro

    diffgyro.enable_x64()
    from diffgyro.data import Batch
    from diffgyro.diagnose import diagnose
    from diffgyro.diagnose import random_walk as rw_mod

    default = rw_mod.RW_POINTS
    points = args.points or default
    rows, t0 = [], time.perf_counter()
    for base, part in _groups():
        batch = Batch.from_recordings([h.recording for h in part])
        length = int(batch.t.shape[1])
        runs = []
        for pts in (1 << 30, points):  # sample by sample, then segment means
            rw_mod.RW_POINTS = pts
            try:
                runs.append(diagnose(base, batch))
            finally:
                rw_mod.RW_POINTS = default
        m = rw_mod.segment_length(length, runs[0].options["n_blocks"], points)
        for h, a, b in zip(part, runs[0].devices, runs[1].devices):
            rows.append({"effect": h.effect, "samples": int(h.recording.t.shape[0]), "segment": m,
                         "sample_level": _summary(a), "block_averaged": _summary(b)})
    same = [r["sample_level"]["verdict"] == r["block_averaged"]["verdict"]
            and r["sample_level"]["best"] == r["block_averaged"]["best"] for r in rows]
    ratio = [r["block_averaged"]["rw_heldout_rms"] / r["sample_level"]["rw_heldout_rms"]
             for r in rows if r["sample_level"]["rw_heldout_rms"]]
    out = {"devices": len(rows), "points": points, "default_points": default,
           "same_verdict_and_effect": int(sum(same)),
           "changed": [r for r, s in zip(rows, same) if not s],
           "rw_heldout_ratio": {"min": float(np.min(ratio)), "median": float(np.median(ratio)),
                                "max": float(np.max(ratio))},
           "segment_lengths": sorted({r["segment"] for r in rows}),
           "seconds": time.perf_counter() - t0, "rows": rows}
    print(f"{out['same_verdict_and_effect']}/{out['devices']} devices: same verdict and effect; "
          f"segments of {out['segment_lengths']} samples; random walk held-out RMS ratio "
          f"{out['rw_heldout_ratio']}")
    if args.out:
        from diffgyro.jsonio import atomic_write_text, dumps

        atomic_write_text(args.out, dumps(out, indent=1))
    return 0 if all(same) else 1


if __name__ == "__main__":
    raise SystemExit(main())
