"""What a record resolves (issue 42): a Gauss–Markov process shorter than a few sample
intervals is white noise and comes out as such, its variance in the white part; the output
says what the record cannot see; export refuses the parameters the model does not identify.

Truth: one simulated device at 100 Hz, each axis white noise plus a Gauss–Markov process of
τ below two sample intervals (x: the Xsens recording of the issue, 0.4 dt, whose fit had
put the white part 2x low with an interval of dozens of decades)."""

from __future__ import annotations

import json
import math

import jax
import numpy as np
import pytest

from diffgyro.cli import main
from diffgyro.stochastic import gm_white_power, identify_devices, simulate_noise

N, DT = 8192, 0.01  # the length test_noise_mpu6050 and test_diagnose_noise compile for
AXES = {"x": dict(arw=2.2e-4, gm=((4e-3, 0.004),)),
        "y": dict(arw=1e-4, gm=((4e-3, 0.015),)),
        "z": dict(arw=3e-4, gm=((3e-3, 0.008),))}


def _density(kw) -> float:
    """The white density the truth shows at long scales (what a filter integrates)."""
    return math.sqrt(kw["arw"] ** 2 + sum(gm_white_power(s * s, t, DT) for s, t in kw["gm"]))


@pytest.fixture(scope="module")
def entry():
    keys = jax.random.split(jax.random.PRNGKey(0), 3)
    y = np.stack([np.asarray(simulate_noise(k, N, DT, **kw)) for k, kw in zip(keys, AXES.values())], 1)
    entries, _ = identify_devices(y[None], np.array([N]), (np.arange(N) * DT)[None], ["sim"])
    return entries[0]


def test_a_gauss_markov_process_below_the_sampling_is_white_noise(entry):
    """White only, the white density within 10 % of the truth's, its interval tight; the
    fitted process is named as merged."""
    assert entry["status"] == "ok"
    for ax, axis in entry["axes"].items():
        assert axis["structure"] == ["white"], (ax, axis["structure"])
        assert "gauss_markov" in axis["fitted_structure"]
        (white,) = axis["components"]
        arw = white["params"]["arw"]
        assert arw["status"] == "identified"
        assert arw["value"] == pytest.approx(_density(AXES[ax]), rel=0.10), ax
        assert arw["ci"][1] / arw["ci"][0] < 1.3
        res = axis["resolution"]
        assert res["merged"] and all(m["tau"] < 3 * DT for m in res["merged"])
        assert any("merged into the white part" in n for n in res["notes"])


def test_what_the_record_cannot_see_is_stated(entry):
    """The resolvable Gauss–Markov times, and the smallest random walk the criterion would
    take, of the order of the white density over the record, in both notations."""
    record = N * DT
    for axis in entry["axes"].values():
        res = axis["resolution"]
        assert res["gauss_markov_tau"]["min"] == pytest.approx(3 * DT)
        assert res["gauss_markov_tau"]["max"] == pytest.approx(0.1 * record)
        k = res["random_walk_limit"]
        n = axis["components"][0]["params"]["arw"]["value"]
        assert n / record < k["value"] < 100 * n / record
        assert (k["unit"], k["same_as"], k["display"]["unit"]) == ("rad/s²/√Hz", "rad/s/√s", "°/h/√h")
        assert k["display"]["value"] == pytest.approx(k["value"] * 180 / math.pi * 3600 * 60)
        assert any(s.startswith("a random walk below K = ") and "not resolvable in 81.9 s" in s
                   for s in res["notes"])


def test_units_and_interval_level(entry):
    assert entry["interval_level"] == 0.95
    arw = entry["axes"]["x"]["components"][0]["params"]["arw"]
    assert arw["unit"] == "rad/s/√Hz" and arw["display"]["unit"] == "°/√h"
    assert arw["display"]["value"] == pytest.approx(arw["value"] * 180 / math.pi * 60)


def _param(v, lo, hi, **extra):
    return {"value": v, "ci": [lo, hi], "unit": "-", **extra}


def test_export_refuses_what_the_model_does_not_identify(tmp_path, capsys):
    """The issue's model as the identification wrote it before (white 2x low with an interval
    of dozens of decades, a Gauss–Markov τ of 4 ms at 100 Hz: EKF2_GYR_B_NOISE 0.9 rad/s²)
    is refused naming both; a walk marked not identified is refused for every filter
    format, and written with --force, the file saying so."""
    old = {"components": [{"kind": "white", "params": {"arw": _param(1e-4, 9.8e-24, 1.02e15)}},
                          {"kind": "gauss_markov", "params": {
                              "sigma": _param(4.4e-3, 4.6e-4, 4.2e-2),
                              "tau": _param(4.04e-3, 6.5e-4, 2.5e-2)}}]}
    doc = {"devices": [{"device": "xsens", "status": "ok", "sample_interval": 0.01,
                        "axes": {"x": old, "y": old, "z": old}}]}
    path = tmp_path / "old.json"
    path.write_text(json.dumps(doc))
    out = tmp_path / "ekf.params"
    assert main(["export", str(path), "--format", "px4-ekf", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "axis x: white arw is not identified" in err and "gauss_markov tau" in err
    assert "--force" in err and not out.exists()

    walk = {"components": [
        {"kind": "white", "params": {"arw": _param(4.4e-4, 4.3e-4, 4.5e-4, status="identified")}},
        {"kind": "random_walk", "params": {"rrw": _param(2e-5, 1e-9, 0.4, status="not_identified",
                                                         why="its 95 % interval spans 8.6 decades")}}]}
    doc = {"devices": [{"device": "imu", "status": "ok", "sample_interval": 0.01,
                        "axes": {"x": walk, "y": walk, "z": walk}}]}
    path = tmp_path / "walk.json"
    path.write_text(json.dumps(doc))
    for fmt in ("px4-ekf", "ardupilot-ekf", "kalibr"):
        assert main(["export", str(path), "--format", fmt, "--accel-noise-density", "1e-3",
                     "--accel-random-walk", "1e-4"]) == 2, fmt
        err = capsys.readouterr().err
        assert "random_walk rrw is not identified (its 95 % interval spans 8.6 decades)" in err, fmt
    assert main(["export", str(path), "--format", "px4-ekf", "--force", "--out", str(out)]) == 0
    text = out.read_text()
    assert "# WARNING: written with --force: device imu axis x: random_walk rrw is not identified" in text
    assert "EKF2_GYR_B_NOISE" in text
