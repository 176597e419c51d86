"""``diffgyro diagnose``: the --json object exactly, the report, --auto, bad input.

Data: independent recordings (hidden_effects.py) written in the standard
schema: one device with a hidden ``gradient`` (CSV), one clean (Parquet), both
2 Hz thermal runs.
"""

from __future__ import annotations

import json

import hidden_effects as H
import numpy as np
import pytest

from diffgyro.cli import main
from diffgyro.io import save

KEYS = {"device", "rms", "heldout_rms", "noise_floor", "verdict", "candidates"}
CAND_KEYS = {"effect", "spec", "heldout_rms", "significant"}


@pytest.fixture(scope="module")
def thermal_csv(tmp_path_factory):
    noise = H.Noise(white=2e-4, flicker=0.1, drift=0.1)
    hidden = H.make_recording("thermal", "gradient", "bias_poly(2)", 21, size=2.0, noise=noise,
                              device="unit-gradient").recording
    clean = H.make_recording("thermal", None, "bias_poly(2)", 22, noise=noise,
                             device="unit-clean").recording
    folder = tmp_path_factory.mktemp("diag")
    save(hidden, folder / "unit-gradient.csv")
    save(clean, folder / "unit-clean.parquet")
    return [str(folder / "unit-gradient.csv"), str(folder / "unit-clean.parquet")]


def _json(capsys, args):
    code = main(args)
    cap = capsys.readouterr()
    assert code == 0, cap.err
    return json.loads(cap.out)


def test_json_contract(thermal_csv, capsys):
    out = _json(capsys, ["diagnose", *thermal_csv, "--model", "bias_poly(2)", "--json"])
    assert out["model"] == "bias_poly(2)"
    devs = {d["device"]: d for d in out["devices"]}
    assert set(devs) == {"unit-gradient", "unit-clean"}
    for d in devs.values():
        assert KEYS <= set(d)
        assert d["verdict"] in ("adequate", "missing_effect")  # both fits are ok: judged
        assert d["candidates"], "every supported effect is scored"
        for c in d["candidates"]:
            assert CAND_KEYS <= set(c) and isinstance(c["significant"], bool)
            assert c["spec"].startswith("bias_poly(2)+") or c["spec"].startswith("bias_poly(3)")
        hs = [c["heldout_rms"] for c in d["candidates"]]
        assert hs == sorted(hs), "candidates best first"
        if d["verdict"] == "adequate":
            assert not any(c["significant"] for c in d["candidates"])
        else:
            assert any(c["significant"] for c in d["candidates"])
    g = devs["unit-gradient"]
    assert g["verdict"] == "missing_effect" and g["candidates"][0]["effect"] == "gradient"
    assert g["candidates"][0]["spec"] == "bias_poly(2)+gradient"
    assert g["candidates"][0]["heldout_rms"] < g["heldout_rms"]
    assert devs["unit-clean"]["verdict"] == "adequate"
    assert "dT/dt" in g["explanation"]


def test_fit_and_diagnose_report_the_same_noise_floor(thermal_csv, capsys):
    """One model-free floor: ``fit --json`` and ``diagnose --json`` print the same
    ``noise_floor`` (and per axis) for the same device; diagnose's decision level is
    reported apart as ``white_noise_rms``."""
    diag = _json(capsys, ["diagnose", *thermal_csv, "--model", "bias_poly(2)", "--json"])
    fitted = _json(capsys, ["fit", *thermal_csv, "--model", "bias_poly(2)", "--json"])
    floors = {d["device"]: d["noise_floor"] for d in fitted["devices"]}
    assert set(floors) == {d["device"] for d in diag["devices"]}
    for d in diag["devices"]:
        assert d["noise_floor"] == floors[d["device"]], d["device"]
        assert 1e-4 < d["noise_floor"] < 4e-4  # the simulated white noise, 2e-4 rad/s
        assert len(d["noise_floor_axes"]) == 3 and len(d["white_noise_rms_axes"]) == 3
        # a different statistic of the same white noise: close, not equal
        assert d["white_noise_rms"] != d["noise_floor"]
        assert abs(d["white_noise_rms"] / d["noise_floor"] - 1) < 0.1


def test_report_auto_and_calibration(thermal_csv, tmp_path, capsys):
    report, cal = tmp_path / "report", tmp_path / "diag-cal.json"
    out = _json(capsys, ["diagnose", *thermal_csv, "--model", "bias_poly(2)", "--json",
                         "--auto", "--report", str(report), "--out", str(cal)])
    assert [s["added"] for s in out["ladder"]] == [None, "gradient"]
    assert out["ladder"][-1]["spec"] == "bias_poly(2)+gradient"
    assert all(d["verdict"] == "adequate" for d in out["final"]["devices"])
    pages = sorted(p.name for p in report.iterdir())
    assert pages == ["index.html", "unit-clean.html", "unit-gradient.html"]
    page = (report / "unit-gradient.html").read_text()
    assert page.count("data:image/png;base64,") >= 4 and "http" not in page.split("<body>")[1][:200]
    # --out: the final model's calibration, equal to what `fit --out` writes for that model
    ref = tmp_path / "fit-cal.json"
    assert main(["fit", *thermal_csv, "--model", out["ladder"][-1]["spec"], "--out", str(ref)]) == 0
    capsys.readouterr()
    got, want = json.loads(cal.read_text()), json.loads(ref.read_text())
    assert got["model"] == want["model"] == "bias_poly(2)+gradient"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp files
    for key in set(got) - {"created", "devices"}:
        assert got[key] == want[key], key
    for g, w in zip(got["devices"], want["devices"], strict=True):
        assert g["device"] == w["device"] and g["status"] == w["status"]
        for key in ("beta", "theta", "temp_centre", "temp_scale", "temp_range"):
            np.testing.assert_allclose(g[key], w[key], rtol=1e-12, atol=1e-12, err_msg=key)
        assert g["quality"] == pytest.approx(w["quality"], rel=1e-12, abs=1e-12)
        assert set(g["params"]) == set(w["params"])
        for ax in g["params"]:
            for lab, v in g["params"][ax].items():
                assert v == pytest.approx(w["params"][ax][lab], rel=1e-12, abs=1e-12), (ax, lab)


def test_table_output(thermal_csv, capsys):
    code = main(["diagnose", *thermal_csv, "--model", "bias_poly(2)", "--candidates",
                 "gradient,temp_diff,bias_poly"])
    cap = capsys.readouterr()
    assert code == 0, cap.err
    assert "unit-gradient" in cap.out and "missing_effect" in cap.out and "add `gradient`" in cap.out


@pytest.mark.parametrize("args, must", [
    (["--model", "bias_poly(2)+gradiant"], "gradiant"),
    (["--model", "bias_poly(2)", "--candidates", "nonsense"], "nonsense"),
])
def test_bad_spec_is_one_line(thermal_csv, capsys, args, must):
    code = main(["diagnose", *thermal_csv, *args])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and must in err and "Traceback" not in err


def test_bad_data_is_one_line(tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_text("t,gx,gy,gz,temp\n0,0,0,0,20\n1,0,0,0,21\n1,0,0,0,22\n")
    code = main(["diagnose", str(path), "--model", "bias_poly(1)", "--json"])
    cap = capsys.readouterr()
    assert code == 2 and len(cap.err.strip().splitlines()) == 1 and "bad.csv" in cap.err
    doc = json.loads(cap.out)  # --json: the error as an object on stdout too
    assert doc["file"] == str(path) and doc["row"] == 3 and doc["column"] == "t"
    assert cap.err.strip() == f"diffgyro: error: {doc['error']}"


def test_model_needs_missing_column(tmp_path, capsys):
    rec = H.make_recording("thermal", None, "bias_poly(2)", 5, hours=0.5).recording
    from diffgyro.data import Recording

    bare = Recording(t=rec.t, gyro=rec.gyro, device="bare")
    path = tmp_path / "bare.csv"
    save(bare, path)
    code = main(["diagnose", str(path), "--model", "bias_poly(2)"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and "temp" in err and len(err.splitlines()) == 1


def test_out_does_not_stream(tmp_path, capsys):
    code = main(["diagnose", str(tmp_path), "--model", "bias_poly(1)", "--out", str(tmp_path / "c.json")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "--out" in err
    assert not (tmp_path / "c.json").exists()
