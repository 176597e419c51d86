"""Numbers written without pyarrow (``diffgyro.io._float_text``) are the bytes Arrow's CSV
writer gives, and read back to the same bits."""

from __future__ import annotations

import io

import numpy as np
import pyarrow as pa
import pyarrow.csv as pcsv

from diffgyro.data import Recording
from diffgyro.io import _float_text, _save, load, save

EDGES = [5e-324, 2.5e-308, 1.7976931348623157e308, -0.0, 0.0, np.nan, np.inf, -np.inf, 1e10,
         9999999999.5, 9.999999999999999e9, 1e-6, 9.99999e-7, 1e-4, 9.9999e-5, 0.5, 3600.0]


def _arrow_texts(x: np.ndarray) -> list[str]:
    buf = io.BytesIO()
    pcsv.write_csv(pa.table({"x": x}), buf, pcsv.WriteOptions(include_header=False))
    return buf.getvalue().decode().split()


def test_texts_are_arrows_and_read_back_exactly():
    rng = np.random.default_rng(7)
    x = np.concatenate([rng.standard_normal(20000) * 10.0 ** rng.integers(-30, 30, 20000),
                        np.round(rng.standard_normal(500) * 1e6), np.arange(0, 600, 0.5),
                        10.0 ** np.arange(-20, 25), -1.5 * 10.0 ** np.arange(-20, 25), EDGES])
    texts = _float_text.float_texts(x)
    assert texts == _arrow_texts(x)
    back = np.array([float(t) for t in texts])
    assert np.array_equal(back, x, equal_nan=True)
    assert np.array_equal(np.signbit(back), np.signbit(x))


def test_a_small_file_is_written_as_arrow_writes_it(tmp_path, monkeypatch):
    rng = np.random.default_rng(3)
    rec = Recording(t=np.arange(200) * 0.5, gyro=rng.standard_normal((200, 3)) * 1e-3,
                    temp=25 + rng.standard_normal(200), device="imu 7")
    small = save(rec, tmp_path / "small.csv").read_bytes()
    monkeypatch.setattr(_save, "SMALL_VALUES", 0)  # Arrow writes every file now
    assert save(rec, tmp_path / "arrow.csv").read_bytes() == small
    (back,) = load(tmp_path / "small.csv", check_units=False)
    assert back.gyro.tobytes() == rec.gyro.tobytes() and back.t.tobytes() == rec.t.tobytes()
