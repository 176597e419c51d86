"""report.py: self-contained HTML pages with the diagnosis figures, written atomically."""

from __future__ import annotations

import base64
import os
import re

import hidden_effects as H
import pytest

from diffgyro.data import Batch
from diffgyro.diagnose import diagnose, diagnose_auto
from diffgyro.report import outliers, write_atomic, write_report


@pytest.fixture(scope="module")
def rate_table():
    hs = [H.make_recording("rate_table", "scale_asym" if k < 3 else None, "bias_poly(1)+scale_poly(0)",
                           60 + k, size=2.0, noise=H.Noise(white=3e-4), hours=1.0, device=f"rt{k}")
          for k in range(4)]
    return Batch.from_recordings([h.recording for h in hs])


def _images(page: str) -> list[bytes]:
    return [base64.b64decode(m) for m in re.findall(r"data:image/png;base64,([A-Za-z0-9+/=]+)", page)]


def test_pages_are_self_contained(rate_table, tmp_path):
    ladder = diagnose_auto("bias_poly(1)+scale_poly(0)", rate_table, max_steps=2)
    paths = write_report(ladder.first, rate_table, tmp_path / "r", ladder=ladder)
    names = sorted(p.name for p in paths)
    assert names == ["index.html", "rt0.html", "rt1.html", "rt2.html", "rt3.html"]
    page = (tmp_path / "r" / "rt0.html").read_text()
    imgs = _images(page)
    # time, rate/force, Allan, candidates, ladder (no temperature figure: no thermal span needed)
    assert len(imgs) >= 5 and all(i.startswith(b"\x89PNG") for i in imgs)
    assert not re.search(r"""(src|href)=['"]https?:""", page)  # nothing fetched from outside
    assert "scale_asym" in page and "missing_effect" in page
    index = (tmp_path / "r" / "index.html").read_text()
    assert "rt3.html" in index and "Model ladder" in index and "Outlier devices" in index
    assert not [p for p in (tmp_path / "r").iterdir() if p.name.startswith(".")]  # no temp files
    assert oct(os.stat(tmp_path / "r" / "index.html").st_mode & 0o444) == oct(0o444)


def test_thermal_page_has_heating_and_cooling(tmp_path):
    hs = [H.make_recording("thermal", "hysteresis", "bias_poly(2)", 80 + k, size=2.0, hours=2.0,
                           device=f"th{k}") for k in range(2)]
    batch = Batch.from_recordings([h.recording for h in hs])
    dg = diagnose("bias_poly(2)", batch)
    write_report(dg, batch, tmp_path)
    page = (tmp_path / "th0.html").read_text()
    assert "heating red, cooling blue" in page or "temperature" in page
    assert "hysteresis" in page


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    path = tmp_path / "page.html"
    write_atomic(path, "old")

    with pytest.raises(TypeError):
        write_atomic(path, 12345)  # not text: the write fails
    assert path.read_text() == "old"
    assert [p.name for p in tmp_path.iterdir()] == ["page.html"]


def test_outlier_device_is_listed(rate_table):
    import numpy as np

    # a bias far outside the others' spread makes one device an outlier
    recs = rate_table.recordings()
    recs[2] = H.replace_recording(recs[2], recs[2].gyro + np.array([0.5, 0.0, 0.0]))
    batch = Batch.from_recordings(recs)
    dg = diagnose("bias_poly(1)+scale_poly(0)+scale_asym", batch)
    flagged = outliers(dg)
    assert any(dev == "rt2" and "bias_poly(1).c0" in why for dev, why in flagged), flagged
