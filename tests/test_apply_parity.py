"""apply.py (numpy only, the reference users port to firmware) against calibration.compensate,
for every built-in effect alone and all together, on one recording that exercises each term:
rotation on every axis (scale, asymmetry, nonlinearity, misalignment), a changing specific
force (g_sens), temperature ramps up and down with soaks (gradient, hysteresis, thermal lag),
temperature and the extra column beyond their calibrated ranges (clamping), an external
temperature (temp_diff) and a warm-up from the first sample."""

from __future__ import annotations

import math

import numpy as np
import pytest
from recordings import turning_chamber_run

from diffgyro import apply as A
from diffgyro import calibration as C
from diffgyro.data import Recording
from diffgyro.effects import registry
from diffgyro.model import ErrorModel

#: The spec each built-in effect is tried with (orders above one where the effect has them).
ALONE = {
    "aux": "aux(vdd,2)", "bias_poly": "bias_poly(3)", "g_sens": "g_sens",
    "gradient": "gradient", "hysteresis": "hysteresis", "misalignment": "misalignment",
    "random_walk": "bias_poly(1)+random_walk", "scale_asym": "scale_asym",
    "scale_nonlin": "scale_nonlin", "scale_poly": "scale_poly(2)", "temp_diff": "temp_diff",
    "thermal_lag": "thermal_lag(2)", "warmup": "warmup", "term": "term(temp*az*lag(vdd))",
}
ALL = ("bias_poly(2)+scale_poly(1)+scale_asym+scale_nonlin+misalignment+g_sens+gradient+"
       "temp_diff+hysteresis+thermal_lag(2)+warmup+aux(vdd,2)+term(temp*az*lag(vdd))+term(w^2*ax)")
#: log τ of the time constants in spec order (thermal lag 300 s, warm-up 600 s)
THETA = {"thermal_lag": math.log(300.0), "warmup": math.log(600.0), "term": math.log(200.0)}


def test_every_built_in_effect_is_covered():
    built_in = {k for k, cls in registry().items() if cls.__module__.startswith("diffgyro.effects.")}
    assert built_in == set(ALONE)


@pytest.fixture(scope="module")
def recording() -> Recording:
    """50 min (see :func:`turning_chamber_run`)."""
    return turning_chamber_run(3000, [0, 300, 1200, 1500, 2700, 3000], seed=11)


def _calibration(spec: str, seed: int) -> dict:
    model = ErrorModel.from_spec(spec)
    rng = np.random.default_rng(seed)
    theta = [THETA[t.name] for t in model.terms for _ in range(t.n_nonlinear)]
    dev = {"device": "imu0", "status": "ok",
           "beta": (rng.normal(size=(3, model.n_params)) * 0.02).tolist(), "theta": theta,
           "temp_centre": 28.0, "temp_scale": 16.0, "temp_range": [14.0, 45.0]}
    if "vdd" in spec:  # narrower than the data's 3.1 .. 3.5 V: clamped at both ends
        dev["aux"] = {"vdd": {"centre": 3.3, "scale": 0.15, "range": [3.15, 3.45]}}
    return {"format": "diffgyro-calibration", "format_version": 1, "model": spec,
            "dtemp_window": 60.0, "devices": [dev]}


def _both(spec: str, rec: Recording, seed: int):
    doc = _calibration(spec, seed)
    cal = C.from_json(doc)
    if "temp" in cal.error_model.requires():  # beyond the calibrated range on both sides
        with pytest.warns(UserWarning, match="clamped"):
            out, clamped = C.compensate(cal, rec)
        assert clamped["imu0"] > 0
    else:
        out, _ = C.compensate(cal, rec)
    ours = np.asarray(out.gyro[0, : rec.n])
    ref = A.compensate(doc, "imu0", rec.t, rec.gyro, temp=rec.temp, temp_ext=rec.temp_ext,
                       accel=rec.accel, aux=rec.aux)
    return ours, ref


@pytest.mark.parametrize("name", sorted(ALONE))
def test_apply_equals_compensate_for_each_effect(recording, name):
    ours, ref = _both(ALONE[name], recording, seed=len(name))
    # each term really acts (a term both sides ignored would agree too)
    assert np.abs(ours - recording.gyro).max() > 1e-4
    np.testing.assert_allclose(ref, ours, rtol=0, atol=1e-10)


def test_apply_equals_compensate_for_all_effects_together(recording):
    ours, ref = _both(ALL, recording, seed=5)
    np.testing.assert_allclose(ref, ours, rtol=0, atol=1e-10)
