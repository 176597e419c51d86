"""Term synthesis: its cost inside diagnose and its false-proposal rate.

    python benchmarks/synthesis.py                       # quick sizes, prints a table
    python benchmarks/synthesis.py --noise-devices 300 --json benchmarks/results/synthesis.json

Three measurements, every diagnose timed warm (its programs compiled by a first call):

- ``diagnose``: the benchmark's diagnose case (``run.py``: thermal plan, bias ∝ dT/dt hidden
  beyond ``bias_poly(2)``, every candidate) with and without synthesis. A built-in term
  closes the gap there, so synthesis only checks that it need not run.
- ``outside``: the five outside-the-vocabulary cases of ``tests/grammar_catalogue.py``,
  where synthesis runs and proposes a term: the worst case of its cost.
- ``noise_only``: devices whose base model is right, with Gauss–Markov, random-walk or
  flicker-like noise, through the full diagnose (synthesis where diagnose runs it): how
  many get a synthesised term.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def timed(fn, repeats: int = 2) -> float:
    fn()  # compile
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--devices", type=int, default=8)
    p.add_argument("--samples", type=int, default=5000)
    p.add_argument("--noise-devices", type=int, default=102)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)

    import diffgyro
    from diffgyro.data import Batch
    from diffgyro.diagnose import diagnose
    from diffgyro.simulate import simulate

    diffgyro.enable_x64()
    import grammar_catalogue as gc

    out: dict = {"devices": args.devices, "samples": args.samples, "rows": []}
    batch, _ = simulate("thermal", args.devices, effects="bias_poly(2)+gradient", seed=6,
                        sample_rate=1.0, duration=float(args.samples))
    off = timed(lambda: diagnose("bias_poly(2)", batch, synthesis=False))
    on = timed(lambda: diagnose("bias_poly(2)", batch))
    out["rows"].append({"case": "diagnose", "off_s": off, "on_s": on, "ratio": on / off})
    for name, case in gc.CASES.items():
        b = Batch.from_recordings([gc.make(name, 0)[0]])
        off = timed(lambda c=case, b=b: diagnose(c.base, b, synthesis=False), 1)
        on = timed(lambda c=case, b=b: diagnose(c.base, b), 1)
        best = diagnose(case.base, b).devices[0].best
        out["rows"].append({"case": f"outside:{name}", "off_s": off, "on_s": on,
                            "ratio": on / off, "proposed": best.spec if best else None})
    noisy = Batch.from_recordings(gc.noise_only(args.noise_devices, seed=11, n=2000))
    t0 = time.perf_counter()
    dg = diagnose(gc.NOISE_BASE, noisy)
    got = [d.device for d in dg.devices if d.best is not None and d.best.effect == "term"]
    out["noise_only"] = {"devices": args.noise_devices, "synthesised": len(got),
                         "rate": len(got) / args.noise_devices, "which": got,
                         "seconds": time.perf_counter() - t0}
    for r in out["rows"]:
        print(f"{r['case']:<16} off {r['off_s']:7.2f} s   on {r['on_s']:7.2f} s   "
              f"× {r['ratio']:.2f}   {r.get('proposed') or ''}")
    print(f"noise only: {len(got)} of {args.noise_devices} devices got a synthesised term")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
