"""The command line explains itself: one line saying what was written, units and reasons
in recipe and Allan output, "did you mean" for a misspelt effect, every coefficient of a
term of order k, device names never cut alike, kalibr input read by its content."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from diffgyro.cli import main


@pytest.fixture(scope="module")
def thermal(tmp_path_factory):
    """Two devices through a thermal plan whose bias is linear in temperature on every
    axis, with names such as one DataFlash log gives its IMUs."""
    import pandas as pd

    from diffgyro.io import save
    from diffgyro.simulate import simulate

    d = tmp_path_factory.mktemp("surface")
    batch, _ = simulate("thermal", 2, effects="bias_poly(1)", seed=3, duration=3600.0,
                        sample_rate=2.0)
    save(batch, d / "x.csv")
    frame = pd.read_csv(d / "x.csv")
    frame["device"] = frame["device"].map(dict(zip(
        sorted(frame["device"].unique()),
        ["00000042_thermal_chamber_soak/imu0", "00000042_thermal_chamber_soak/imu1"])))
    frame.to_csv(d / "log.csv", index=False)
    return d


def test_compensate_and_export_say_what_they_wrote(thermal, tmp_path, capsys):
    cal = tmp_path / "cal.json"
    assert main(["fit", str(thermal / "x.csv"), "-m", "bias_poly(1)", "--out", str(cal)]) == 0
    capsys.readouterr()
    out = tmp_path / "c.csv"
    assert main(["compensate", str(thermal / "x.csv"), "--cal", str(cal), "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"wrote {out}: 2 device(s), ") and "corrected by bias_poly(1)" in line
    n = int(re.search(r"(\d+) samples", line).group(1))
    assert n == sum(1 for _ in open(out)) - 1
    params = tmp_path / "p.params"
    assert main(["export", str(cal), "--format", "px4", "--out", str(params)]) == 0
    line = capsys.readouterr().out.strip()
    lines = len(params.read_text().splitlines())
    assert line == f"wrote {params}: px4 calibration of 2 devices (dev000, dev001), {lines} lines"


def test_binned_thermal_gives_units_and_the_reason_per_axis(thermal, capsys):
    assert main(["recipe", "binned-thermal", str(thermal / "x.csv"), "--device", "dev000",
                 "--r-min", "0.9999999"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"offset: \[.*\] rad/s\n", out) and "rad/s per °C" in out
    line = next(s for s in out.splitlines() if s.strip().startswith("accepted:"))
    # with r_min this close to 1 no axis passes, and each says by how much
    assert len(re.findall(r"[xyz] no \(\|r\| 0\.\d+ ≤ r_min 0\.9999999\)", line)) == 3, line
    assert "--r-min" in line


def test_allan_taus_table_shows_each_asked_tau_with_reasons(thermal, tmp_path, capsys):
    out = tmp_path / "allan.json"
    assert main(["allan", str(thermal / "x.csv"), "--taus", "0.5,1,10,100000", "--out",
                 str(out)]) == 0
    text = capsys.readouterr().out
    for head in ("τ = 0.5 s", "τ = 1 s", "τ = 10 s", "τ = 100000 s"):
        assert head in text
    marks = set(re.findall(r"— \[(\d+)\]", text))
    notes = dict(re.findall(r"^\[(\d+)\] (.+)$", text, re.M))
    assert marks and marks <= set(notes)  # every dash has its reason under the table
    assert any("longer than a quarter of the recording" in v for v in notes.values())
    doc = json.loads(out.read_text())
    assert doc["devices"][0]["axes"]["gx"]["tau"] == [0.5, 1.0, 10.0]  # not 0.49999999999
    assert f"wrote {out}" in text


def test_misspelt_effect_gets_did_you_mean(thermal, capsys):
    assert main(["fit", str(thermal / "x.csv"), "-m", "bias_poly(1)+gradiant"]) == 2
    assert "did you mean 'gradient'?" in capsys.readouterr().err


def test_effects_lists_every_coefficient_of_order_k(capsys):
    assert main(["effects"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"bias_poly\(k\).*c0, c1, …, ck", out)
    assert re.search(r"scale_poly\(k\).*s0, s1, …, sk", out)


def test_fit_table_at_80_columns_keeps_two_imus_of_one_log_apart(thermal, capsys, monkeypatch):
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["fit", str(thermal / "log.csv"), "-m", "bias_poly(1)"]) == 0
    out = capsys.readouterr().out
    assert max(map(len, out.splitlines())) <= 80 and "…" not in out
    cells = [line.split("│")[1].strip() for line in out.splitlines() if line.startswith("│")]
    joined = "".join(cells)
    assert "00000042_thermal_chamber_soak/imu0" in joined and joined.endswith("/imu1")


def test_kalibr_export_reads_allan_json_by_content(thermal, tmp_path, capsys):
    allan_json = tmp_path / "allan.json"
    assert main(["allan", str(thermal / "x.csv"), "--json", "--out", str(allan_json)]) == 0
    renamed = tmp_path / "allan_readouts.txt"
    shutil.copy(allan_json, renamed)
    capsys.readouterr()
    code = main(["export", str(renamed), "--format", "kalibr", "--device", "dev000",
                 "--accel-noise-density", "2e-3", "--accel-random-walk", "3e-4"])
    out, err = capsys.readouterr()
    # read as Allan read-outs, not as a recording: it writes, or names what the curves lack
    assert (code == 0 and "gyroscope_noise_density" in out) or \
        (code == 2 and "the Allan curves show no" in err), (out, err)


NUMBER_CELL = re.compile(r"\d\.\d{3}e[-+]\d{2}")


@pytest.mark.parametrize("extra", [[], ["--static-only"]])
def test_fit_table_with_limits_at_80_columns_never_splits_a_number(thermal, tmp_path, capsys,
                                                                   monkeypatch, extra):
    """A number stays whole on one line of an 80-column table (rich folded ``2.898e-0`` /
    ``4`` before): the numeric columns do not wrap, the text columns fold."""
    limits = tmp_path / "limits.toml"
    limits.write_text('[about]\nname = "line"\n\n[limits]\nheldout_rms = { max = 0.01 }\n')
    monkeypatch.setenv("COLUMNS", "80")
    assert main(["fit", str(thermal / "log.csv"), "-m", "bias_poly(1)", "--limits",
                 str(limits), *extra]) == 0
    out = capsys.readouterr().out
    body = [line for line in out.splitlines() if line.startswith("│")]
    drawn = [line for line in out.splitlines() if line[:1] in "┏┃┡│└"]
    assert body and max(map(len, drawn)) <= 80, out
    rows = [[c.strip() for c in line.split("│")[1:-1]] for line in body]
    for cells in rows:  # rms, held-out rms, noise floor: a whole number or (a folded row) none
        nums = cells[2:5]
        assert all(NUMBER_CELL.fullmatch(c) for c in nums) or nums == ["", "", ""], cells
        assert re.fullmatch(r"\d+( of \d+)?|", cells[6]), cells  # samples
    for above, below in zip(rows, rows[1:]):  # no number goes on in the line below
        for a, b in zip(above[2:7], below[2:7]):
            assert not (re.search(r"[\d.e-]$", a) and re.match(r"[\d.e+-]", b)), (a, b, out)
    assert sum(NUMBER_CELL.fullmatch(c) is not None for r in rows for c in r) == 6
