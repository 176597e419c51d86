"""Extra logged columns: loading, the aux(NAME) term, both fit paths, calibration files,
compensation (JAX and numpy-only apply.py) and bad input."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import diffgyro
from diffgyro import apply as A
from diffgyro import calibration as C
from diffgyro import io
from diffgyro.cli import main
from diffgyro.data import Batch, Recording
from diffgyro.effects import parse_spec
from diffgyro.errors import DataError, SpecError
from diffgyro.fit import fit
from diffgyro.simulate import simulate

SPEC = "bias_poly(2)+aux(vdd,2)"


@pytest.fixture(scope="module")
def supply_batch():
    diffgyro.enable_x64()
    return simulate("thermal", 3, effects=SPEC, seed=4, duration=7200.0, sample_rate=1.0,
                    noise={"arw": 2e-5, "rrw": 0.0, "bias_instability": 0.0})


def _with_aux(batch: Batch, aux) -> Batch:
    """The batch's recordings with extra columns replaced (``aux``: name -> per-device list)."""
    recs = batch.recordings()
    return Batch.from_recordings([
        Recording(t=r.t, gyro=r.gyro, temp=r.temp, accel=r.accel, device=r.device,
                  source=f"{r.device}.csv", aux={k: v[i] for k, v in aux.items()})
        for i, r in enumerate(recs)])


# ----------------------------------------------------------------------------- grammar


def test_spec_grammar_takes_column_arguments():
    (t,) = parse_spec("aux(vdd)")
    assert (t.column, t.order, t.spec, t.requires()) == ("vdd", 1, "aux(vdd)",
                                                         frozenset({"aux:vdd"}))
    terms = parse_spec("bias_poly(2)+aux( board.t2 , 3 )+aux(vdd)")
    assert [x.spec for x in terms] == ["bias_poly(2)", "aux(board.t2,3)", "aux(vdd)"]
    for bad, words in [("aux", "needs a column name"), ("aux(vdd,0)", "below the minimum"),
                       ("aux(2x)", "not a column name"), ("aux(vdd)+aux(vdd,2)", "more than once"),
                       ("bias_poly(2,3)", "at most 1 argument"), ("gradient(vdd)", "no argument")]:
        with pytest.raises(SpecError, match=words):
            parse_spec(bad)


# ----------------------------------------------------------------------------- loading


def test_loader_keeps_numeric_extras_warns_once_about_text(tmp_path):
    path = tmp_path / "log.csv"
    rows = ["t,gx,gy,gz,Supply V,mode,heater,note"]
    for k in range(6):
        rows.append(f"{k},0.1,0.2,0.3,{5 + 0.01 * k},{'ab'[k % 2]},{0.5 * k},{'' if k else 'x'}")
    path.write_text("\n".join(rows) + "\n")
    with warnings.catch_warnings(record=True) as got:
        warnings.simplefilter("always")
        (rec,) = io.load(path, columns=io.parse_columns("vdd=Supply V"))
    assert [str(w.message) for w in got] == [
        f"ignored non-numeric columns mode, note in file {path}"]
    assert list(rec.aux) == ["heater", "vdd"]
    np.testing.assert_array_equal(rec.aux["vdd"], 5 + 0.01 * np.arange(6))
    report = io.LoadReport()
    io.load(path, report=report)
    assert report.lines() == [f"ignored non-numeric columns mode, note in file {path}"]
    # a name that is not a standard column but not a column name either
    with pytest.raises(DataError, match="unknown standard column"):
        io.parse_columns("supply v=Supply V")


@pytest.mark.parametrize("ext", ["csv", "parquet", "npz"])
def test_save_and_frame_keep_extra_columns(tmp_path, ext):
    t = np.arange(50.0)
    rec = Recording(t=t, gyro=np.zeros((50, 3)), temp=20 + 0.1 * t, device="a",
                    aux={"vdd": 5 + 1e-3 * np.sin(t), "duty": 0.3 + 0 * t})
    path = io.save(rec, tmp_path / f"x.{ext}")
    (back,) = io.load(path)
    assert list(back.aux) == ["duty", "vdd"]
    for k in rec.aux:
        np.testing.assert_array_equal(back.aux[k], rec.aux[k])
    assert list(rec.to_frame().columns[-2:]) == ["duty", "vdd"]
    batch = Batch.from_recordings([rec])
    assert batch.aux["vdd"].shape == (1, batch.length)
    assert batch.aux["vdd"][0, -1] == rec.aux["vdd"][-1]  # padding holds the last value


def test_batch_keeps_only_common_extra_columns():
    t = np.arange(10.0)
    a = Recording(t=t, gyro=np.zeros((10, 3)), device="a", aux={"vdd": t, "x": t})
    b = Recording(t=t[:8], gyro=np.zeros((8, 3)), device="b", aux={"vdd": t[:8]})
    batch = Batch.from_recordings([a, b])
    assert list(batch.aux) == ["vdd"]
    np.testing.assert_array_equal(batch.recording(1).aux["vdd"], t[:8])
    assert list(batch.select([1]).aux) == ["vdd"]


# ----------------------------------------------------------------------------- fits


def test_both_fit_paths_recover_aux_coefficients(supply_batch):
    batch, truth = supply_batch
    assert list(batch.aux) == ["vdd"]
    kw = dict(norm=truth.norm, aux_norm=truth.aux_norm)
    sums = fit(SPEC, batch, path="sums", **kw)
    direct = fit(SPEC, batch, path="direct", solver="lm", **kw)
    assert np.all(np.asarray(sums.status) == 0)
    b_s, b_d = np.asarray(sums.params.beta), np.asarray(direct.params.beta)
    np.testing.assert_allclose(b_s, b_d, rtol=0, atol=1e-10 * np.abs(b_s).max())
    true = np.asarray(truth.params.beta)
    se = np.stack([np.asarray(sums.stderr(i).beta) for i in range(batch.n_devices)])
    assert np.all(np.abs(b_s - true) < 6 * se + 1e-9)
    # the aux coefficients are large against their errors: they are really seen
    assert np.all(np.abs(true[..., 3:]) > 20 * se[..., 3:])
    assert list(sums.aux_norm) == ["vdd"] and sums.aux_range["vdd"].shape == (3, 2)


def test_calibration_round_trip_compensate_and_apply(supply_batch, tmp_path):
    batch, truth = supply_batch
    res = fit(SPEC, batch)
    cal = C.from_fit(res, batch)
    path = tmp_path / "cal.json"
    C.save(cal, path)
    obj = json.loads(path.read_text())
    entry = obj["devices"][0]["aux"]["vdd"]
    assert set(entry) == {"centre", "scale", "range"}
    assert entry["range"] == pytest.approx([batch.aux["vdd"][0, :batch.n_valid[0]].min(),
                                            batch.aux["vdd"][0, :batch.n_valid[0]].max()])
    out, _ = C.compensate(C.load(path), batch)
    for i in range(batch.n_devices):
        rec = batch.recording(i)
        om = np.asarray(out.gyro[i, :rec.n])
        assert np.std(om, axis=0).max() < 3 * 2e-5  # the model removed, noise left
        ref = A.compensate(obj, rec.device, rec.t, rec.gyro, temp=rec.temp, aux=rec.aux)
        np.testing.assert_allclose(om, ref, rtol=0, atol=1e-12)
    # an old-style file can't claim an aux model without its columns' centring
    del obj["devices"][0]["aux"]
    with pytest.raises(SpecError, match="aux must describe the extra columns vdd"):
        C.from_json(obj)


def test_compensate_without_the_column_names_it(supply_batch):
    batch, _ = supply_batch
    cal = C.from_fit(fit(SPEC, batch), batch)
    with pytest.raises(DataError, match="needs extra column 'vdd', not in the data") as err:
        C.compensate(cal, _with_aux(batch, {}))
    assert "file dev000.csv, column vdd" in str(err.value)


@pytest.mark.parametrize("case, words", [
    ("constant", "extra column is constant"),
    ("nan", "holds no numbers"),
    ("gap", "missing or non-finite value at sample 5"),
    ("absent", "needs extra column 'vdd', not in the data"),
])
def test_bad_aux_column_is_one_clear_error(supply_batch, case, words):
    batch, _ = supply_batch
    n = batch.length
    good = [np.asarray(batch.aux["vdd"][i]) for i in range(3)]
    cols = {"constant": [good[0], np.full(n, 5.0), good[2]],
            "nan": [good[0], np.full(n, np.nan), good[2]],
            "gap": [good[0], np.where(np.arange(n) == 4, np.nan, good[1]), good[2]]}
    data = _with_aux(batch, {"vdd": [c[:int(batch.n_valid[i])] for i, c in
                                     enumerate(cols[case])]} if case in cols else {})
    with pytest.raises(DataError, match=words) as err:
        fit("bias_poly(2)+aux(vdd)", data)
    text = str(err.value)
    assert "column vdd" in text and text.count("\n") == 0
    if case != "absent":
        assert "device dev001" in text and "file dev001.csv" in text


def test_cli_fit_compensate_and_text_column(supply_batch, tmp_path, capsys):
    batch, _ = supply_batch
    data = tmp_path / "run.csv"
    io.save(batch.select([0]), data)
    cal = tmp_path / "cal.json"
    assert main(["fit", str(data), "--model", "bias_poly(2)+aux(vdd)", "--out", str(cal)]) == 0
    assert json.loads(cal.read_text())["model"] == "bias_poly(2)+aux(vdd)"
    # the same data with the column as text: ignored with one line, then a clear error
    frame = batch.recording(0).to_frame()
    frame["vdd"] = [f"{v:.4f} V" for v in frame["vdd"]]
    text = tmp_path / "text.csv"
    frame.to_csv(text, index=False)
    capsys.readouterr()
    assert main(["compensate", str(text), "--cal", str(cal), "--out",
                 str(tmp_path / "c.csv")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == f"diffgyro: ignored non-numeric column vdd in file {text}"
    assert err[1].startswith("diffgyro: error:") and "extra column 'vdd'" in err[1]
    assert len(err) == 2
