"""False alarms and detections of the judgement of rest (:mod:`diffgyro.motion`).

Every recording of the simulator's ``static`` and ``thermal`` plans is at rest: a verdict
``in_motion`` on one is a false alarm (goal ≤ 1 %); ``unverified`` is counted apart (a
recording too short or too slowly sampled to show rest: the honest answer, but not ``ok``).
Recordings that moved are counted as detected when their verdict is not ``at_rest`` (a
fit of them is not ``ok`` and ``export`` refuses it), and their ``in_motion`` share is
given too:

* the ``attitude`` plan (rotations about random axes with pauses, at up to 180 °/s);
* a steady spin: a static recording turned about the vertical at a constant 0.5 rad/s
  from a third of the recording on (its spin-up over a second);
* short knocks: three bursts of 0.3 s of a 15 Hz oscillation of 1 rad/s about x;
* a slow turn of 5° about x over 20 s and back after 20 s, the accelerometer's gravity
  turned with it.

Each class at 5, 10, 20, 100 and 200 Hz and 10 s, 1 min and 1 h: the recordings at rest
``--seeds`` devices each (default 100), the moving ones ``--motion-seeds`` (default 20),
checked in batches of 25.

``--fit SPEC`` judges each batch as a fit of that model does (``fit(SPEC, batch).motion``:
by what the fitted model leaves, docs/rest.md rule 7) instead of the recording alone.

    python benchmarks/motion_false_alarms.py --json benchmarks/results/motion-false-alarms.json
    python benchmarks/motion_false_alarms.py --seeds 10 --durations 10,60   # a quick look
    python benchmarks/motion_false_alarms.py --fit 'bias_poly(2)' --json benchmarks/results/motion-false-alarms-fit.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

import diffgyro
from diffgyro.motion import AT_REST, IN_MOTION, UNVERIFIED, motion_check
from diffgyro.simulate import simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the shared helpers
from _timing import cpu_name  # noqa: E402

RATES = (5.0, 10.0, 20.0, 100.0, 200.0)
DURATIONS = (10.0, 60.0, 3600.0)
CHUNK = 25  # devices simulated at once


def _rest(plan: str, n: int, rate: float, duration: float, seed: int):
    """``n`` devices of ``plan``, simulated ``CHUNK`` at a time (a batch each, made as it is
    needed: an hour at 200 Hz is 2 GB a batch)."""
    for k in range(0, n, CHUNK):  # a gyro log: without the plan's rate reference
        yield _without_reference(simulate(plan, min(CHUNK, n - k), seed=seed + k,
                                          sample_rate=rate, duration=duration)[0])


def _turned(batch, kind: str, rng):
    """``batch`` (at rest, +z up) with a motion of ``kind`` added to its gyro (and, for a
    tilt, its accelerometer)."""
    t = np.asarray(batch.t)
    gyro = np.array(batch.gyro)
    accel = None if batch.accel is None else np.array(batch.accel)
    span = t[:, -1:] - t[:, :1]
    rel = t - t[:, :1]
    if kind == "spin":  # about the vertical: gravity does not change
        start = span / 3.0
        rate = 0.5 * np.clip(rel - start, 0.0, 1.0)
        gyro[..., 2] += rate
    elif kind == "knocks":
        for start in rng.uniform(0.1, 0.9, (3,)):
            on = (rel >= start * span) & (rel < start * span + 0.3)
            gyro[..., 0] += np.where(on, np.sin(2 * np.pi * 15.0 * (rel - start * span)), 0.0)
    elif kind == "slow_turn":  # 5° about x over 20 s, 20 s still, back over 20 s
        start = span / 4.0
        u = rel - start
        rate = math.radians(5.0) / 20.0
        w = np.where((u >= 0) & (u < 20), rate, 0.0) - np.where((u >= 40) & (u < 60), rate, 0.0)
        gyro[..., 0] += w
        if accel is not None:
            ang = np.cumsum(w, axis=1) * np.diff(t, axis=1, prepend=t[:, :1])
            c, s = np.cos(ang), np.sin(ang)
            ay, az = accel[..., 1].copy(), accel[..., 2].copy()
            accel[..., 1], accel[..., 2] = c * ay + s * az, -s * ay + c * az
    import equinox as eqx

    out = eqx.tree_at(lambda b: b.gyro, batch, gyro)
    if accel is not None:
        out = eqx.tree_at(lambda b: b.accel, out, accel)
    return out


def _without_reference(batch):
    import equinox as eqx

    return eqx.tree_at(lambda b: b.rate, batch, None, is_leaf=lambda x: x is None)


def _verdict(batch, spec: str | None) -> np.ndarray:
    """Each device's verdict: of the recording alone (``spec`` None), or as a fit of the
    model ``spec`` gives it."""
    if spec is None:
        return np.asarray(motion_check(batch).verdict)
    from diffgyro.fit import fit

    return np.asarray(fit(spec, batch).motion.verdict)


def _verdicts(batches, spec: str | None) -> np.ndarray:
    return np.concatenate([_verdict(b, spec) for b in batches])


def run(seeds: int, rates, durations, motion_seeds: int, spec: str | None = None) -> list[dict]:
    rows = []
    rng = np.random.default_rng(0)
    for duration in durations:
        for rate in rates:
            t0 = time.perf_counter()
            row = {"rate_hz": rate, "duration_s": duration, "devices": seeds,
                   "moving_devices": motion_seeds}
            for plan in ("static", "thermal"):
                v = _verdicts(_rest(plan, seeds, rate, duration, 1000), spec)
                row[f"{plan}_false_alarm"] = float(np.mean(v == IN_MOTION))
                row[f"{plan}_unverified"] = float(np.mean(v == UNVERIFIED))
            v = _verdicts(_rest("attitude", motion_seeds, rate, duration, 2000), spec)
            row["attitude_detected"] = float(np.mean(v != AT_REST))
            row["attitude_in_motion"] = float(np.mean(v == IN_MOTION))
            # the turn of a slow turn and its return take 60 s
            kinds = ("spin", "knocks") + (("slow_turn",) if duration >= 90 else ())
            got = {kind: [] for kind in kinds}
            for b in _rest("static", motion_seeds, rate, duration, 3000):
                for kind in kinds:
                    got[kind].append(_verdict(_turned(b, kind, rng), spec))
            for kind, parts in got.items():
                v = np.concatenate(parts)
                row[f"{kind}_detected"] = float(np.mean(v != AT_REST))
                row[f"{kind}_in_motion"] = float(np.mean(v == IN_MOTION))
            row["seconds"] = round(time.perf_counter() - t0, 1)
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def table(rows: list[dict]) -> str:
    cols = ["rate_hz", "duration_s", "static_false_alarm", "thermal_false_alarm", "static_unverified",
            "thermal_unverified", "attitude_detected", "spin_detected", "knocks_detected",
            "slow_turn_detected"]
    head = "| " + " | ".join(cols) + " |\n|" + "---|" * len(cols) + "\n"

    def f(r, c):
        v = r.get(c)
        return "—" if v is None else f"{v:g}" if c in ("rate_hz", "duration_s") else f"{100 * v:.0f} %"

    return head + "".join("| " + " | ".join(f(r, c) for c in cols) + " |\n" for r in rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=100)
    ap.add_argument("--motion-seeds", type=int, default=20)
    ap.add_argument("--rates", default=",".join(f"{r:g}" for r in RATES))
    ap.add_argument("--durations", default=",".join(f"{d:g}" for d in DURATIONS))
    ap.add_argument("--fit", help="judge as a fit of this model does (default: the recording alone)")
    ap.add_argument("--json")
    args = ap.parse_args()
    diffgyro.enable_x64()
    rows = run(args.seeds, [float(x) for x in args.rates.split(",")],
               [float(x) for x in args.durations.split(",")], args.motion_seeds, args.fit)
    worst = max(max(r["static_false_alarm"], r["thermal_false_alarm"]) for r in rows)
    print(table(rows))
    print(f"largest false-alarm rate: {100 * worst:.1f} % (goal ≤ 1 %)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"rows": rows, "machine": cpu_name(),
                       "goal": "false alarms ≤ 1 %", "largest_false_alarm": worst,
                       "judged_by": f"fit({args.fit!r})" if args.fit else "the recording"}, fh, indent=1)


if __name__ == "__main__":
    main()
