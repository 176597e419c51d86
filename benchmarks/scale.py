"""Scale benchmark: ``bias_poly(3)+gradient`` fitted to a fleet streamed from Parquet.

Simulates ``--devices`` gyros × ``--samples`` samples (the thermal-chamber plan)
into a directory of Parquet files (written once, file by file; an existing
dataset with the same settings is reused), then runs the streaming fit end to
end in a fresh process per measurement: indexing, reading, validation,
fitting, chunk files, merging into the calibration file and the results
table. Each run reports devices/s and the peak resident memory of its
process (``getrusage`` max RSS, JAX and XLA included). With ``--compare M``
(default 10 000) a run on the first M devices comes first, so the two peaks
can be compared: streaming keeps peak memory set by the chunk size.

    python benchmarks/scale.py --devices 100000            # the acceptance run
    python benchmarks/scale.py --devices 2000 --compare 500 # a quick look

Storage: device ids (dictionary-encoded), t, gx, gy, gz, temp as float64,
row groups of 250 devices; about 24 kB per device of 2 000 samples (the
simulated gyro output is quantised, so Parquet's dictionary encoding works).
This is a benchmark, not a test: results go to stdout and ``--json FILE``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

MODEL = "bias_poly(3)+gradient"
SAMPLE_RATE = 0.5          # Hz: ``samples`` samples span 2·samples seconds of the thermal plan
PER_FILE = 500             # devices per Parquet file
ROW_GROUP_DEVICES = 250    # devices per row group


def _file_name(k: int) -> str:
    return f"part-{k:05d}.parquet"


def generate(data: Path, devices: int, samples: int, seed: int) -> list[Path]:
    """Parquet files holding at least ``devices`` simulated devices (reused when present)."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    import diffgyro
    from diffgyro.simulate import simulate

    diffgyro.enable_x64()
    diffgyro.enable_compilation_cache()
    data.mkdir(parents=True, exist_ok=True)
    meta_path = data / "dataset.json"
    meta = {"model": MODEL, "samples": samples, "per_file": PER_FILE, "seed": seed,
            "sample_rate": SAMPLE_RATE}
    if meta_path.exists() and json.loads(meta_path.read_text()).get("settings") != meta:
        raise SystemExit(f"{data} holds a dataset with other settings; give another --data")
    meta_path.write_text(json.dumps({"settings": meta}))
    n_files = math.ceil(devices / PER_FILE)
    files, t0, made = [], time.monotonic(), 0
    for k in range(n_files):
        path = data / _file_name(k)
        files.append(path)
        if path.exists():
            continue
        batch, _ = simulate("thermal", PER_FILE, effects=MODEL, seed=seed + k,
                            sample_rate=SAMPLE_RATE, duration=samples / SAMPLE_RATE,
                            device_prefix=f"u{k:05d}-")
        n = int(batch.n_valid[0])
        assert n == samples and np.all(batch.n_valid == n), (n, samples)
        dev = pa.DictionaryArray.from_arrays(
            pa.array(np.repeat(np.arange(PER_FILE, dtype=np.int32), n)),
            pa.array(list(batch.devices)))
        table = pa.table({"device": dev, "t": batch.t[:, :n].ravel(),
                          "gx": batch.gyro[:, :n, 0].ravel(), "gy": batch.gyro[:, :n, 1].ravel(),
                          "gz": batch.gyro[:, :n, 2].ravel(), "temp": batch.temp[:, :n].ravel()})
        tmp = path.with_name("." + path.name + ".tmp")
        pq.write_table(table, tmp, row_group_size=ROW_GROUP_DEVICES * n)
        os.replace(tmp, path)
        made += 1
        if made % 10 == 0:
            rate = made * PER_FILE / (time.monotonic() - t0)
            print(f"  simulated {(k + 1) * PER_FILE} devices ({rate:.0f} devices/s)",
                  file=sys.stderr)
    return files


def run_fit(files: list[Path], out: Path, chunk: int) -> dict:
    """The streaming fit in a fresh process; its wall time, rate and peak memory."""
    args = {"files": [str(f) for f in files], "out": str(out), "chunk": chunk}
    proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(args)],
                          capture_output=True, text=True)
    if proc.returncode:
        raise SystemExit(f"fit run failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def child(args: dict) -> None:
    import diffgyro

    diffgyro.enable_x64()
    diffgyro.enable_compilation_cache()
    from diffgyro.pipeline import fit_dataset

    out = Path(args["out"])
    t0 = time.monotonic()
    summary = fit_dataset(args["files"], MODEL, out=out, chunk_devices=args["chunk"],
                          resume=False, progress=True)
    wall = time.monotonic() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # kB -> MB (Linux)
    rss_end = float("nan")
    try:
        with open("/proc/self/status") as fh:
            rss_end = next(int(x.split()[1]) for x in fh if x.startswith("VmRSS:")) / 1024.0
    except (OSError, StopIteration, ValueError):
        pass
    load = os.getloadavg()[0]
    print(json.dumps({
        "devices": summary.n_devices, "ok": summary.n_ok, "chunks": summary.chunks_total,
        "chunk_devices": args["chunk"], "wall_s": round(wall, 1),
        "devices_per_s_end_to_end": round(summary.n_devices / wall, 1),
        "devices_per_s_fitting": round(summary.devices_per_second, 1),
        "peak_rss_mb": round(rss, 1), "rss_at_end_mb": round(rss_end, 1),
        "load_average_1min": round(load, 1),
        "calibration_mb": round(out.stat().st_size / 2**20, 1)}))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=100_000)
    ap.add_argument("--samples", type=int, default=2000)
    ap.add_argument("--compare", type=int, default=10_000,
                    help="also run on the first N devices first (0: skip)")
    ap.add_argument("--chunk-devices", type=int, default=256)
    ap.add_argument("--data", type=Path, default=Path("/tmp/diffgyro-scale/data"))
    ap.add_argument("--out", type=Path, default=Path("/tmp/diffgyro-scale/out"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        child(json.loads(a.child))
        return
    t0 = time.monotonic()
    files = generate(a.data, a.devices, a.samples, a.seed)
    gen_s = time.monotonic() - t0
    size = sum(f.stat().st_size for f in files)
    print(f"dataset: {len(files)} files, {size / 2**30:.2f} GiB, "
          f"{size / (len(files) * PER_FILE) / 1024:.1f} kB/device ({gen_s:.0f} s to make)")
    runs = []
    sizes = ([a.compare] if 0 < a.compare < a.devices else []) + [a.devices]
    for n in sizes:
        subset = files[: math.ceil(n / PER_FILE)]
        res = run_fit(subset, a.out / f"{n}" / "cal.json", a.chunk_devices)
        runs.append(res)
        print(f"{res['devices']:>7} devices: {res['wall_s']:.0f} s, "
              f"{res['devices_per_s_end_to_end']:.1f} devices/s end to end "
              f"({res['devices_per_s_fitting']:.1f} while fitting), "
              f"peak RSS {res['peak_rss_mb']:.0f} MB (at the end {res['rss_at_end_mb']:.0f} MB), "
              f"{res['ok']} ok, load average {res['load_average_1min']}")
    report = {"model": MODEL, "samples": a.samples, "chunk_devices": a.chunk_devices,
              "dataset_gib": round(size / 2**30, 2), "generate_s": round(gen_s, 1), "runs": runs}
    if len(runs) == 2:
        report["peak_ratio"] = round(runs[1]["peak_rss_mb"] / runs[0]["peak_rss_mb"], 3)
        print(f"peak memory {runs[1]['devices']} / {runs[0]['devices']} devices: "
              f"{report['peak_ratio']:.2f}x (acceptance: <= 1.5)")
    if a.json:
        a.json.write_text(json.dumps(report, indent=1) + "\n")


if __name__ == "__main__":
    main()
