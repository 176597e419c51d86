"""The term grammar (``term(EXPR)``): spec text, bad specs, apply.py parity, fits, the
calibration file round trip, composition with a registered term, sensitivity, export."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import registered
from grammar_catalogue import CASES, SIGMA, make
from recordings import turning_chamber_run

import diffgyro
from diffgyro import apply as A
from diffgyro import calibration as C
from diffgyro.data import Batch, Recording
from diffgyro.effects import AbstractEffect, Term, parse_spec
from diffgyro.errors import DataError, SpecError
from diffgyro.fit import fit
from diffgyro.internal import per_axis
from diffgyro.model import ErrorModel


@pytest.fixture(scope="module", autouse=True)
def _x64():
    diffgyro.enable_x64()


@pytest.mark.parametrize("text, canonical", [
    ("term(az*temp)", "term(temp*az)"),
    ("term( temp * temp * az )", "term(temp^2*az)"),
    ("term(lag(heater))", "term(lag(heater))"),
    ("term(heater*lag(heater)^2)", "term(heater*lag(heater)^2)"),
    ("term(w^2*temp)", "term(temp*w^2)"),
    ("term(vdd*rx*temp_ext)", "term(temp_ext*rx*vdd)"),
])
def test_spec_text_is_canonical_and_round_trips(text, canonical):
    (t,) = parse_spec(text)
    assert t.spec == canonical
    assert parse_spec(t.spec)[0] == t  # the stored text reads back as the same term


def test_requirements_and_rate_dependence():
    t1, t2, t3 = parse_spec("term(temp*az)+term(lag(heater)*temp_ext)+term(rx*w)")
    assert t1.requires() == {"temp", "accel"} and not t1.rate_dependent
    assert t2.requires() == {"temp", "temp_ext", "aux:heater"} and t2.nonlinear_names() == ("tau",)
    assert t3.requires() == {"rate"} and t3.rate_dependent


@pytest.mark.parametrize("spec, where", [
    ("term(temp*^az)", "character 6"),
    ("term(temp**az)", "character 6"),
    ("term(temp^0)", "character 6"),
    ("term(temp^12)", "character 6"),
    ("term(lag(rx))", "character 5"),
    ("term(lag(temp)*lag(vdd))", "one lagged factor"),
    ("term(heating^2)", "even power"),
    ("term(temp az)", "character 6"),
    ("term(temp*az)+term(az*temp)", "more than once"),
    ("term", "needs a product of signals"),
    ("term(temp$)", "character 5"),
])
def test_bad_spec_is_one_line_naming_the_position(spec, where):
    with pytest.raises(SpecError) as err:
        parse_spec(spec)
    assert where in str(err.value) and "\n" not in str(err.value)


# ----------------------------------------------------------------------------- apply.py parity


@pytest.fixture(scope="module")
def recording() -> Recording:
    """40 min at 1 Hz: temperature up and down, turning on all axes, tilting, an extra column."""
    return turning_chamber_run(2400, [0, 300, 1000, 1300, 2100, 2400], seed=3)


def _document(spec: str, seed: int) -> dict:
    model = ErrorModel.from_spec(spec)
    rng = np.random.default_rng(seed)
    dev = {"device": "imu0", "status": "ok",
           "beta": (rng.normal(size=(3, model.n_params)) * 0.02).tolist(),
           "theta": [math.log(250.0)] * model.n_nonlinear,
           "temp_centre": 28.0, "temp_scale": 16.0, "temp_range": [14.0, 45.0]}
    if "vdd" in spec:
        dev["aux"] = {"vdd": {"centre": 3.3, "scale": 0.15, "range": [3.15, 3.45]}}
    return {"format": "diffgyro-calibration", "format_version": 1, "model": spec,
            "dtemp_window": 60.0, "devices": [dev]}


@pytest.mark.parametrize("spec, rtol", [
    ("bias_poly(1)+term(temp*az)", 0.0),
    ("bias_poly(0)+term(lag(vdd))+term(temp_ext*heating)", 0.0),
    # dT/dt: JAX's blocked prefix sums and numpy's cumsum round differently (a few 1e-12
    # relative at the ends, as for the built-in gradient term)
    ("bias_poly(0)+term(temp_ext*dtemp)", 1e-11),
    ("term(heating*ay)+term(lag(temp)^2*ax)", 0.0),
    ("scale_poly(0)+term(temp*w^2)+term(rx*ry)", 0.0),
])
def test_apply_equals_compensate(recording, spec, rtol):
    doc = _document(spec, seed=len(spec))
    cal = C.from_json(doc)
    with pytest.warns(UserWarning, match="clamped"):
        out, _ = C.compensate(cal, recording)
    ours = np.asarray(out.gyro[0, :recording.n])
    ref = A.compensate(doc, "imu0", recording.t, recording.gyro, temp=recording.temp,
                       temp_ext=recording.temp_ext, accel=recording.accel, aux=recording.aux)
    assert np.abs(ours - recording.gyro).max() > 1e-4  # the terms act
    np.testing.assert_allclose(ref, ours, rtol=rtol, atol=1e-12)


# ----------------------------------------------------------------------------- fit and files


@pytest.fixture(scope="module")
def heater():
    """The heater case: fitted with its true model, and the calibration file."""
    rec, _ = make("heater", 0)
    batch = Batch.from_recordings([rec])
    res = fit(CASES["heater"].base + "+" + CASES["heater"].term, batch)
    return batch, res


def test_fit_learns_the_lag_and_the_file_round_trips(heater, tmp_path):
    from grammar_catalogue import HEATER_TAU

    batch, res = heater
    assert float(res.heldout_rms[0]) < 1.05 * SIGMA
    tau = float(np.exp(np.asarray(res.params.theta)[0, 0]))
    assert abs(tau / HEATER_TAU - 1) < 0.15
    cal = C.from_fit(res, batch)
    path = tmp_path / "cal.json"
    C.save(cal, path)
    obj = json.loads(path.read_text())
    assert obj["model"] == "bias_poly(1)+term(lag(heater))"
    assert set(obj["devices"][0]["aux"]) == {"heater"}
    back = C.load(path)
    assert back.model == cal.model
    np.testing.assert_array_equal(back.device("unit").beta, cal.device("unit").beta)
    C.save(back, tmp_path / "again.json")
    assert (tmp_path / "again.json").read_text() == path.read_text()
    out, _ = C.compensate(back, batch)
    rec = batch.recording(0)
    ref = A.compensate(obj, "unit", rec.t, rec.gyro, temp=rec.temp, aux=rec.aux)
    np.testing.assert_allclose(np.asarray(out.gyro[0, :rec.n]), ref, rtol=0, atol=1e-12)


def test_sensitivity_and_export_see_the_grammar_term(heater):
    from diffgyro.export import render
    from diffgyro.sensitivity import hac_covariance

    batch, res = heater
    cov = np.asarray(hac_covariance(res, batch)["cov"])
    assert cov.shape[-1] == 3 * res.model.n_params + res.model.n_nonlinear  # τ included
    assert np.all(np.isfinite(cov))
    cal = C.from_fit(res, batch)
    for fmt in ("c-header", "px4", "ardupilot"):
        with pytest.raises(DataError, match=r"term\(lag\(heater\)\) cannot be written as "):
            render(cal, fmt, device_ids=[1])


class SupplyStep(AbstractEffect):
    """A test-only user term: bias ∝ whether the extra column is above its centre."""

    name = "supply_step"
    description = "bias step when the supply is above its centre (test)"
    needs = frozenset({"aux:vdd"})

    def param_names(self):
        return ("s",)

    def columns(self, sig, theta):
        return per_axis((sig.aux["vdd"] > 0).astype(sig.gyro.dtype))


@pytest.fixture
def supply_step_term():
    """The test's own term in the registry while it runs (registered at import, it would be
    in every test file's registry read after this one)."""
    with registered(SupplyStep):
        yield


def test_registered_term_composes_with_grammar_terms(supply_step_term):
    rec, _ = make("supply", 0)
    spec = "bias_poly(1)+aux(vdd)+supply_step+term(temp*vdd)"
    res = fit(spec, Batch.from_recordings([rec]))
    assert res.model.spec == spec and isinstance(res.model.terms[-1], Term)
    assert float(res.heldout_rms[0]) < 1.05 * SIGMA


def test_report_draws_the_residual_against_the_product(heater):
    from diffgyro.report import residual_drop_figure

    batch, res = heater
    n = int(batch.n_valid[0])
    base = fit(CASES["heater"].base, batch)
    e0 = np.asarray(base.residuals(batch))[0, :n]
    e1 = np.asarray(res.residuals(batch))[0, :n]
    fig = residual_drop_figure(base.model, res.model.spec, batch.recording(0), e0, e1)
    assert fig.axes[1].get_xlabel() == "lag(heater)"


def test_the_effects_command_lists_the_grammar(capsys):
    from diffgyro.cli import main

    assert main(["effects"]) == 0
    assert "term(EXPR)" in capsys.readouterr().out
