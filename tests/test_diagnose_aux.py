"""diagnose offers ``aux(col)`` for every extra logged column the model does not read.

Data: thermal runs made apart from the project's simulator (``hidden_effects.py``)
whose hidden bias follows a logged supply voltage ``vdd`` (a wander, load steps
and read-out noise, independent of the temperatures), noise drawn per device as
in the discovery catalogue. Beside ``vdd`` every device logs columns that must
not be named or must be skipped with a reason: ``humidity`` (varies, unrelated),
``const`` (constant), ``empty`` (all NaN) and ``probe`` (a gap on one device).
"""

from __future__ import annotations

import json
import math
import zlib

import hidden_effects as H
import numpy as np
import pytest

from diffgyro.cli import main
from diffgyro.data import Batch, Recording
from diffgyro.diagnose import candidate_specs, diagnose
from diffgyro.io import save
from diffgyro.model import ErrorModel

BASE = "bias_poly(2)"


def _vdd_device(k: int) -> H.Hidden:
    seed = zlib.crc32(f"thermal|{BASE}|vdd|{k}".encode())
    rng = np.random.default_rng(seed)
    noise = H.draw_noise(rng)
    size = float(np.exp(rng.uniform(math.log(0.5), math.log(3.0))))
    return H.make_recording("thermal", "vdd", BASE, seed, size=size, noise=noise,
                            device=f"vdd-{k}")


def _with_extras(rec: Recording, k: int) -> Recording:
    rng = np.random.default_rng(1000 + k)
    n = rec.n
    probe = 1.0 + 0.1 * rng.normal(size=n)
    if k == 0:
        probe[10] = np.nan
    aux = dict(rec.aux, humidity=40.0 + rng.normal(size=n), const=np.full(n, 3.3),
               empty=np.full(n, np.nan), probe=probe)
    return Recording(t=rec.t, gyro=rec.gyro, temp=rec.temp, temp_ext=rec.temp_ext,
                     accel=rec.accel, rate=rec.rate, device=rec.device, aux=aux)


@pytest.fixture(scope="module")
def vdd_devices():
    """Six devices whose bias follows ``vdd``, each logging the extra columns."""
    hs = [_vdd_device(k) for k in range(6)]
    return hs, [_with_extras(h.recording, k) for k, h in enumerate(hs)]


@pytest.fixture(scope="module")
def vdd_rows(vdd_devices):
    hs, recs = vdd_devices
    return hs, diagnose(BASE, Batch.from_recordings(recs))


def test_candidates_are_the_unused_columns():
    cols = ("humidity", "vdd")
    avail = frozenset({"t", "gyro", "temp", "aux:vdd", "aux:humidity"})
    specs = [c.spec for c in candidate_specs(ErrorModel.from_spec(BASE), avail, columns=cols)
             if c.effect == "aux"]
    assert specs == ["bias_poly(2)+aux(humidity)", "bias_poly(2)+aux(vdd)"]
    used = ErrorModel.from_spec("bias_poly(2)+aux(vdd,2)")
    assert [c.term.spec for c in candidate_specs(used, avail, columns=cols)
            if c.effect == "aux"] == ["aux(humidity)"]
    only = candidate_specs(ErrorModel.from_spec(BASE), avail, ["aux"], columns=cols)
    assert [c.term.spec for c in only] == ["aux(humidity)", "aux(vdd)"]
    assert [c.spec for c in candidate_specs(ErrorModel.from_spec(BASE), avail, ["aux(vdd,2)"],
                                            columns=cols)] == ["bias_poly(2)+aux(vdd,2)"]


def test_the_followed_column_is_named_first_and_reaches_the_noise(vdd_rows):
    """``aux(vdd)`` first on every device; with it held-out RMS is within 10 % of the
    simulated noise σ (all the gyro noise: white, flicker, walk, LSB)."""
    hs, dg = vdd_rows
    for h, d in zip(hs, dg.devices):
        assert d.verdict == "missing_effect", d.explanation
        first = d.candidates[0]
        assert (first.effect, first.term, first.spec) == ("aux", "aux(vdd)", f"{BASE}+aux(vdd)")
        assert d.best is first and first.significant
        assert abs(first.heldout_rms / h.noise_rms - 1.0) <= 0.10, (d.device, first.heldout_rms
                                                                     / h.noise_rms)


def test_explanation_json_and_skipped(vdd_rows):
    hs, dg = vdd_rows
    out = json.loads(json.dumps(dg.to_json()))
    for k, (d, rec) in enumerate(zip(dg.devices, out["devices"])):
        ev = d.evidence["aux:vdd"]
        assert f"residual follows `vdd` (r = {ev['r']:+.2f} on axis {ev['axis']})" in d.explanation
        assert "add `aux(vdd)`" in d.explanation
        assert abs(ev["r"]) > 0.3
        top = rec["candidates"][0]
        assert (top["effect"], top["spec"]) == ("aux", f"{BASE}+aux(vdd)")
        skipped = rec["skipped"]
        assert "constant" in skipped["aux(const)"] and "all NaN" in skipped["aux(empty)"]
        terms = [c.term for c in d.candidates]
        assert "aux(const)" not in terms and "aux(empty)" not in terms
        if k == 0:  # a gap in its probe column: skipped on this device only, with the sample
            assert "non-finite value at sample 11" in skipped["aux(probe)"]
            assert "aux(probe)" not in terms
        else:
            assert "aux(probe)" in terms and "aux(probe)" not in skipped
        assert all(not c.significant for c in d.candidates if c.term in ("aux(humidity)",
                                                                         "aux(probe)"))


def test_cli_auto_adds_the_column_term(vdd_devices, vdd_rows, tmp_path, capsys):
    """``diagnose --auto --out`` on the same six devices (written to CSV, so its first rung
    reuses the programs ``vdd_rows`` compiled): the ladder adds aux(vdd) and nothing else,
    every device ends adequate, and the calibration keeps the column's centring for
    compensate."""
    paths = [str(save(rec, tmp_path / f"unit{k}.csv")) for k, rec in enumerate(vdd_devices[1])]
    cal = tmp_path / "cal.json"
    code = main(["diagnose", *paths, "--model", BASE, "--json", "--auto", "--out", str(cal)])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    out = json.loads(cap.out)
    assert [s["added"] for s in out["ladder"]] == [None, "aux(vdd)"]
    assert all(d["verdict"] == "adequate" for d in out["final"]["devices"])
    got = json.loads(cal.read_text())
    assert got["model"] == f"{BASE}+aux(vdd)" and "vdd" in got["devices"][0]["aux"]
