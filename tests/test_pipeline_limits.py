"""``--limits`` on the streaming run (``fit DIR --chunk-devices N``, ``diagnose``): every
device judged as the in-memory fit judges it, the yield and the rejected units in the
JSON, the calibration file and the results table; other bounds re-merge without fitting.

Data: the streaming tests' simulated devices (pipeline_data: same model, sizes and chunk,
so the compiled fit is shared) and a file of faulty devices.
"""

from __future__ import annotations

import contextlib
import io
import json

import numpy as np
import pytest
from pipeline_data import CHUNK, MODEL, add_bad_devices, make_dataset

from diffgyro import calibration
from diffgyro.cli import main
from diffgyro.pipeline import diagnose_dataset, fit_dataset

#: The streaming fit's dT/dt window (60 s unless given): the in-memory reference uses it too.
WINDOW = ["--dtemp-window", "60"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("stream-limits") / "data"
    ids = make_dataset(root, files=(4, 3))
    bad = add_bad_devices(root)
    return root, ids, bad


def _limits(path, c0_max: float) -> str:
    path.write_text(f"""[about]
name = "stream line"
[limits]
status = "ok"
"params.x.bias_poly(1).c0" = {{ abs = true, max = {c0_max!r} }}   # rad/s
allan.rrw = {{ max = 1.0, optional = true }}   # rad/s^2/sqrt(Hz): 200 samples seldom show one
temp_range.span = {{ min = 1.0 }}                # °C
""")
    return str(path)


@pytest.fixture(scope="module")
def reference(dataset, tmp_path_factory):
    """In-memory ``fit --limits --json`` of the good files, with a c0 bound at the median."""
    root, ids, _ = dataset
    folder = tmp_path_factory.mktemp("ref")
    files = [str(p) for p in sorted(root.glob("part-0*.parquet"))]
    probe = _limits(folder / "probe.toml", 1.0)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        assert main(["fit", *files, "--model", MODEL, "--json", "--limits", probe, *WINDOW]) == 0
    c0 = [abs(d["params"]["x"]["bias_poly(1).c0"]) for d in json.loads(buf.getvalue())["devices"]]
    bound = float(np.median(c0))
    limits = _limits(folder / "line.toml", bound)
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        assert main(["fit", *files, "--model", MODEL, "--json", "--limits", limits, *WINDOW]) == 0
    return json.loads(buf.getvalue()), limits, folder


def test_streamed_fit_judges_every_device_as_the_in_memory_fit(dataset, reference, tmp_path,
                                                                capsys):
    root, ids, bad = dataset
    ref, limits, _ = reference
    out = tmp_path / "cal.json"
    assert main(["fit", str(root), "--model", MODEL, "--chunk-devices", str(CHUNK), "--out",
                 str(out), "--results", str(tmp_path / "res.parquet"), "--json",
                 "--limits", limits]) == 0
    cap = capsys.readouterr()
    got = json.loads(cap.out)
    devs = {d["device"]: d for d in got["devices"]}
    expect = {d["device"]: d for d in ref["devices"]}
    judged = [n for n in expect if n != "f0-000"]  # f0-000 is in two files: never fitted
    assert any(expect[n]["limits"]["result"] == "pass" for n in judged)
    assert any(expect[n]["limits"]["result"] == "fail" for n in judged)
    for name in judged:
        a, b = devs[name]["limits"], expect[name]["limits"]
        assert a["result"] == b["result"], name
        assert [x["limit"] for x in a["broken"]] == [x["limit"] for x in b["broken"]]
        for x, y in zip(a["broken"], b["broken"]):
            assert x["by"] == pytest.approx(y["by"], rel=1e-9)
        assert set(devs[name]["allan"]) == {"arw", "bias_instability", "rrw", "x", "y", "z"}
        assert devs[name]["temp_range"] == pytest.approx(expect[name]["temp_range"], rel=1e-12)
        assert devs[name]["temp_range"]["span"] > 1.0
        for ax in "xyz":  # the read-outs of the residual, computed in the chunk
            for k, v in expect[name]["allan"][ax].items():
                w = devs[name]["allan"][ax][k]
                assert (w is None) == (v is None) and (v is None or w == pytest.approx(v, rel=1e-9))
    for name in [*bad, "f0-000"]:  # faulty data: rejected, with the status that says why
        assert devs[name]["limits"]["result"] == "fail"
        assert devs[name]["limits"]["broken"][0]["limit"] == "status"
    rejected = [n for n in devs if devs[n]["limits"]["result"] == "fail"]
    lim = got["limits"]
    assert lim["rejected"] == rejected and lim["failed"] == len(rejected)
    assert lim["passed"] + lim["failed"] == len(devs)
    assert lim["yield"] == pytest.approx(lim["passed"] / len(devs))
    assert f"{lim['passed']} of {len(devs)} devices pass" in cap.err
    # the calibration file and the results table say the same
    saved = json.loads(out.read_text())
    assert saved["limits"] == lim
    for d in saved["devices"]:
        assert d["limits"] == devs[d["device"]]["limits"]
    assert calibration.load(out).limits == lim
    import pyarrow.parquet as pq

    table = pq.read_table(tmp_path / "res.parquet").to_pandas()
    assert dict(zip(table["device"], table["limits_result"])) == {
        n: d["limits"]["result"] for n, d in devs.items()}


def test_other_bounds_merge_again_without_fitting(dataset, reference, tmp_path):
    root, _, _ = dataset
    _, _, folder = reference
    work = tmp_path / "work"
    first = fit_dataset([root], MODEL, work_dir=work, chunk_devices=CHUNK, progress=False,
                        limits=_limits(folder / "strict.toml", 1e-9))
    assert first.limits["passed"] == 0
    again = fit_dataset([root], MODEL, work_dir=work, chunk_devices=CHUNK, progress=False,
                        limits=_limits(folder / "loose.toml", 10.0))
    assert again.chunks_run == 0
    assert again.limits["passed"] == first.n_ok and again.limits["failed"] == first.n_failed


def test_streamed_diagnose_gives_each_device_its_result(dataset, reference, tmp_path):
    root, _, bad = dataset
    ref, limits, _ = reference
    buf = io.StringIO()
    summary = diagnose_dataset([root], MODEL, ["gradient"], chunk_devices=CHUNK,
                               work_dir=tmp_path / "w", progress=False, json_stream=buf,
                               fit_options={"dtemp_window": 60.0}, limits=limits)
    obj = json.loads(buf.getvalue())
    devs = {d["device"]: d for d in obj["devices"]}
    expect = {d["device"]: d["limits"]["result"] for d in ref["devices"] if d["device"] != "f0-000"}
    assert {n: devs[n]["limits"]["result"] for n in expect} == expect
    assert all(devs[n]["limits"]["result"] == "fail" for n in bad)
    assert obj["limits"] == summary.limits and summary.limits["rejected"] == [
        n for n, d in devs.items() if d["limits"]["result"] == "fail"]
