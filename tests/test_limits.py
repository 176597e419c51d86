"""``--limits FILE.toml``: pass/fail per device and the batch's yield (diffgyro.limits).

Known truth: the bounds and excesses in closed form on hand-made records; the bias,
its temperature coefficient and the angle random walk of simulated devices written
here (one within the BMI088 datasheet's figures of ``examples/limits/bmi088.toml``,
one outside on three of them); text, --json, the calibration file and the report
agree; a damaged or wrong limits file is one line naming the file and the key.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from diffgyro.cli import main
from diffgyro.errors import DataError
from diffgyro.internal import unit_scale
from diffgyro.limits import (
    add_figures,
    bias_figures,
    check,
    from_dict,
    load,
    lookup,
    residual_allan,
    split_path,
    summary,
)

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "limits" / "bmi088.toml"
DEG = math.pi / 180.0

# --------------------------------------------------------------------------- the mechanism


RECORD = {"device": "u1", "status": "ok", "heldout_rms": 2.5e-3, "noise_floor": None,
          "params": {"x": {"bias_poly(1).c0": -0.07, "bias_poly(1).c1": 0.01},
                     "y": {"bias_poly(1).c0": 0.02, "bias_poly(1).c1": 0.0},
                     "z": {"bias_poly(1).c0": 0.04, "bias_poly(1).c1": -0.02}}}


def test_paths_hold_dots_inside_keys_and_wildcards():
    assert split_path("params.*.bias_poly(2).c0") == ["params", "*", "bias_poly(2)", "c0"]
    assert lookup(RECORD, "params.x.bias_poly(1).c0") == [("params.x.bias_poly(1).c0", -0.07)]
    assert [p for p, _ in lookup(RECORD, "params.*.bias_poly(1).c1")] == [
        "params.x.bias_poly(1).c1", "params.y.bias_poly(1).c1", "params.z.bias_poly(1).c1"]
    assert lookup(RECORD, "params.x.bias_poly(2).c0") == [] and lookup(RECORD, "nothing") == []
    assert [v for _, v in lookup(RECORD, "params.*.bias_poly(*).c0")] == [-0.07, 0.02, 0.04]
    assert len(lookup(RECORD, "params.*.*")) == 6 and lookup(RECORD, "params.x.aux(*).a1") == []


def test_bounds_say_which_limit_broke_and_by_how_much():
    limits = from_dict({"limits": {
        "status": "ok", "heldout_rms": {"max": 2e-3},
        "params": {"*": {"bias_poly(1).c0": {"abs": True, "max": 0.05}}},  # nested tables
        "params.y.bias_poly(1).c0": {"min": 0.03},
        "noise_floor": {"max": 1.0}}}, "line.toml")
    got = check(limits, RECORD)
    assert got["result"] == "fail"
    by = {b["limit"]: b for b in got["broken"]}
    assert set(by) == {"heldout_rms", "params.x.bias_poly(1).c0", "params.y.bias_poly(1).c0",
                       "noise_floor"}
    assert by["heldout_rms"]["by"] == pytest.approx(0.5e-3)
    assert by["heldout_rms"]["max"] == 2e-3 and by["heldout_rms"]["min"] is None
    x = by["params.x.bias_poly(1).c0"]
    assert x["value"] == -0.07 and x["abs"] is True and x["by"] == pytest.approx(0.02)
    assert by["params.y.bias_poly(1).c0"]["by"] == pytest.approx(0.01)
    assert by["noise_floor"]["value"] is None and "no value" in by["noise_floor"]["detail"]
    # optional: a missing value passes; a text field that differs fails
    lenient = from_dict({"limits": {"noise_floor": {"max": 1.0, "optional": True},
                                    "status": ["ok", "not_converged"]}})
    assert check(lenient, RECORD) == {"result": "pass", "broken": []}
    moving = check(lenient, {**RECORD, "status": "in_motion"})["broken"]
    assert moving[0]["limit"] == "status" and moving[0]["expected"] == ["ok", "not_converged"]
    records = [{"device": "a", "limits": {"result": "pass"}},
               {"device": "b", "limits": {"result": "fail"}},
               {"device": "c", "limits": {"result": "pass"}}]
    s = summary(limits, records)
    assert (s["passed"], s["failed"], s["rejected"]) == (2, 1, ["b"])
    assert s["yield"] == pytest.approx(2 / 3) and s["file"] == "line.toml"


def test_datasheet_units_convert_to_the_records():
    assert unit_scale("deg/s") == pytest.approx(DEG)
    assert unit_scale("mdps") == pytest.approx(DEG * 1e-3)
    assert unit_scale("deg/s/sqrt(Hz)") == pytest.approx(DEG)
    assert unit_scale("mdps/√Hz") == pytest.approx(DEG * 1e-3)
    assert unit_scale("deg/sqrt(h)") == pytest.approx(DEG / 60.0)  # 1 °/√h = (π/180)/60 rad/√s
    assert unit_scale("dps/K") == pytest.approx(DEG)
    assert unit_scale("rad/s") == 1.0 and unit_scale("furlongs") is None


def test_bias_figures_in_closed_form():
    """b(T_s) = c0 + c1·T_s + c2·T_s², T_s = (T − 25)/10 on [15, 35] °C: the largest |b| is at
    an end or at the vertex, the largest |db/dT| = |c1 ± 2 c2| / 10 at an end."""
    c = {"x": (0.01, 0.004, -0.002), "y": (-0.02, 0.0, 0.0), "z": (0.0, -0.006, 0.003)}
    params = {ax: {f"bias_poly(2).c{j}": v for j, v in enumerate(cs)} for ax, cs in c.items()}
    got = bias_figures(params, 25.0, 10.0, [15.0, 35.0])
    for ax, (c0, c1, c2) in c.items():
        ends = [c0 + c1 * s + c2 * s * s for s in (-1.0, 1.0)]
        vertex = [c0 - c1 * c1 / (4 * c2)] if c2 and abs(c1 / (2 * c2)) <= 1 else []
        assert got["bias_range"][ax] == pytest.approx(max(abs(v) for v in ends + vertex), rel=1e-4)
        assert got["bias_tempco"][ax] == pytest.approx(max(abs(c1 - 2 * c2), abs(c1 + 2 * c2)) / 10)
    assert got["bias_range"]["worst"] == max(got["bias_range"][a] for a in "xyz")
    const = bias_figures({a: {"bias_poly(0).c0": -0.3} for a in "xyz"}, None, None, None)
    assert const["bias_range"]["worst"] == pytest.approx(0.3) and const["bias_tempco"]["x"] is None


def test_temperature_range_figure():
    rec = add_figures({"device": "a"}, {"temp_range"}, temp_range=[14.5, 36.0])
    assert rec["temp_range"] == {"min": 14.5, "max": 36.0, "span": 21.5}
    limits = from_dict({"limits": {"temp_range": {"span": {"min": 25.0}}}})
    broken = check(limits, rec)["broken"]
    assert broken[0]["limit"] == "temp_range.span" and broken[0]["by"] == pytest.approx(3.5)
    none = add_figures({"device": "b"}, {"temp_range"}, temp_range=None)["temp_range"]
    assert none == {"min": None, "max": None, "span": None}


def test_residual_allan_reads_the_white_noise_density():
    """White noise of density N rad/s/√Hz sampled every dt has σ = N/√dt per sample; the
    read-out of its Allan curve is N (within the scatter of 20 000 samples)."""
    rng = np.random.default_rng(3)
    dt, n, dens = 0.01, 20000, np.array([1e-4, 2e-4, 4e-4])
    res = rng.normal(size=(1, n, 3)) * dens / np.sqrt(dt)
    got = residual_allan(res, np.arange(n)[None] * dt, np.array([n]))[0]
    for a, ax in enumerate("xyz"):
        assert got[ax]["arw"] == pytest.approx(dens[a], rel=0.08)
    assert got["arw"] == max(got[ax]["arw"] for ax in "xyz")


# --------------------------------------------------------------------------- bad files


BAD = [
    ("[limits]\nheldout_rms = { max = 0.002 \n", "not valid TOML", "heldout_rms"),
    ("[limits]\nstatus = 'ok'\nstatus = 'ok'\n", "not valid TOML", "status"),
    ("[limits]\nheldout_rsm = { max = 0.002 }\n", "unknown field", "heldout_rsm"),
    ("[limits]\nheldout_rms = { mx = 0.002 }\n", "unknown bound field", "heldout_rms.mx"),
    ("[limits]\nheldout_rms = { max = '0.002' }\n", "finite number", "heldout_rms.max"),
    ("[limits]\nheldout_rms = 0.002\n", "must be a bound", "heldout_rms"),
    ("[limits]\nheldout_rms = { min = 2, max = 1 }\n", "above max", "heldout_rms"),
    ("[limits]\nheldout_rms = { max = 1, abs = 'yes' }\n", "true or false", "heldout_rms.abs"),
    ("[limits]\nheldout_rms = { max = 1, unit = 'furlong/s' }\n", "unknown unit", "heldout_rms.unit"),
    ("[limit]\nheldout_rms = { max = 1 }\n", "unknown section", "limit"),
    ("[limits]\n", "missing or empty", "limits"),
    ("[limits]\n'params.x.bias_poly(3).c0' = { max = 1 }\n", "names no coefficient",
     "params.x.bias_poly(3).c0"),
]


@pytest.fixture(scope="module")
def tiny_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("lim") / "tiny.csv"
    t = np.arange(64) * 0.5
    pd.DataFrame(dict(t=t, gx=1e-3, gy=0.0, gz=0.0, temp=20 + t / 4)).to_csv(path, index=False)
    return path


@pytest.mark.parametrize("text, problem, key", BAD)
@pytest.mark.parametrize("command", ["fit", "diagnose"])
def test_a_bad_limits_file_is_one_line_naming_file_and_key(tiny_csv, tmp_path, capsys, text,
                                                          problem, key, command):
    bad = tmp_path / "bad.toml"
    bad.write_text(text)
    code = main([command, str(tiny_csv), "--model", "bias_poly(1)", "--limits", str(bad)])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "Traceback" not in err
    assert str(bad) in err and problem in err
    if key is not None:
        assert f"key {key!r}" in err
    if problem == "not valid TOML":
        assert "(at line " in err


def test_load_refuses_a_missing_file(tmp_path):
    with pytest.raises(DataError, match="cannot read limits file"):
        load(tmp_path / "none.toml")


# --------------------------------------------------------------------------- the datasheet example


def _device(name: str, bias_dps, tempco_dps_k, arw_dps, seed: int) -> pd.DataFrame:
    """20 min at 10 Hz over a 15–35 °C ramp: bias (°/s at 25 °C) + tempco·(T − 25) + white
    noise of density ``arw_dps`` (°/s/√Hz), in rad/s."""
    rng = np.random.default_rng(seed)
    dt, n = 0.1, 12000
    t = np.arange(n) * dt
    temp = 25.0 + 10.0 * np.cos(2 * np.pi * t / t[-1])  # 35 → 15 → 35 °C
    g = (np.asarray(bias_dps) + np.outer(temp - 25.0, tempco_dps_k)) * DEG
    g = g + rng.normal(size=(n, 3)) * arw_dps * DEG / np.sqrt(dt)
    return pd.DataFrame(dict(device=name, t=t, gx=g[:, 0], gy=g[:, 1], gz=g[:, 2], temp=temp))


@pytest.fixture(scope="module")
def datasheet_run(tmp_path_factory):
    """Two simulated BMI088s: one within the datasheet's figures, one outside on three; the
    fit --limits JSON, text and calibration file of both."""
    folder = tmp_path_factory.mktemp("bmi088")
    data = folder / "line.csv"
    good = _device("in-spec", [0.3, -0.2, 0.5], [0.005, -0.008, 0.01], 0.008, 1)
    bad = _device("out-of-spec", [1.5, -0.2, 0.4], [0.004, 0.002, 0.03], 0.03, 2)
    pd.concat([good, bad]).to_csv(data, index=False)
    cal = folder / "cal.json"
    args = ["fit", str(data), "--model", "bias_poly(1)", "--limits", str(EXAMPLE)]
    return {"data": data, "args": args, "cal": cal, "folder": folder}


def test_datasheet_example_passes_a_unit_in_spec_and_names_what_fails(datasheet_run, capsys):
    run = datasheet_run
    assert main([*run["args"], "--json", "--out", str(run["cal"])]) == 0
    out = json.loads(capsys.readouterr().out)
    devs = {d["device"]: d for d in out["devices"]}
    good, bad = devs["in-spec"], devs["out-of-spec"]
    assert good["limits"] == {"result": "pass", "broken": []}
    # the figures the limits asked for, at their true size
    assert good["bias_tempco"]["worst"] == pytest.approx(0.010 * DEG, rel=0.05)
    assert good["allan"]["arw"] == pytest.approx(0.008 * DEG, rel=0.1)
    broken = {b["limit"]: b for b in bad["limits"]["broken"]}
    assert bad["limits"]["result"] == "fail"
    assert set(broken) == {"params.x.bias_poly(1).c0", "bias_tempco.worst", "allan.arw"}
    assert broken["params.x.bias_poly(1).c0"]["by"] == pytest.approx(0.5 * DEG, rel=0.05)
    assert broken["params.x.bias_poly(1).c0"]["max"] == pytest.approx(1.0 * DEG)
    assert broken["bias_tempco.worst"]["by"] == pytest.approx(0.015 * DEG, rel=0.05)
    assert broken["allan.arw"]["by"] == pytest.approx((0.03 - 0.014) * DEG, rel=0.15)
    lim = out["limits"]
    assert (lim["passed"], lim["failed"], lim["rejected"], lim["yield"]) == (1, 1, ["out-of-spec"], 0.5)
    assert lim["file"] == str(EXAMPLE) and lim["name"].startswith("BMI088")
    # the calibration file keeps the same, and still loads
    from diffgyro import calibration

    saved = json.loads(run["cal"].read_text())
    assert saved["limits"] == lim
    assert {d["device"]: d["limits"] for d in saved["devices"]} == {
        k: v["limits"] for k, v in devs.items()}
    assert calibration.load(run["cal"]).limits["rejected"] == ["out-of-spec"]
    # the text output says the same
    assert main(run["args"]) == 0
    text = capsys.readouterr().out
    assert "out-of-spec: fail — |params.x.bias_poly(1).c0|" in text
    assert "bias_tempco.worst" in text and "allan.arw" in text and "in-spec: fail" not in text
    assert "1 of 2 devices pass (yield 50.0 %); rejected: out-of-spec" in text


def test_diagnose_limits_agree_in_text_json_and_report(datasheet_run, tmp_path, capsys):
    run = datasheet_run
    args = ["diagnose", str(run["data"]), "--model", "bias_poly(1)", "--limits", str(EXAMPLE),
            "--candidates", "bias_poly"]
    report = tmp_path / "report"
    assert main([*args, "--json", "--report", str(report)]) == 0
    out = json.loads(capsys.readouterr().out)
    devs = {d["device"]: d for d in out["devices"]}
    assert devs["in-spec"]["limits"]["result"] == "pass"
    assert {b["limit"] for b in devs["out-of-spec"]["limits"]["broken"]} == {
        "params.x.bias_poly(1).c0", "bias_tempco.worst", "allan.arw"}
    assert out["limits"]["rejected"] == ["out-of-spec"]
    assert main(args) == 0
    text = capsys.readouterr().out
    rows = {line.split("│")[1].strip(): line for line in text.splitlines()
            if line.startswith("│") and ("in-spec" in line or "out-of-spec" in line)}
    assert rows["in-spec"].rstrip("│ ").endswith("pass")
    assert rows["out-of-spec"].rstrip("│ ").endswith("fail")
    assert "rejected: out-of-spec" in text
    index = (report / "index.html").read_text()
    assert "1 of 2 devices pass (yield 50.0 %); rejected: out-of-spec." in index
    page = (report / "out-of-spec.html").read_text()
    assert "<span class=fail>fail</span>" in page and "bias_tempco.worst" in page
    assert "<span class=pass>pass</span>" in (report / "in-spec.html").read_text()
    # --auto judges no model given in advance: refused in one line
    assert main([*args, "--auto"]) == 2
    assert "--limits judges the model given" in capsys.readouterr().err
