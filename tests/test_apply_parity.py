"""apply.py (numpy only, the reference users port to firmware) against calibration.compensate,
for every registered effect alone (read from the registry: tests/effect_cases.py) and the
built-in ones all together, on one recording that exercises each term:
rotation on every axis (scale, asymmetry, nonlinearity, misalignment), a changing specific
force (g_sens), temperature ramps up and down with soaks (gradient, hysteresis, thermal lag),
temperature and the extra column beyond their calibrated ranges (clamping), an external
temperature (temp_diff) and a warm-up from the first sample."""

from __future__ import annotations

import numpy as np
import pytest
from effect_cases import BUILT_IN, cases
from recordings import turning_chamber_run

from diffgyro import apply as A
from diffgyro import calibration as C
from diffgyro.data import Recording
from diffgyro.effects import registry
from diffgyro.model import ErrorModel

#: Every registered term, read from the registry (effect_cases.py): its spec alone, its
#: time constants, its numpy form. A term registered anywhere is covered here unedited.
CASES = cases()
ALL = ("bias_poly(2)+scale_poly(1)+scale_asym+scale_nonlin+misalignment+g_sens+gradient+"
       "temp_diff+hysteresis+thermal_lag(2)+warmup+aux(vdd,2)+term(temp*az*lag(vdd))+term(w^2*ax)")


def test_every_built_in_effect_has_a_hand_tuned_case():
    built_in = {k for k, cls in registry().items() if cls.__module__.startswith("diffgyro.effects.")}
    assert built_in == set(BUILT_IN)
    assert {t.name for t in ErrorModel.from_spec(ALL).terms} == built_in - {"random_walk"}


@pytest.fixture(scope="module")
def recording() -> Recording:
    """50 min (see :func:`turning_chamber_run`)."""
    return turning_chamber_run(3000, [0, 300, 1200, 1500, 2700, 3000], seed=11)


def _calibration(spec: str, seed: int) -> dict:
    model = ErrorModel.from_spec(spec)
    rng = np.random.default_rng(seed)
    tau = {c.name: c.theta for c in CASES}
    theta = [tau[t.name][k] for t in model.terms for k in range(t.n_nonlinear)]
    dev = {"device": "imu0", "status": "ok",
           "beta": (rng.normal(size=(3, model.n_params)) * 0.02).tolist(), "theta": theta,
           "temp_centre": 28.0, "temp_scale": 16.0, "temp_range": [14.0, 45.0]}
    if "vdd" in spec:  # narrower than the data's 3.1 .. 3.5 V: clamped at both ends
        dev["aux"] = {"vdd": {"centre": 3.3, "scale": 0.15, "range": [3.15, 3.45]}}
    return {"format": "diffgyro-calibration", "format_version": 1, "model": spec,
            "dtemp_window": 60.0, "devices": [dev]}


def _both(spec: str, rec: Recording, seed: int, terms=None):
    doc = _calibration(spec, seed)
    cal = C.from_json(doc)
    if "temp" in cal.error_model.requires():  # beyond the calibrated range on both sides
        with pytest.warns(UserWarning, match="clamped"):
            out, clamped = C.compensate(cal, rec)
        assert clamped["imu0"] > 0
    else:
        out, _ = C.compensate(cal, rec)
    return np.asarray(out.gyro[0, : rec.n]), _apply(doc, rec, terms)


def _apply(doc: dict, rec: Recording, terms=None) -> np.ndarray:
    return A.compensate(doc, "imu0", rec.t, rec.gyro, temp=rec.temp, temp_ext=rec.temp_ext,
                        accel=rec.accel, aux=rec.aux, terms=terms)


@pytest.mark.parametrize("case", CASES, ids=[c.name if c.has_numpy_form else
                                             f"{c.name}-no-numpy-form" for c in CASES])
def test_apply_equals_compensate_for_each_effect(recording, case):
    """apply.py agrees with the fit's compensation on every term it has a numpy form of
    (its own code, or the ``numpy_columns`` a term's class declares); a term without one
    is refused by name, never silently left out of the firmware's formula."""
    if not case.has_numpy_form:
        with pytest.raises(ValueError, match=f"not {case.name!r}"):
            _apply(_calibration(case.alone, seed=len(case.name)), recording)
        return
    ours, ref = _both(case.alone, recording, seed=len(case.name), terms=case.apply_terms)
    # each term really acts (a term both sides ignored would agree too)
    assert np.abs(ours - recording.gyro).max() > 1e-4
    np.testing.assert_allclose(ref, ours, rtol=0, atol=1e-10)


def test_apply_equals_compensate_for_all_effects_together(recording):
    ours, ref = _both(ALL, recording, seed=5)
    np.testing.assert_allclose(ref, ours, rtol=0, atol=1e-10)
