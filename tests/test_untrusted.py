"""Files and specs from elsewhere: the spec parser and the calibration loader give a valid
object or a SpecError/DataError, never another exception (property-based fuzzing)."""

from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from diffgyro import calibration
from diffgyro.calibration import Calibration, DeviceCalibration
from diffgyro.effects import AbstractNoise, format_spec, parse_spec, registry
from diffgyro.errors import DataError, SpecError
from diffgyro.model import ErrorModel

FUZZ = settings(max_examples=300, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])

# --------------------------------------------------------------------------- model specs

NAMES = sorted(registry())
term = st.one_of(
    st.sampled_from(NAMES),
    st.builds(lambda n, k: f"{n}({k})", st.sampled_from(NAMES), st.integers(-3, 12)),
    st.builds(lambda n, k: f"{n}({k})", st.sampled_from(NAMES),
              st.text(alphabet="0123456789 .-+e()x", max_size=6)),
    st.text(alphabet="abcdefghijklmnopqrstuvwxyz_()0123456789 \t\n+", max_size=20),
)
structured_spec = st.lists(term, min_size=0, max_size=6).map("+".join)
spec_like = st.one_of(structured_spec, st.text(max_size=60),
                      st.builds(lambda s, junk: s + junk, structured_spec,
                                st.sampled_from(["\x00", "\u202e", "٣", "１", "(", ")", "++", " ",
                                                 "(2)(3)", "(" + "9" * 50 + ")", "\n"])))


@FUZZ
@given(spec_like)
def test_spec_parser_gives_terms_or_a_spec_error(text):
    try:
        terms = parse_spec(text)
    except SpecError:
        return
    # a spec that parses is canonical after one round and builds a model: its effect
    # terms in order, then its noise component
    canonical = format_spec(terms)
    assert format_spec(parse_spec(canonical)) == canonical
    noise = [t for t in terms if isinstance(t, AbstractNoise)]
    model = ErrorModel(tuple(t for t in terms if t not in noise), noise[0] if noise else None)
    assert model.spec == format_spec([t for t in terms if t not in noise] + noise)
    assert ErrorModel.from_spec(canonical) == model


@FUZZ
@given(st.one_of(st.none(), st.integers(), st.floats(), st.binary(max_size=10),
                 st.lists(st.text(max_size=5), max_size=3), st.dictionaries(st.text(), st.text())))
def test_spec_parser_rejects_non_text(value):
    with pytest.raises(SpecError):
        parse_spec(value)


def test_spec_limits():
    with pytest.raises(SpecError, match="longer than"):
        parse_spec("+".join(["bias_poly(1)"] * 200))
    with pytest.raises(SpecError, match="maximum"):
        parse_spec("bias_poly(" + "9" * 40 + ")")
    with pytest.raises(SpecError):
        parse_spec("bias_poly(２)")  # full-width digit: not an order


# --------------------------------------------------------------------------- calibration files

SPEC = "bias_poly(1)+thermal_lag"


def valid_calibration() -> dict:
    model = ErrorModel.from_spec(SPEC)
    p, q = model.n_params, model.n_nonlinear
    devs = []
    for i, status in enumerate(["ok", "not_converged"]):
        beta = (np.arange(3 * p).reshape(3, p) * 1e-3 + i).tolist()
        theta = [3.0 + i] * q
        devs.append(DeviceCalibration(
            device=f"unit-{i}", status=status, beta=beta, theta=theta, temp_centre=25.0,
            temp_scale=30.0, temp_range=[-5.0, 55.0], status_detail=status,
            quality={"rms": 1e-4, "heldout_rms": 1.1e-4, "noise_floor": 9e-5, "n_samples": 100,
                     "steps": 7},
            params={"x": {"bias_poly(1).c0": 0.1}, "shared": {"thermal_lag.tau": 20.0}}))
    cal = Calibration(model=SPEC, devices=devs, created="2024-01-01T00:00:00+00:00",
                      diffgyro_version="0.1.0", input_hash="sha256:00",
                      units=calibration.units_of(model))
    return json.loads(json.dumps(cal.to_json(), allow_nan=False))


def check_loaded(cal: Calibration) -> None:
    """A calibration that loads is usable and can be saved and loaded again unchanged."""
    model = cal.error_model
    p, q = model.n_params, model.n_nonlinear
    text = json.dumps(cal.to_json(), allow_nan=False)
    again = calibration.from_json(json.loads(text))
    assert json.dumps(again.to_json(), allow_nan=False) == text
    assert cal.devices and len({d.device for d in cal.devices}) == len(cal.devices)
    for d in cal.devices:
        assert np.asarray(d.beta, float).shape == (3, p)
        assert np.asarray(d.theta, float).shape == (q,)
        assert math.isfinite(d.temp_centre) and math.isfinite(d.temp_scale) and d.temp_scale > 0
        if d.status == "ok":
            assert np.all(np.isfinite(d.beta)) and np.all(np.isfinite(d.theta))
            assert np.all(np.isfinite(np.exp(np.asarray(d.theta, float))))
        if d.temp_range is not None:
            assert all(math.isfinite(x) for x in d.temp_range)


def load_obj(obj) -> None:
    try:
        cal = calibration.from_json(obj)
    except (SpecError, DataError):
        return
    check_loaded(cal)


def test_valid_file_round_trips(tmp_path):
    obj = valid_calibration()
    cal = calibration.from_json(obj)
    check_loaded(cal)
    path = tmp_path / "cal.json"
    calibration.save(cal, path)
    assert calibration.load(path).to_json() == cal.to_json()


json_scalar = st.one_of(
    st.none(), st.booleans(), st.text(max_size=8),
    st.integers(min_value=-(10**400), max_value=10**400),
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([0, -1, 1e308, -1e308, 5e-324, 10**309, 2**63, "ok", "", "\x00", "NaN"]))
json_value = st.recursive(
    json_scalar,
    lambda inner: st.one_of(st.lists(inner, max_size=4),
                            st.dictionaries(st.text(max_size=6), inner, max_size=4)),
    max_leaves=12)


def _paths(obj, prefix=()):
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


def _get(obj, path):
    for k in path:
        obj = obj[k]
    return obj


def _set(obj, path, value):
    if not path:
        return value
    cur = obj
    for k in path[:-1]:
        cur = cur[k]
    cur[path[-1]] = value
    return obj


def _delete(obj, path):
    if not path:
        return obj
    cur = obj
    for k in path[:-1]:
        cur = cur[k]
    del cur[path[-1]]
    return obj


BASE = valid_calibration()
BASE_PATHS = list(_paths(BASE))


@FUZZ
@given(st.lists(st.tuples(st.sampled_from(BASE_PATHS), st.sampled_from(["set", "delete", "add"]),
                          json_value, st.text(max_size=8)), min_size=1, max_size=3))
def test_tampered_calibration_is_rejected_or_valid(edits):
    obj = copy.deepcopy(BASE)
    for path, how, value, key in edits:
        try:
            if how == "set":
                obj = _set(obj, path, value)
            elif how == "delete":
                obj = _delete(obj, path)
            else:
                target = obj
                for k in path:
                    target = target[k]
                if isinstance(target, dict):
                    target[key] = value
                elif isinstance(target, list):
                    target.append(value)
        except (KeyError, IndexError, TypeError):
            continue  # an earlier edit removed or replaced this path
    load_obj(obj)


NASTY = st.sampled_from([10**400, -(10**309), 2**1024, 1e308, -1e308, 1e999, -1e999,
                         float("nan"), 0, -0.0, 5e-324, 1e-320, 10**20, True, None, "1", [1],
                         {"a": 1}])


@FUZZ
@given(st.data())
def test_nasty_number_at_any_numeric_field_is_rejected_or_valid(data):
    paths = [p for p in BASE_PATHS if isinstance(_get(BASE, p), (int, float))]
    obj = copy.deepcopy(BASE)
    for _ in range(data.draw(st.integers(1, 3))):
        obj = _set(obj, data.draw(st.sampled_from(paths)), data.draw(NASTY))
    load_obj(obj)


@FUZZ
@given(json_value)
def test_any_json_value_is_rejected_or_valid(value):
    load_obj(value)


@FUZZ
@given(st.one_of(st.binary(max_size=300), st.text(max_size=300).map(str.encode),
                 st.sampled_from([b"", b"{", b"[]", b"null", b"NaN", b"\xef\xbb\xbf{}",
                                  b"[" * 100000 + b"]" * 100000, b"1" * 5000,
                                  b'{"format": "diffgyro-calibration"}'])))
def test_any_bytes_in_a_file_are_rejected_or_valid(tmp_path_factory, data):
    path = tmp_path_factory.mktemp("raw") / "cal.json"
    path.write_bytes(data)
    try:
        cal = calibration.load(path)
    except (SpecError, DataError) as err:
        assert str(path) in str(err)
        return
    check_loaded(cal)


@pytest.mark.parametrize("text, match", [
    # duplicate keys: two parsers could read two different files
    ('{"format": "diffgyro-calibration", "format": "x"}', "twice"),
    # the JSON extensions Python accepts by default
    ('{"a": NaN}', "not valid JSON"),
    ('{"a": Infinity}', "not valid JSON"),
    ('{"a": -Infinity}', "not valid JSON"),
])
def test_loader_refuses_json_tricks(tmp_path, text, match):
    path = tmp_path / "cal.json"
    path.write_text(text)
    with pytest.raises(SpecError, match=match):
        calibration.load(path)


P = len(BASE["devices"][0]["beta"][0])


@pytest.mark.parametrize("edit, match", [
    (lambda o: o["devices"][0].__setitem__("beta", [[1e999] + [0] * (P - 1), [0] * P, [0] * P]),
     "non-finite|numbers"),
    (lambda o: o["devices"][0].__setitem__("theta", [1e6]), "time constant"),
    (lambda o: o["devices"][0].__setitem__("temp_range", [-1e999, 1e999]), "temp_range"),
    (lambda o: o["devices"][0].__setitem__("temp_centre", 10**400), "temp_centre|number"),
    (lambda o: o["devices"][0].__setitem__("beta", [[0] * P, [0, 0], [0] * P]), "beta"),
    (lambda o: o["devices"][0].__setitem__("device", ""), "device"),
    (lambda o: o["devices"][0].__setitem__("device", "a\x1b[31mb"), "device"),
    (lambda o: o.__setitem__("dtemp_window", 1e300), "dtemp_window"),
    (lambda o: o.__setitem__("extra", 1), "unknown key"),
    (lambda o: o["devices"][0].__setitem__("code", "__import__('os')"), "unknown key"),
    (lambda o: o["devices"][0]["quality"].__setitem__("rms", {"a": [1]}), "quality"),
    (lambda o: o["devices"][0].__setitem__("params", {"x": [[[[1]]]]}), "params"),
    (lambda o: o["devices"][0].__setitem__("status_detail", ["x"]), "status_detail"),
    (lambda o: o.__setitem__("created", {"a": 1}), "created"),
    (lambda o: o.__setitem__("units", {"a": 1}), "units"),
    (lambda o: o.__setitem__("model", "bias_poly(1)+__import__"), "cannot read|unknown"),
])
def test_tampered_fields_get_clear_errors(edit, match):
    obj = copy.deepcopy(BASE)
    edit(obj)
    with pytest.raises(SpecError, match=match):
        calibration.from_json(obj)


def test_deeply_nested_python_object_is_rejected_without_recursion_error():
    obj = copy.deepcopy(BASE)
    deep: list = []
    for _ in range(100000):
        deep = [deep]
    obj["devices"][0]["quality"]["rms"] = deep
    with pytest.raises(SpecError):
        calibration.from_json(obj)


# --------------------------------------------------------------------------- recordings


def strict_json(text: str):
    """json.loads refusing NaN/Infinity (Python's default extensions)."""
    def refuse(token):
        raise ValueError(f"non-standard JSON token {token}")
    return json.loads(text, parse_constant=refuse)


def thermal_rows(device: str, n: int = 240, temp_span: float = 20.0, seed: int = 0) -> list[str]:
    """A device with a known quadratic bias in temperature (rad/s) and white noise."""
    rng = np.random.default_rng(seed)
    t = np.arange(n, dtype=float)
    temp = 25.0 + temp_span * np.sin(np.pi * t / n)
    ts = temp - 25.0
    bias = np.array([1e-3, -2e-3, 5e-4])[None] + np.outer(ts, [2e-5, 1e-5, -3e-5]) \
        + np.outer(ts**2, [1e-6, 0.0, 2e-7])
    gyro = bias + rng.normal(scale=1e-4, size=(n, 3))
    return [f"{device},{t[i]:g},{gyro[i, 0]:.17g},{gyro[i, 1]:.17g},{gyro[i, 2]:.17g},{temp[i]:.17g}"
            for i in range(n)]


HEADER = "device,t,gx,gy,gz,temp"


def run_cli(argv, capsys):
    from diffgyro.cli import main

    capsys.readouterr()
    code = main(argv)
    out = capsys.readouterr()
    return code, out.out, out.err


def test_constant_temperature_device_gets_a_reason_and_the_batch_its_fits(tmp_path, capsys):
    """Issue 22: a constant temperature fitted with bias_poly(2) gave NaN in --json and a
    traceback. Now: valid JSON, exit 0, the device says why, its neighbour is fitted."""
    path = tmp_path / "two.csv"
    path.write_text("\n".join([HEADER, *thermal_rows("steady", temp_span=0.0),
                               *thermal_rows("swept", seed=1)]) + "\n")
    cal = tmp_path / "cal.json"
    code, out, err = run_cli(["fit", str(path), "--model", "bias_poly(2)", "--json",
                              "--out", str(cal)], capsys)
    assert code == 0, err
    recs = {r["device"]: r for r in strict_json(out)["devices"]}
    steady, swept = recs["steady"], recs["swept"]
    assert steady["status"] == "insufficient_range"
    assert "temperature constant at 25.0 °C" in steady["status_detail"]
    assert "bias_poly(2) needs a temperature span" in steady["status_detail"]
    assert swept["status"] == "ok", swept["status_detail"]
    doc = strict_json(cal.read_text())
    assert [d["status"] for d in doc["devices"]] == ["insufficient_range", "ok"]
    dc = doc["devices"][1]["temp_centre"] - 25.0  # c0 is the bias at the centring point
    truth = 1e-3 + 2e-5 * dc + 1e-6 * dc**2
    assert abs(swept["params"]["x"]["bias_poly(2).c0"] - truth) < 3e-5


def test_impossible_gyro_value_is_refused_naming_the_row(tmp_path, capsys):
    """Issue 22: one gyro sample of 1e308 made the device 'failed' with no reason."""
    rows = thermal_rows("u1")
    rows[3] = rows[3].replace(rows[3].split(",")[2], "1e308", 1)  # row 4, column gx
    path = tmp_path / "big.csv"
    path.write_text("\n".join([HEADER, *rows]) + "\n")
    code, out, err = run_cli(["fit", str(path), "--model", "bias_poly(2)", "--json"], capsys)
    assert code == 2
    doc = strict_json(out)  # under --json the error is an object on stdout too
    assert (doc["file"], doc["device"], doc["column"], doc["row"]) == (str(path), "u1", "gx", 4)
    line, = err.strip().splitlines()
    assert str(path) in line and "device u1" in line and "column gx" in line and "row 4" in line
    assert "1e+308 rad/s is not physical" in line
    code, out, err = run_cli(["fit", str(path), "--model", "bias_poly(2)", "--json",
                              "--drop-invalid"], capsys)
    assert code == 0
    assert "dropped 1 row" in err and "row 4" in err
    rec, = strict_json(out)["devices"]
    assert rec["status"] == "ok" and rec["n_samples"] == len(rows) - 1


@pytest.mark.parametrize("column, value, unit_opts, words", [
    ("temp", "-273.2", [], "below absolute zero"),
    ("temp", "501", [], "above 500 °C"),
    ("temp", "-1", ["--temp-unit", "K"], "-274.15 °C (read -1) is not physical (below absolute"),
    ("gz", "-1.1e8", [], "beyond ±1e+08 rad/s"),
    ("gz", "6e9", ["--gyro-unit", "deg/s"], "gyro value 1.0472e+08 rad/s (read 6e+09) is not"),
])
def test_physical_limits_at_load(tmp_path, capsys, column, value, unit_opts, words):
    from diffgyro.io import LIMITS

    rows = thermal_rows("u1", n=40)
    k = HEADER.split(",").index(column)
    cells = rows[6].split(",")
    cells[k] = value
    rows[6] = ",".join(cells)
    path = tmp_path / "x.csv"
    path.write_text("\n".join([HEADER, *rows]) + "\n")
    code, _, err = run_cli(["fit", str(path), "--model", "bias_poly(1)", *unit_opts], capsys)
    assert code == 2, err
    line, = err.strip().splitlines()
    assert f"column {column}" in line and "row 7" in line and words in line, line
    assert LIMITS["gyro"] == (-1e8, 1e8) and LIMITS["temp"] == (-273.15, 500.0)


def test_accelerometer_limit_and_the_limits_in_the_api(tmp_path):
    from diffgyro.errors import DataError
    from diffgyro.io import load

    path = tmp_path / "a.csv"
    path.write_text("t,gx,gy,gz,ax,ay,az\n0,0,0,0,0,0,9.8\n1,0,0,0,2e8,0,9.8\n2,0,0,0,0,0,9.8\n")
    with pytest.raises(DataError, match=r"column ax, row 2: accelerometer value 2e\+08 m/s²"):
        load(path)
    rec, = load(path, drop_invalid=True)
    assert rec.n == 2 and rec.accel[:, 0].tolist() == [0.0, 0.0]
    # raw 24-bit ADC counts (the recipes calibrate counts) are not refused
    path.write_text("t,gx,gy,gz,ax,ay,az\n0,8388607,-8388608,0,8388607,0,-8388608\n"
                    "1,0,0,0,0,0,9.8\n")
    rec, = load(path)
    assert rec.gyro[0, :2].tolist() == [8388607.0, -8388608.0]


def test_every_json_command_says_why_a_device_is_not_ok(tmp_path, capsys):
    """The constant-temperature device through diagnose, recipe, allan and compensate:
    strict JSON (exit 0) with the reason beside each missing number, or one line naming
    the file and the reason (exit 2)."""
    path = tmp_path / "two.csv"
    path.write_text("\n".join([HEADER, *thermal_rows("steady", temp_span=0.0),
                               *thermal_rows("swept", seed=1)]) + "\n")
    reason = "temperature constant at 25.0 °C: bias_poly(2) needs a temperature span"
    code, out, err = run_cli(["diagnose", str(path), "--model", "bias_poly(2)", "--json",
                              "--candidates", "bias_poly"], capsys)
    assert code == 0, err
    steady = strict_json(out)["devices"][0]
    # the least-squares residual of the data stands (rank-deficient: minimum norm); what
    # the data cannot give, the held-out error, is missing beside its reason
    assert steady["heldout_rms"] is None and steady["status"] == "insufficient_range"
    assert steady["rms"] is not None and steady["rms"] > 0
    assert reason in steady["status_detail"] and reason in steady["explanation"]
    assert steady["verdict"] == "not_judged" and reason in steady["verdict_detail"]

    code, out, err = run_cli(["recipe", "binned-thermal", str(path), "--json",
                              "--bin-width", "2.5"], capsys)
    assert code == 0, err
    steady, swept = strict_json(out)["devices"]
    assert steady == {"device": "steady", "status": "failed", "status_detail":
                      "failed: only 1 temperature bins of 2.5 °C hold 10 samples or more"}
    assert swept["status"] == "ok" and len(swept["bin_temp"]) == 8
    code, out, err = run_cli(["recipe", "binned-thermal", str(path), "--bin-width", "2.5"], capsys)
    assert code == 0 and f"file {path}, device steady: only 1 temperature bins" in err

    code, out, err = run_cli(["allan", str(path), "--json"], capsys)
    assert code == 0, err
    for dev in strict_json(out)["devices"]:
        for ax in dev["axes"].values():
            nulls = {k for k in ("arw", "bias_instability", "rrw") if ax[k] is None}
            assert nulls == set(ax.get("missing", {})), ax  # a reason for each null, no other
            if dev["device"] == "steady":  # white noise: the -1/2 line only
                assert ax["arw"] is not None and "rate-random-walk" in ax["missing"]["rrw"]

    cal = tmp_path / "cal.json"
    assert run_cli(["fit", str(path), "--model", "bias_poly(2)", "--out", str(cal)],
                   capsys)[0] == 0
    code, out, err = run_cli(["compensate", str(path), "--cal", str(cal),
                              "--out", str(tmp_path / "c.csv")], capsys)
    line, = err.strip().splitlines()
    assert code == 2 and f"file {cal}, device steady" in line and reason in line
