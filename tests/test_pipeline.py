"""Streaming fits over Parquet datasets: same numbers as the in-memory fit, per-device
failures recorded, resumable state, the command line."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from pipeline_data import CHUNK, MODEL, add_bad_devices, load_outputs, make_dataset

from diffgyro import calibration
from diffgyro.errors import DataError
from diffgyro.fit import fit
from diffgyro.internal import ReadConfig, WorkDir, expand_inputs, index_dataset
from diffgyro.io import load
from diffgyro.pipeline import fit_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("stream") / "data"
    ids = make_dataset(root)
    bad = add_bad_devices(root)
    return root, ids, bad


@pytest.fixture(scope="module")
def streamed(dataset, tmp_path_factory):
    root, _, _ = dataset
    out = tmp_path_factory.mktemp("out") / "cal.json"
    chunks = []
    summary = fit_dataset([root], MODEL, out=out, chunk_devices=CHUNK, progress=False,
                          on_chunk=lambda r: chunks.append(r["chunk"]))
    return out, summary, chunks


def test_streamed_equals_in_memory_fit(dataset, streamed):
    root, ids, _ = dataset
    out, summary, _ = streamed
    good = [f for f in sorted(root.glob("part-0*.parquet"))]
    reference = fit(MODEL, load(good))
    cal = calibration.load(out)
    by_name = {d.device: d for d in cal.devices}
    assert "f0-000" not in by_name          # duplicated across files: never fitted
    for i, name in enumerate(reference.devices):
        if name == "f0-000":
            continue
        d = by_name[name]
        assert d.status == reference.status_name(i) == "ok"
        np.testing.assert_allclose(d.beta, np.asarray(reference.params.beta[i]), rtol=1e-12,
                                   atol=1e-15)
        assert d.quality["rms"] == pytest.approx(float(reference.rms[i]), rel=1e-12)
        assert d.quality["heldout_rms"] == pytest.approx(float(reference.heldout_rms[i]),
                                                         rel=1e-12)
        assert d.temp_centre == pytest.approx(float(reference.norm.centre[i]), rel=1e-14)


def test_every_device_once_in_dataset_order_with_reasons(dataset, streamed):
    root, ids, bad = dataset
    out, summary, chunks = streamed
    _, rows = load_outputs(out)
    names = [r["device"] for r in rows]
    expected = ids + [f"bad-{i:03d}" for i in range(5)]
    assert names == expected
    assert summary.n_devices == len(expected)
    assert chunks == list(range(-(-len(expected) // CHUNK)))
    status = {r["device"]: r for r in rows}
    for dev, text in bad.items():
        assert status[dev]["status"] == "invalid_data"
        assert text in status[dev]["reason"], status[dev]["reason"]
        assert status[dev]["params"] is None
    # the reasons name the file, device, column and row
    assert "column gx" in status["bad-001"]["reason"] and "row 218" in status["bad-001"]["reason"]
    ok = [r for r in rows if r["device"] not in bad]
    assert all(r["status"] == "ok" and r["n_samples"] == 200 for r in ok)
    assert summary.n_ok == len(ok) and summary.n_failed == len(bad)


def test_rerun_skips_finished_chunks_and_gives_the_same_output(dataset, streamed):
    root, _, _ = dataset
    out, _, _ = streamed
    before = load_outputs(out)
    again = fit_dataset([root], MODEL, out=out, chunk_devices=CHUNK, progress=False)
    assert again.chunks_run == 0 and again.chunks_total > 0
    assert load_outputs(out) == before


def test_missing_chunk_file_is_recomputed_identically(dataset, streamed, tmp_path):
    root, _, _ = dataset
    out, _, _ = streamed
    work = tmp_path / "work"
    shutil.copytree(str(out) + ".work", work)
    (work / "chunks" / "chunk-000002.json").unlink()
    (work / "chunks" / "chunk-000003.json").write_text('{"chunk": 3, "devi')  # torn file
    out2 = tmp_path / "cal.json"
    s = fit_dataset([root], MODEL, out=out2, work_dir=work, chunk_devices=CHUNK, progress=False)
    assert s.chunks_run == 2
    assert load_outputs(out2) == load_outputs(out)


def test_changed_command_refuses_to_resume(dataset, streamed):
    root, _, _ = dataset
    out, _, _ = streamed
    with pytest.raises(DataError, match="different run"):
        fit_dataset([root], "bias_poly(2)", out=out, chunk_devices=CHUNK, progress=False)
    with pytest.raises(DataError, match="different run"):
        fit_dataset([root], MODEL, out=out, chunk_devices=CHUNK + 1, progress=False)


def test_one_run_per_work_dir(dataset, tmp_path):
    root, _, _ = dataset
    held = WorkDir(tmp_path / "w")
    held.lock()
    try:
        with pytest.raises(DataError, match="another diffgyro run"):
            fit_dataset([root], MODEL, work_dir=tmp_path / "w", chunk_devices=CHUNK,
                        progress=False)
    finally:
        held.unlock()


def test_chunks_read_only_their_row_groups(dataset):
    root, ids, _ = dataset
    index = index_dataset(expand_inputs([root]), ReadConfig(wanted=("rate", "temp")))
    assert index.devices[: len(ids)] == ids
    assert all(index.n_rows[d] == 200 for d in ids)
    # 450-row groups: a device spans at most two of them
    spans = [len(index.locations[d][1]) for d in ids]
    assert max(spans) == 2 and min(spans) == 1


def test_interleaved_rows_and_renamed_columns_in_other_units(dataset, tmp_path):
    """Rows of devices interleaved in time order, columns renamed, gyro in deg/s, time in ms:
    the same numbers as the standard file."""
    import pandas as pd
    from pipeline_data import write_parquet

    root, _, _ = dataset
    src = root / "part-01.parquet"
    frame = pd.read_parquet(src)
    frame = frame.sort_values(["t", "device"], kind="stable").reset_index(drop=True)
    for c in ("gx", "gy", "gz"):
        frame[c] = np.rad2deg(frame[c])
    frame["t"] = frame["t"] * 1000.0
    frame = frame.rename(columns={"gx": "gyr_x", "device": "unit"})
    write_parquet(frame, tmp_path / "mapped" / "x.parquet", row_group_size=97)
    out = tmp_path / "cal.json"
    fit_dataset([tmp_path / "mapped"], MODEL, out=out, chunk_devices=CHUNK, progress=False,
                columns={"gx": "gyr_x", "device": "unit"},
                units={"gyro": "deg/s", "t": "ms"})
    ref = tmp_path / "ref.json"
    fit_dataset([src], MODEL, out=ref, chunk_devices=CHUNK, progress=False)
    a, b = calibration.load(out), calibration.load(ref)
    assert [d.device for d in a.devices] == [d.device for d in b.devices]
    for x, y in zip(a.devices, b.devices):
        np.testing.assert_allclose(x.beta, y.beta, rtol=1e-9, atol=1e-14)


def test_file_level_problems_stop_before_fitting(tmp_path, dataset):
    root, _, _ = dataset
    with pytest.raises(DataError, match="no Parquet files"):
        fit_dataset([tmp_path], MODEL, work_dir=tmp_path / "w", progress=False)
    with pytest.raises(DataError, match="column 'nope'"):
        fit_dataset([root], MODEL, work_dir=tmp_path / "w", progress=False,
                    columns={"gx": "nope"})
    import pandas as pd
    from pipeline_data import write_parquet

    frame = pd.read_parquet(root / "part-00.parquet", columns=["device", "t", "gx", "gy", "gz"])
    write_parquet(frame, tmp_path / "notemp" / "a.parquet")
    with pytest.raises(DataError, match="no input file has it"):
        fit_dataset([tmp_path / "notemp"], MODEL, work_dir=tmp_path / "w2", progress=False)


def test_cli_streams_a_directory_with_the_json_contract(dataset, tmp_path, capsys):
    from diffgyro.cli import main

    root, ids, bad = dataset
    out = tmp_path / "cal.json"
    code = main(["fit", str(root), "--model", MODEL, "--chunk-devices", str(CHUNK), "--out",
                 str(out), "--results", str(tmp_path / "res.parquet"), "--json"])
    assert code == 0
    captured = capsys.readouterr()
    obj = json.loads(captured.out)
    assert obj["model"] == MODEL
    assert [d["device"] for d in obj["devices"]] == ids + [f"bad-{i:03d}" for i in range(5)]
    for d in obj["devices"]:
        assert {"device", "status", "rms", "heldout_rms", "noise_floor", "params"} <= set(d)
    assert "devices ok" in captured.err
    import pyarrow.parquet as pq

    table = pq.read_table(tmp_path / "res.parquet").to_pandas()
    assert list(table["device"]) == [d["device"] for d in obj["devices"]]
    assert set(table.loc[table.status != "ok", "device"]) == set(bad)


def test_fast_calibration_entries_equal_from_fit():
    """The pipeline's entry builder gives exactly calibration.from_fit's entries, including
    time constants, non-ok statuses and non-finite numbers."""
    from diffgyro.fit import FitOptions, FitResult
    from diffgyro.internal import calibration_entries
    from diffgyro.model import ErrorModel, Params
    from diffgyro.signals import TempNorm

    model = ErrorModel.from_spec("bias_poly(1)+thermal_lag+gradient+aux(vdd)")
    d, p, q, t = 4, model.n_params, model.n_nonlinear, len(model.terms)
    rng = np.random.default_rng(0)
    beta = rng.standard_normal((d, 3, p))
    beta[2, 1, 0] = np.nan
    rms = rng.uniform(1e-5, 1e-4, d)
    rms[2] = np.inf
    status = np.array([0, 1, 3, 2])
    range_flags = np.zeros((d, t), bool)
    range_flags[2, 0] = True
    collinear = np.zeros((d, t), bool)
    collinear[3, 1:] = True
    k = 3 * p + q
    result = FitResult(
        model=model, devices=("a", "b", "c", "d"),
        params=Params(beta=beta, theta=rng.uniform(1, 6, (d, q))),
        norm=TempNorm(centre=rng.uniform(0, 30, d), scale=rng.uniform(5, 40, d)),
        temp_range=np.sort(rng.uniform(-10, 60, (d, 2)), axis=1), cov=np.zeros((d, k, k)),
        rms=rms, heldout_rms=rms * 1.1, fold_mse=np.zeros((d, 5)),
        noise_floor=rng.uniform(1e-5, 1e-4, d), noise_axes=np.zeros((d, 3)),
        sigma=np.zeros((d, 3)), steps=np.array([5, 100, 3, 1]), status=status,
        range_flags=range_flags, collinear=collinear, n_samples=np.full(d, 200.0),
        options=FitOptions(),
        aux_norm={"vdd": TempNorm(centre=rng.uniform(4, 6, d), scale=rng.uniform(0.1, 1, d))},
        aux_range={"vdd": np.sort(rng.uniform(4, 6, (d, 2)), axis=1)})
    expected = [calibration.entry_json(x.__dict__) for x in calibration.from_fit(result).devices]
    got = calibration_entries(result)
    assert json.dumps(got, allow_nan=False) == json.dumps(expected, allow_nan=False)
    assert got[2]["status_detail"].startswith("insufficient_range")
    assert "thermal_lag.tau" in got[0]["params"]["shared"]
    assert set(got[1]["aux"]["vdd"]) == {"centre", "scale", "range"}


def test_streamed_diagnosis_names_the_missing_effect(tmp_path):
    """The truth has a gradient term; diagnosing bias_poly(1) without it finds it missing
    (gradient, or its look-alike temp_diff, first); a device with bad data is recorded."""
    import io

    import pandas as pd
    from pipeline_data import simulated, write_parquet

    from diffgyro.pipeline import diagnose_dataset

    batch, _ = simulated(3, 5, "g-")
    frame = batch.to_frame()
    bad = frame[frame.device == "g-002"].copy()
    bad["device"] = "g-bad"
    bad.loc[bad.index[5], "temp"] = np.inf
    write_parquet(pd.concat([frame, bad], ignore_index=True), tmp_path / "d" / "a.parquet")
    buf = io.StringIO()
    summary = diagnose_dataset([tmp_path / "d"], "bias_poly(1)", chunk_devices=CHUNK,
                               work_dir=tmp_path / "w", progress=False, json_stream=buf,
                               fit_options={"dtemp_window": 60.0})
    obj = json.loads(buf.getvalue())
    assert obj["model"] == "bias_poly(1)"
    devs = {d["device"]: d for d in obj["devices"]}
    assert list(devs) == ["g-000", "g-001", "g-002", "g-bad"]
    for name in ("g-000", "g-001", "g-002"):
        d = devs[name]
        assert d["verdict"] == "missing_effect", d["explanation"]
        assert d["candidates"][0]["effect"] in ("gradient", "temp_diff")
        assert d["candidates"][0]["significant"] is True
        assert d["candidates"][0]["heldout_rms"] < d["heldout_rms"]
    assert devs["g-bad"]["status"] == "invalid_data" and "infinite" in devs["g-bad"]["reason"]
    assert summary.statuses == {"ok": 3, "invalid_data": 1}
    lines = (tmp_path / "w" / "results.jsonl").read_text().splitlines()
    assert [json.loads(x)["device"] for x in lines] == list(devs)
