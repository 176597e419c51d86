"""The command line: bad input gives one line naming file/device/column/row and exit 2;
fit --json / --out and compensate follow the command-line contract."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from diffgyro.cli import main

BAD = {
    "missing_column": ("t,gx,gy\n0,0,0\n1,0,0\n", "column gz"),
    "non_numeric": ("t,gx,gy,gz\n0,0,0,0\n1,0,abc,0\n2,0,0,0\n", "row 2"),
    "nan": ("t,gx,gy,gz\n0,0,0,0\n1,0,nan,0\n2,0,0,0\n", "column gy"),
    "inf": ("t,gx,gy,gz\n0,0,0,0\n1,0,0,inf\n2,0,0,0\n", "column gz"),
    "time_backwards": ("t,gx,gy,gz\n0,0,0,0\n2,0,0,0\n1,0,0,0\n", "row 3"),
    "time_duplicate": ("t,gx,gy,gz\n0,0,0,0\n1,0,0,0\n1,0,0,0\n", "row 3"),
    "too_few_samples": ("t,gx,gy,gz,temp\n0,0,0,0,20\n1,0,0,0,21\n2,0,0,0,22\n", "fewer samples"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_is_one_clear_line(case, tmp_path, capsys):
    text, must = BAD[case]
    path = tmp_path / f"{case}.csv"
    path.write_text(text)
    code = main(["fit", str(path), "--model", "bias_poly(2)"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert str(path) in err or path.name in err
    assert must in err, err


@pytest.mark.parametrize("argv", [
    ["fit", "--model", "bias_poly(2)", "--json"],
    ["diagnose", "--model", "bias_poly(0)", "--json"],
    ["allan", "--json"],
    ["noise", "--json"],
    ["recipe", "binned-thermal", "--json"],
    ["compensate", "--cal", "CAL", "--out", "OUT", "--json"],
])
def test_json_error_is_an_object_on_stdout(argv, tmp_path, capsys):
    """Under --json, every command that takes it gives its error as one JSON object on
    stdout (the DataError's fields) as well as the one line on stderr, exit code 2."""
    path = tmp_path / "bad.csv"
    path.write_text(BAD["missing_column"][0])
    cal = tmp_path / "cal.json"
    cal.write_text("{}")
    argv = [str(cal) if a == "CAL" else str(tmp_path / "o.csv") if a == "OUT" else a
            for a in argv]
    code = main([*argv[:2], str(path), *argv[2:]] if argv[0] == "recipe"
                else [argv[0], str(path), *argv[1:]])
    out, err = capsys.readouterr()
    assert code == 2
    line, = err.strip().splitlines()
    doc = json.loads(out)
    assert set(doc) == {"error", "problem", "file", "device", "column", "row", "hint"}
    assert line == f"diffgyro: error: {doc['error']}"
    if argv[0] != "compensate":  # compensate reads the (empty) calibration first
        assert doc["file"] == str(path) and doc["column"] == "gz" and doc["row"] is None
    assert main([argv[0], str(tmp_path / "nope.csv"), "--json"] if argv[0] in ("allan", "noise")
                else ["fit", str(tmp_path / "nope.csv"), "-m", "bias_poly(0)", "--json"]) == 2
    out, err = capsys.readouterr()
    assert json.loads(out)["file"] == str(tmp_path / "nope.csv") and err.count("\n") == 1
    assert main(["fit", str(path), "-m", "bias_poly(2)+gradiant", "--json"]) == 2  # a SpecError
    doc = json.loads(capsys.readouterr().out)
    assert doc["problem"] == "unknown effect 'gradiant'" and doc["file"] is None


def test_unknown_unit_and_repeated_device(tmp_path, capsys):
    a = tmp_path / "a.csv"
    a.write_text("device,t,gx,gy,gz\nu1,0,0,0,0\nu1,1,0,0,0\nu1,2,0,0,0\n")
    assert main(["fit", str(a), "--model", "bias_poly(0)", "--gyro-unit", "furlong/s"]) == 2
    assert "furlong" in capsys.readouterr().err
    b = tmp_path / "b.csv"
    b.write_text(a.read_text())
    assert main(["fit", str(a), str(b), "--model", "bias_poly(0)"]) == 2
    err = capsys.readouterr().err
    assert "u1" in err and "a.csv" in err and "b.csv" in err


def test_bad_model_spec_lists_valid_names(tmp_path, capsys):
    a = tmp_path / "a.csv"
    a.write_text("t,gx,gy,gz\n0,0,0,0\n1,0,0,0\n2,0,0,0\n")
    assert main(["fit", str(a), "--model", "bias_poly(2)+gradiant"]) == 2
    err = capsys.readouterr().err
    assert "gradiant" in err and "gradient" in err


@pytest.fixture(scope="module")
def thermal_csv(tmp_path_factory):
    path = tmp_path_factory.mktemp("cli") / "th.csv"
    assert main(["simulate", "--plan", "thermal", "--devices", "3", "--seed", "2",
                 "--duration", "3600", "--rate", "1", "--out", str(path)]) == 0
    return path


def test_fit_json_out_and_compensate(thermal_csv, tmp_path, capsys):
    capsys.readouterr()
    cal = tmp_path / "cal.json"
    assert main(["fit", str(thermal_csv), "--model", "bias_poly(2)", "--json",
                 "--out", str(cal)]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model"] == "bias_poly(2)" and len(out["devices"]) == 3
    for d in out["devices"]:
        assert {"device", "status", "rms", "heldout_rms", "noise_floor", "params"} <= set(d)
    saved = json.loads(cal.read_text())
    assert saved["model"] == "bias_poly(2)" and saved["input_hash"].startswith("sha256:")
    assert {"created", "diffgyro_version", "format_version"} <= set(saved)
    comp = tmp_path / "comp.parquet"
    assert main(["compensate", str(thermal_csv), "--cal", str(cal), "--out", str(comp)]) == 0
    from diffgyro.io import load

    before = {r.device: r for r in load(thermal_csv)}
    after = load(comp)
    assert [r.device for r in after] == list(before)
    for r in after:
        np.testing.assert_array_equal(r.t, before[r.device].t)       # nothing reordered or lost
        np.testing.assert_array_equal(r.temp, before[r.device].temp)
        assert np.abs(r.gyro.mean(axis=0)).max() < np.abs(before[r.device].gyro.mean(axis=0)).max()


def test_console_script_has_no_traceback(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,gx,gy,gz\n0,0,0,0\n0,0,0,0\n")
    p = subprocess.run([sys.executable, "-m", "diffgyro", "fit", str(bad), "--model", "bias_poly(0)"],
                       capture_output=True, text=True)
    assert p.returncode == 2 and "Traceback" not in p.stderr and "row 2" in p.stderr


def test_fit_widens_the_dtemp_window_for_a_coarse_read_out(tmp_path, capsys):
    """Without --dtemp-window, fit picks the window diagnose would (wider than 60 s for a
    0.5 °C read-out at 1 Hz); an explicit window is kept."""
    from diffgyro import Batch
    from diffgyro.internal import suggest_dtemp_window
    from diffgyro.io import load, save
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 2, effects="bias_poly(1)+gradient", seed=3, duration=3600.0,
                        sample_rate=1.0, temp_quantum=0.5)
    path = tmp_path / "coarse.csv"
    save(batch, path)
    expected = suggest_dtemp_window(Batch.from_recordings(load(path)))
    assert expected > 60.0
    for extra, window in (([], expected), (["--dtemp-window", "90"], 90.0)):
        cal = tmp_path / f"cal{len(extra)}.json"
        assert main(["fit", str(path), "--model", "bias_poly(1)+gradient", "--json",
                     "--out", str(cal), *extra]) == 0
        capsys.readouterr()
        assert json.loads(cal.read_text())["dtemp_window"] == window
