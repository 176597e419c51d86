"""What the judgement of rest adds to the commands that read it: `diagnose`, `noise`, `allan`.

On the README walkthrough's recordings (a thermal batch of 2 devices × 7200 samples, a
static recording of 12 000 samples), each command is run warm in one process (its
output discarded) and the motion check of the same recording timed beside it (medians of
``--repeats``): the check's share of the command is what the command would save without
it (goal: within 10 %).

    python benchmarks/motion_share.py --json benchmarks/results/motion-share-cpu.json
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

import diffgyro

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the shared timing
from _timing import cpu_name, median_time  # noqa: E402


def _command(args: list[str]) -> None:
    from diffgyro.cli import main

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        try:
            code = main(args)
        except SystemExit as exc:
            code = exc.code
    if code not in (0, None):
        raise RuntimeError(f"diffgyro {' '.join(args)} exited {code}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--json")
    args = ap.parse_args()
    diffgyro.enable_x64()
    diffgyro.enable_compilation_cache()
    from diffgyro.io import load_batch
    from diffgyro.motion import motion_check

    work = Path(tempfile.mkdtemp())
    thermal, static = work / "x.csv", work / "static.csv"
    _command(["simulate", "--plan", "thermal", "--devices", "2", "--duration", "3600", "--rate",
              "2", "--effects", "bias_poly(2)+gradient", "--out", str(thermal)])
    _command(["simulate", "--plan", "static", "--devices", "1", "--duration", "1200", "--rate",
              "10", "--noise", "rrw=2e-5", "--out", str(static)])
    rows = []
    for name, command, path in (
            ("diagnose", ["diagnose", str(thermal), "--model", "bias_poly(2)", "--json"], thermal),
            ("noise", ["noise", str(static), "--json"], static),
            ("allan", ["allan", str(static), "--json"], static)):
        whole = median_time(lambda c=command: _command(c), args.repeats)
        batch = load_batch([path])
        check = median_time(lambda b=batch: motion_check(b), args.repeats)
        rows.append({"command": name, "command_s": whole, "check_s": check,
                     "check_share": check / whole})
        print(f"{name:10s} {whole:7.3f} s, of which the check {check:7.4f} s "
              f"({100 * check / whole:.1f} %)")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"rows": rows, "machine": cpu_name()}, fh,
                      indent=1)


if __name__ == "__main__":
    main()
