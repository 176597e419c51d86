"""Small Parquet datasets for the streaming tests (simulated devices with known truth).

Shapes are shared by every streaming test (same model, 200 samples per
device, chunks of 3) so that one compiled fit serves them all.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

MODEL = "bias_poly(1)+gradient"
SAMPLES = 200
CHUNK = 3


def simulated(n_devices: int, seed: int, prefix: str):
    from diffgyro.simulate import simulate

    batch, truth = simulate("thermal", n_devices, effects=MODEL, seed=seed, sample_rate=0.1,
                            duration=10.0 * SAMPLES, device_prefix=prefix)
    return batch, truth


def write_parquet(frame, path: Path, row_group_size: int | None = None) -> Path:
    """A DataFrame in the standard schema as Parquet (device ids as text)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(pa.Table.from_pandas(frame, preserve_index=False), path,
                   row_group_size=row_group_size)
    return path


def make_dataset(root: Path, files: tuple[int, ...] = (4, 4, 3), seed: int = 0,
                 row_group_size: int | None = 450) -> list[str]:
    """Directory ``root`` of Parquet files with ``files[k]`` devices each; device ids in order.

    Small row groups (450 rows: a device spans two or three) exercise reading
    a chunk row group by row group.
    """
    ids = []
    for k, n in enumerate(files):
        batch, _ = simulated(n, seed + k, f"f{k}-")
        write_parquet(batch.to_frame(), root / f"part-{k:02d}.parquet", row_group_size)
        ids += list(batch.devices)
    return ids


def add_bad_devices(root: Path, seed: int = 99) -> dict[str, str]:
    """A file with faulty devices among good ones; returns device -> expected reason text."""
    import pandas as pd

    batch, _ = simulated(5, seed, "bad-")
    frames = []
    for i, rec in enumerate(batch.recordings()):
        f = rec.to_frame()
        if i == 1:
            f.loc[17, "gx"] = np.nan
        elif i == 2:
            f.loc[40, "t"] = f.loc[38, "t"]
        elif i == 3:
            f = f.iloc[:1]
        frames.append(f)
    write_parquet(pd.concat(frames, ignore_index=True), root / "part-90-bad.parquet")
    # a device id that is also in another file: neither copy is fitted
    dup = batch.recordings()[0].to_frame()
    dup["device"] = "f0-000"
    write_parquet(dup, root / "part-91-dup.parquet")
    return {"bad-001": "missing or NaN value", "bad-002": "time goes backwards",
            "bad-003": "1 sample", "f0-000": "appears in several files"}


def load_outputs(out: Path) -> tuple[dict, list[dict]]:
    """Calibration JSON without its creation time, and the results table lines."""
    import json

    cal = json.loads(out.read_text())
    cal.pop("created")
    res = out.with_name(out.name.removesuffix(".json") + ".devices.jsonl")
    return cal, [json.loads(line) for line in res.read_text().splitlines()]
