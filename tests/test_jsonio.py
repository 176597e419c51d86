"""The one JSON sanitiser and the one atomic write (diffgyro._jsonio)."""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro import _jsonio as jsonio


def strict_loads(text: str):
    """json.loads that refuses the NaN/Infinity tokens Python writes by default."""
    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")
    return json.loads(text, parse_constant=refuse)


def test_non_finite_numbers_become_null_everywhere():
    obj = {"a": float("nan"), "b": [1.0, float("inf"), -float("inf")], "c": (np.float32("nan"),),
           "d": np.array([[1.0, np.nan], [np.inf, 2.0]]), "e": jnp.asarray([np.nan, 3.0]),
           "f": np.int64(7), "g": np.bool_(True), 3: "int key", "h": {"i": np.float64(-np.inf)}}
    safe = jsonio.to_json_safe(obj)
    assert safe == {"a": None, "b": [1.0, None, None], "c": [None],
                    "d": [[1.0, None], [None, 2.0]], "e": [None, 3.0], "f": 7, "g": True,
                    "3": "int key", "h": {"i": None}}
    assert type(safe["f"]) is int and type(safe["g"]) is bool
    text = jsonio.dumps(obj)
    assert strict_loads(text) == safe
    assert "NaN" not in text and "Infinity" not in text


def test_objects_with_to_dict_are_converted():
    class R:
        def to_dict(self):
            return {"x": np.array([np.nan, 1.0])}

    assert jsonio.to_json_safe({"r": R()}) == {"r": {"x": [None, 1.0]}}


def test_number():
    assert jsonio.number(np.float64(2.5)) == 2.5
    assert jsonio.number(float("nan")) is None
    assert jsonio.number(jnp.inf) is None
    assert jsonio.number("abc") is None and jsonio.number(None) is None


def test_atomic_write_keeps_the_old_file_on_failure(tmp_path):
    path = tmp_path / "sub" / "f.json"
    jsonio.atomic_write_text(path, "old")
    with pytest.raises(TypeError):
        jsonio.atomic_write_text(path, 123)  # not text: nothing written
    with pytest.raises(RuntimeError):
        with jsonio.AtomicFile(path, "w") as f:
            f.fh.write("half")
            raise RuntimeError("killed mid-write")
    assert path.read_text() == "old"
    assert sorted(p.name for p in path.parent.iterdir()) == ["f.json"]  # no temporary left
    jsonio.atomic_write_bytes(path, b"new")
    assert path.read_bytes() == b"new"


def test_atomic_write_gives_umask_permissions(tmp_path):
    old = os.umask(0o027)
    try:
        path = jsonio.atomic_write_text(tmp_path / "a.txt", "x")
    finally:
        os.umask(old)
    assert path.stat().st_mode & 0o777 == 0o640


def test_one_sanitiser_and_one_atomic_write_in_the_package():
    """No module writes JSON or renames files into place by itself (issue 23): every
    writer goes through jsonio, so a fix there is a fix everywhere."""
    src = Path(jsonio.__file__).parent
    banned = re.compile(r"allow_nan\s*=\s*False|os\.replace\(|mkstemp\(|NamedTemporaryFile|"
                        r"\.write_text\(|json\.dump\(")
    found = [f"{p.relative_to(src)}:{i}: {line.strip()}"
             for p in sorted(src.rglob("*.py")) if p.name != "_jsonio.py"
             for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
             if banned.search(line)]
    assert not found, "\n".join(found)
    printed = [f"{p.relative_to(src)}:{i}: {line.strip()}"
               for p in sorted(src.rglob("*.py")) if p.name != "_jsonio.py"
               for i, line in enumerate(p.read_text(encoding="utf-8").splitlines(), 1)
               if re.search(r"json\.dumps\(", line) and "sha256" not in line
               and "key = json.dumps" not in line]
    assert not printed, "\n".join(printed)


def test_calibration_file_with_a_failed_device_is_strict_json(tmp_path):
    from diffgyro import calibration
    from diffgyro.calibration import Calibration, DeviceCalibration

    dev = DeviceCalibration(device="d", status="failed", beta=[[math.nan]] * 3, theta=[],
                            temp_centre=25.0, temp_scale=1.0, temp_range=None,
                            status_detail="failed: x",
                            quality={"rms": math.inf, "heldout_rms": None, "noise_floor": 1.0,
                                     "n_samples": 10, "steps": 1}, params={})
    cal = Calibration(model="bias_poly(0)", devices=[dev], created="2024-01-01T00:00:00+00:00",
                      diffgyro_version="0", input_hash=None, units={})
    path = tmp_path / "cal.json"
    calibration.save(cal, path)
    doc = strict_loads(path.read_text())
    assert doc["devices"][0]["beta"] == [[None]] * 3
    assert doc["devices"][0]["quality"]["rms"] is None
