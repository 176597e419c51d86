"""``diffgyro diagnose`` takes every model ``fit`` takes, lists the extra columns it cannot
use under ``skipped`` (never an error), and judges no device whose base fit is not ``ok``.

Data: small thermal runs written here with known coefficients: a bias linear in
temperature plus 0.02 rad/s per volt of a logged supply voltage ``vdd``; the same
without ``vdd`` but with a readable-header column ``Magnetometer X (uT)``; and a
second device of 45 samples at constant temperature (``insufficient_range`` for
``bias_poly(2)``).
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from diffgyro.cli import main

N = 1200
VDD_GAIN = 0.02     # rad/s per V
VDD_HALF = 0.05     # V: half-range of the supply ripple
NOISE = 2e-4        # rad/s white noise per axis


def _frame(device: str, n: int, temp_span: float, seed: int, vdd: bool) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.5
    temp = 20.0 + temp_span * np.sin(t / 200.0)
    v = 3.3 + VDD_HALF * np.sin(t / 37.0)
    g = 0.01 + 1e-4 * (temp - 20.0)[:, None] + NOISE * rng.normal(size=(n, 3))
    if vdd:
        g = g + VDD_GAIN * (v - 3.3)[:, None]
    out = pd.DataFrame(dict(device=device, t=t, gx=g[:, 0], gy=g[:, 1], gz=g[:, 2], temp=temp))
    if vdd:
        out["vdd"] = v
    return out


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("diag-columns")
    vdd = folder / "vdd.csv"
    _frame("unit-vdd", N, 20.0, 1, vdd=True).to_csv(vdd, index=False)
    mag = folder / "mag.csv"
    good = _frame("unit-good", N, 20.0, 2, vdd=False)
    good["Magnetometer X (uT)"] = 20.0 + np.random.default_rng(3).normal(size=N)
    flat = _frame("unit-flat", 45, 0.0, 4, vdd=False)
    flat["Magnetometer X (uT)"] = 21.0 + np.random.default_rng(5).normal(size=45)
    pd.concat([good, flat]).to_csv(mag, index=False)
    return {"vdd": str(vdd), "mag": str(mag)}


def _run(capsys, args):
    code = main(args)
    cap = capsys.readouterr()
    assert code == 0, cap.err
    return cap


def test_base_model_reads_an_extra_column(files, capsys):
    """``bias_poly(2)+aux(vdd)``: diagnose runs the fit that ``fit`` runs (same RMS), the
    supply-voltage term found at its true size, nothing left to add."""
    model = "bias_poly(2)+aux(vdd)"
    diag = json.loads(_run(capsys, ["diagnose", files["vdd"], "--model", model, "--json"]).out)
    fitted = json.loads(_run(capsys, ["fit", files["vdd"], "--model", model, "--json"]).out)
    assert diag["model"] == model
    (d,), (f,) = diag["devices"], fitted["devices"]
    assert d["status"] == f["status"] == "ok" and d["verdict"] == "adequate"
    assert d["rms"] == pytest.approx(f["rms"], rel=1e-9)
    assert d["rms"] < 1.1 * NOISE
    assert not any(c["term"] == "aux(vdd)" for c in d["candidates"] if "term" in c)
    for ax in "xyz":  # a1 multiplies the column scaled to [-1, 1]: gain × half-range
        assert f["params"][ax]["aux(vdd).a1"] == pytest.approx(VDD_GAIN * VDD_HALF, rel=0.05)
        assert d["params"][ax] == pytest.approx(f["params"][ax], rel=1e-9)


def test_unusable_column_name_is_skipped_not_an_error(files, capsys):
    """A readable header is not a valid ``aux`` argument: diagnose runs, lists the term it
    cannot write under ``skipped`` with the way to try it, and says so in the text."""
    out = json.loads(_run(capsys, ["diagnose", files["mag"], "--model", "bias_poly(1)",
                                   "--json"]).out)
    for d in out["devices"]:
        why = d["skipped"]["aux(Magnetometer X (uT))"]
        assert "cannot be written in a model term" in why and "--columns" in why
    text = _run(capsys, ["diagnose", files["mag"], "--model", "bias_poly(1)"]).out
    assert "not tried: aux(Magnetometer X (uT))" in text
    # renamed, the column is an ordinary candidate
    renamed = json.loads(_run(capsys, [
        "diagnose", files["mag"], "--model", "bias_poly(1)", "--json", "--candidates", "aux",
        "--columns", "mag_x=Magnetometer X (uT)"]).out)
    good = next(d for d in renamed["devices"] if d["device"] == "unit-good")
    assert [c["term"] for c in good["candidates"]] == ["aux(mag_x)"]
    assert not good["candidates"][0]["significant"]  # the gyro does not follow it


def test_device_whose_fit_is_not_ok_is_not_judged(files, tmp_path, capsys):
    """A 45-sample device at constant temperature: ``insufficient_range``, and its verdict is
    ``not_judged`` with the reason, in --json, the text and the report alike."""
    report = tmp_path / "report"
    out = json.loads(_run(capsys, ["diagnose", files["mag"], "--model", "bias_poly(2)",
                                   "--json", "--report", str(report)]).out)
    devs = {d["device"]: d for d in out["devices"]}
    flat, good = devs["unit-flat"], devs["unit-good"]
    assert good["verdict"] == "adequate" and good["status_detail"] == "ok"
    assert flat["status"] == "insufficient_range" and flat["verdict"] == "not_judged"
    assert flat["candidates"] == [] and flat["best"] is None
    assert flat["verdict_detail"].startswith("not judged: the base fit is not ok (insufficient_range")
    assert flat["status_detail"].startswith("insufficient_range: temperature constant")
    text = _run(capsys, ["diagnose", files["mag"], "--model", "bias_poly(2)"]).out
    row = next(line for line in text.splitlines() if "unit-flat" in line and "│" in line)
    assert "not_judged" in row and "adequate" not in row
    assert "unit-flat: not judged — the base fit is not ok (insufficient_range" in text
    page = (report / "unit-flat.html").read_text()
    assert "class=not_judged>not_judged<" in page and "insufficient_range: temperature" in page
    index = (report / "index.html").read_text()
    assert "1 adequate, 0 missing an effect, 1 not judged" in index


def test_column_some_files_lack_is_listed_not_dropped_silently(files, capsys):
    """``vdd`` is logged in one file only: the batch cannot hold it, and every device lists
    ``aux(vdd)`` under skipped with the count of devices that have it."""
    out = json.loads(_run(capsys, ["diagnose", files["vdd"], files["mag"], "--model",
                                   "bias_poly(1)", "--json", "--candidates", "aux"]).out)
    assert [d["device"] for d in out["devices"]] == ["unit-vdd", "unit-good", "unit-flat"]
    for d in out["devices"]:
        assert "logged for 1 of 3 devices only" in d["skipped"]["aux(vdd)"]
        assert "logged for 2 of 3 devices only" in d["skipped"]["aux(Magnetometer X (uT))"]
