"""The judgement of rest on real public logs (:mod:`diffgyro.motion`), as a user runs it.

``real_logs.json`` beside this file lists each log: where it comes from (repository, path,
commit, licence), what it is (``motion``, ``rest`` or ``spin``: a steady spin beside rest),
the evidence for that independent of diffgyro, the command-line options its format needs,
and facts its reference reader gives (pyulog, pymavlink, rosbags, pandas): the mean gyro
over the whole log (rest) or over its rest intervals (spin), in rad/s. The logs themselves
are not part of the project; point ``--data`` at a folder that holds them under the names
the list gives.

For every log the script runs ``diffgyro fit LOG --model bias_poly(0) --json`` and
``diffgyro export`` of its calibration, and checks:

* ``motion``: no device ``ok``, and ``export --format px4`` refuses the calibration; and
  the same with the log thinned to about 10 Hz (every k-th sample, as a logger that
  writes the sensor at a lower rate than it samples keeps it: a low-rate log of the
  same motion);
* ``rest``: every device ``ok`` and judged ``at_rest``, its bias the reference mean (the
  status of the log thinned to about 10 Hz is reported);
* ``spin``: the plain fit not ``ok``; with ``--static-only`` the fit ``ok``, none of the
  rest it kept within the spin, and its bias the reference's mean over the reference's
  rest intervals to within four standard errors of a mean of the kept samples (the
  share of the kept time inside those intervals is reported: the reference's intervals,
  from the accelerometer and magnetometer alone, are stricter than rest needs).

    python benchmarks/real_logs.py --data DIR --json benchmarks/results/real-logs-judgement.json
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

LIST = Path(__file__).with_name("real_logs.json")


def _run(args: list[str]) -> tuple[int, str, str]:
    from diffgyro.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main(args)
        except SystemExit as exc:  # typer's exit
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


def _fit(path: Path, options: list[str], *extra: str) -> tuple[dict, Path]:
    cal = Path(tempfile.mkdtemp()) / "cal.json"
    code, out, err = _run(["fit", str(path), "--model", "bias_poly(0)", "--json", "--out",
                           str(cal), *options, *extra])
    if code != 0:
        raise RuntimeError(f"{path}: fit exited {code}: {err.strip()}")
    return json.loads(out), cal


def _inside(spans: list[list[float]], rest: list[list[float]], t0: float) -> float:
    """Share of the kept time (``spans``: [start, end, length]) inside the reference rest
    intervals (``rest``: [start, end] from the log's start ``t0``)."""
    kept = inside = 0.0
    for start, end, _ in spans:
        kept += end - start
        for a, b in rest:
            inside += max(0.0, min(end, t0 + b) - max(start, t0 + a))
    return inside / kept if kept > 0 else 0.0


def judge(entry: dict, data: Path) -> dict:
    path = data / entry["file"]
    doc, cal = _fit(path, entry["options"])
    devices = doc["devices"]
    row = {"file": entry["file"], "category": entry["category"], "rate_hz": entry["rate_hz"],
           "devices": [{k: d.get(k) for k in ("device", "status", "status_detail")}
                       | {"verdict": (d.get("motion") or {}).get("verdict"),
                          "c0": [d["params"][ax]["bias_poly(0).c0"] for ax in "xyz"]}
                       for d in devices]}
    if entry["category"] == "motion":
        code, _, err = _run(["export", str(cal), "--format", "px4"])
        row["export_refused"] = code == 2
        row["export_error"] = err.strip().splitlines()[-1] if err.strip() else ""
        low = _thinned(path, entry["options"], entry["rate_hz"])
        row["thinned"] = low
        row["pass"] = (all(d["status"] != "ok" for d in devices) and code == 2
                       and all(d["status"] != "ok" for d in low["devices"]))
    elif entry["category"] == "rest":
        ref = np.asarray(entry["reference_mean_rad_s"], float)
        got = np.asarray(row["devices"][0]["c0"], float)
        row["c0_minus_reference"] = (got - ref).tolist()
        row["thinned"] = _thinned(path, entry["options"], entry["rate_hz"])  # reported only
        row["pass"] = (all(d["status"] == "ok" and d["verdict"] == "at_rest" for d in row["devices"])
                       and bool(np.allclose(got, ref, rtol=0, atol=1e-9)))
    else:  # spin
        plain = all(d["status"] != "ok" for d in devices)
        static, _ = _fit(path, entry["options"], "--static-only")
        dev = static["devices"][0]
        spans = dev["motion"].get("rest_intervals") or []
        t0 = _first_time(path)
        share = _inside(spans, entry["rest_intervals_s"], t0)
        spun = _inside(spans, [[a - 0.5, b + 0.5] for a, b in entry["spin_intervals_s"]], t0)
        ref = np.asarray(entry["reference_mean_rad_s"], float)
        got = np.asarray([dev["params"][ax]["bias_poly(0).c0"] for ax in "xyz"], float)
        se = dev["motion"]["rest_noise"] / np.sqrt(dev["n_samples"])
        row.update(static_status=dev["status"], rest_kept_s=dev["motion"].get("rest_kept_s"),
                   rest_intervals=spans, kept_inside_reference_rest=share, kept_in_spin=spun,
                   c0_static=got.tolist(), c0_minus_reference_rest_mean=(got - ref).tolist(),
                   standard_error=se)
        row["pass"] = (plain and dev["status"] == "ok" and spun == 0.0
                       and bool(np.all(np.abs(got - ref) <= 4 * se)))
    return row


def _thinned(path: Path, options: list[str], rate: float, target: float = 10.0) -> dict:
    """The fit of the log thinned to about ``target`` Hz (every k-th sample), as CSV."""
    from diffgyro.cli._load import load_from_cli

    opts = dict(zip(options[::2], options[1::2]))
    recs = load_from_cli([path], opts.get("--columns"), opts.get("--gyro-unit"),
                         opts.get("--acc-unit"), batch=False)
    k = max(1, int(round(rate / target)))
    folder = Path(tempfile.mkdtemp())
    frames = []
    for r in recs:
        frames.append(r.to_frame().iloc[::k])  # (its device column names the device)
    import pandas as pd

    csv = folder / "thinned.csv"
    pd.concat(frames).to_csv(csv, index=False)
    doc, cal = _fit(csv, ["--gyro-unit", "rad/s", "--acc-unit", "m/s²"])  # as written: SI
    code, _, _ = _run(["export", str(cal), "--format", "px4"])
    return {"every": k, "rate_hz": rate / k, "export_refused": code == 2,
            "devices": [{k2: d.get(k2) for k2 in ("device", "status", "status_detail")}
                        for d in doc["devices"]]}


def _first_time(path: Path) -> float:
    """The log's first time stamp as diffgyro reads it (the reference intervals count from
    the log's start)."""
    from diffgyro.io import load

    return float(np.asarray(load([path])[0].t)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, type=Path, help="folder holding the logs")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    import diffgyro

    diffgyro.enable_x64()
    rows = []
    for entry in json.loads(LIST.read_text()):
        if not (args.data / entry["file"]).exists():
            print(f"{entry['file']}: not in {args.data}, skipped", file=sys.stderr)
            continue
        row = judge(entry, args.data)
        rows.append(row)
        st = ", ".join(f"{d['status']}" for d in row["devices"])
        low = row.get("thinned")
        st += "" if low is None else (f"; at {low['rate_hz']:.1f} Hz: "
                                      + ", ".join(d["status"] for d in low["devices"]))
        print(f"{'PASS' if row['pass'] else 'FAIL'}  {row['category']:6s} {row['rate_hz']:7.1f} Hz  "
              f"{entry['file']}: {st}" + (f"; static-only {row['static_status']}, "
                                          f"{100 * row['kept_inside_reference_rest']:.0f} % of the kept "
                                          f"rest inside the reference's" if "static_status" in row else ""))
    print(f"{sum(r['pass'] for r in rows)} of {len(rows)} logs judged as their evidence says")
    if args.json:
        args.json.write_text(json.dumps({"logs": rows}, indent=1))


if __name__ == "__main__":
    main()
