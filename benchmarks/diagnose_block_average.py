"""Segment means change no verdict on the test catalogue.

``diagnose`` works on segment means of a long record in two places (see
docs/diagnose.md): the random-walk check smooths the base residual's means
past ``diffgyro.diagnose._random_walk.RW_POINTS`` samples (``--check
random_walk``), and a time constant's grid is searched on the means past
``diffgyro.diagnose._scoring.SEARCH_POINTS`` (``--check search``). This script
diagnoses every problem of the catalogue of ``tests/test_diagnose.py``
(recordings of ``tests/hidden_effects.py``, 2 Hz, a few thousand to tens of
thousands of samples) twice, sample by sample (the limit past every record's
length) and with the limit at ``--points`` (default: its value in diffgyro),
and compares the verdicts, the effect named, its held-out RMS and the random
walk's held-out RMS.

    python benchmarks/diagnose_block_average.py --check search --points 4096 --out results/x.json
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
    best = d.best
    return {"device": d.device, "verdict": d.verdict, "best": best.effect if best else None,
            "heldout_rms": d.heldout_rms, "best_heldout_rms": best.heldout_rms if best else None,
            "best_tau": best.tau if best else None, "rw_heldout_rms": rw.heldout_rms if rw else None,
            "rw_significant": bool(rw.significant) if rw else None}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", choices=("random_walk", "search"), default="random_walk",
                    help="which segment means: the random-walk check's or the time-constant search's")
    ap.add_argument("--points", type=int, help="the limit of the second run (default: diffgyro's)")
    ap.add_argument("--out", type=Path, help="results JSON")
    args = ap.parse_args(argv)

    import diffgyro

    diffgyro.enable_x64()
    from diffgyro.data import Batch
    from diffgyro.diagnose import _random_walk as rw_mod
    from diffgyro.diagnose import _scoring as scoring
    from diffgyro.diagnose import diagnose

    mod, name = (rw_mod, "RW_POINTS") if args.check == "random_walk" else (scoring, "SEARCH_POINTS")
    default = getattr(mod, name)
    points = args.points or default
    rows, t0 = [], time.perf_counter()
    for base, part in _groups():
        batch = Batch.from_recordings([h.recording for h in part])
        length = int(batch.t.shape[1])
        runs = []
        for pts in (1 << 30, points):  # sample by sample, then segment means
            setattr(mod, name, pts)
            try:
                runs.append(diagnose(base, batch))
            finally:
                setattr(mod, name, default)
        m = scoring.segment_length(length, runs[0].options["n_blocks"], points)
        for h, a, b in zip(part, runs[0].devices, runs[1].devices):
            rows.append({"effect": h.effect, "samples": int(h.recording.t.shape[0]), "segment": m,
                         "sample_level": _summary(a), "block_averaged": _summary(b)})
    same = [r["sample_level"]["verdict"] == r["block_averaged"]["verdict"]
            and r["sample_level"]["best"] == r["block_averaged"]["best"] for r in rows]
    ratio = [r["block_averaged"]["rw_heldout_rms"] / r["sample_level"]["rw_heldout_rms"]
             for r in rows if r["sample_level"]["rw_heldout_rms"]]
    held = [r["block_averaged"]["best_heldout_rms"] / r["sample_level"]["best_heldout_rms"]
            for r in rows if r["sample_level"]["best_heldout_rms"] and r["block_averaged"]["best_heldout_rms"]]
    out = {"check": args.check, "devices": len(rows), "points": points, "default_points": default,
           "same_verdict_and_effect": int(sum(same)),
           "changed": [r for r, s in zip(rows, same) if not s],
           "rw_heldout_ratio": {"min": float(np.min(ratio)), "median": float(np.median(ratio)),
                                "max": float(np.max(ratio))},
           "heldout_ratio": {"min": float(np.min(held)), "median": float(np.median(held)),
                             "max": float(np.max(held))},
           "segment_lengths": sorted({r["segment"] for r in rows}),
           "seconds": time.perf_counter() - t0, "rows": rows}
    print(f"{out['same_verdict_and_effect']}/{out['devices']} devices: same verdict and effect; "
          f"segments of {out['segment_lengths']} samples; named term's held-out RMS ratio "
          f"{out['heldout_ratio']}; "
          f"random walk held-out RMS ratio {out['rw_heldout_ratio']}")
    if args.out:
        from diffgyro._jsonio import atomic_write_text, dumps

        atomic_write_text(args.out, dumps(out, indent=1))
    return 0 if all(same) else 1


if __name__ == "__main__":
    raise SystemExit(main())
