"""A small plain CSV is read without pandas (``diffgyro.io._plain_csv``), to the same
bits as pandas reads it; anything not plain is left to pandas, whose errors name it."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from diffgyro.io import _plain_csv, load


def _write(path, rng, fmt: str, newline: str = "\n") -> None:
    """Two devices (ids padded with spaces), time, rates over 17 decades, temperature, and
    an extra numeric column; every number written in ``fmt``."""
    lines = ["device, t ,gx,gy,gz,temp,vdd"]
    for dev in (" imu A", "imu B "):
        for k in range(60):
            vals = [k * 0.01, *(rng.standard_normal(3) * 10.0 ** rng.integers(-14, 3, 3)),
                    25 + rng.standard_normal(), 3.3 + 1e-3 * rng.standard_normal()]
            lines.append(",".join([dev] + [repr(float(v)) if fmt == "repr" else fmt % v
                                           for v in vals]))
    path.write_text(newline.join(lines) + newline)


def _arrays(recs) -> list[tuple]:
    return [(r.device, r.t, r.gyro, r.temp, r.aux["vdd"]) for r in recs]


@pytest.mark.parametrize("fmt,newline", [("repr", "\n"), ("%.17g", "\r\n"), ("%.25e", "\n")])
def test_plain_csv_reads_the_same_bits_as_pandas(tmp_path, monkeypatch, fmt, newline):
    path = tmp_path / "x.csv"
    _write(path, np.random.default_rng(len(fmt)), fmt, newline)
    rows = _plain_csv.split_plain(path, ",")
    wanted = ["device", "t", "gx", "gy", "gz", "temp", "vdd"]
    assert rows is not None and _plain_csv.read_plain(rows, wanted, {"device"}) is not None
    plain = load(path, check_units=False)  # numbers of every size, not a device's
    monkeypatch.setattr(_plain_csv, "MAX_BYTES", 0)  # every file is pandas' now
    with_pandas = load(path, check_units=False)
    assert [r.device for r in plain] == ["imu A", "imu B"]
    for a, b in zip(_arrays(plain), _arrays(with_pandas), strict=True):
        assert a[0] == b[0]
        for x, y in zip(a[1:], b[1:], strict=True):
            assert x.dtype == y.dtype == np.float64 and x.tobytes() == y.tobytes()


def test_a_plain_csv_loads_without_pandas(tmp_path):
    _write(tmp_path / "x.csv", np.random.default_rng(0), "repr")
    code = ("import sys; from diffgyro.io import load; r = load('x.csv', check_units=False); "
            "print(len(r), sorted(m for m in ('pandas', 'pyarrow') if m in sys.modules))")
    run = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True,
                         text=True, timeout=60, check=True)
    assert run.stdout.strip() == "2 []"


@pytest.mark.parametrize("body", [
    'device,t,gx,gy,gz\n"a",0,1,2,3\n',        # a quote
    "device,t,gx,gy,gz\na,0,1,2,3\n\na,1,1,2,3\n",  # a blank line
    "device,t,gx,gy,gz\na,0,1,2\n",            # a short row
    "device,t,gx,gy,gz\ra,0,1,2,3\r",          # lone carriage returns
])
def test_files_that_are_not_plain_are_left_to_pandas(tmp_path, body):
    path = tmp_path / "x.csv"
    path.write_text(body)
    assert _plain_csv.split_plain(path, ",") is None


@pytest.mark.parametrize("cell", ["", "nan", "NA", "1_000", " 1.5", "inf", "1e", "0x10"])
def test_a_cell_that_is_not_a_plain_number_is_left_to_pandas(tmp_path, cell):
    path = tmp_path / "x.csv"
    path.write_text(f"device,t,gx,gy,gz\na,0,1,2,3\na,1,{cell},2,3\n")
    rows = _plain_csv.split_plain(path, ",")
    assert rows is not None
    assert _plain_csv.read_plain(rows, ["t", "gx"], set()) is None
    assert _plain_csv.read_plain(rows, ["t", "gy"], set()) is not None
