"""``calibration.compensate(..., engine="numpy")``, what ``diffgyro compensate`` runs without
JAX (:func:`diffgyro.apply.compensate` device by device), against the error model in JAX
(the default): the same corrected rates to 1e-10 rad/s on every built-in term at once,
the same clamped counts and warning, the same padding and fields, on a batch of two
devices of different lengths."""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest
from recordings import turning_chamber_run

from diffgyro import calibration as C
from diffgyro.data import Batch
from diffgyro.errors import DataError
from diffgyro.model import ErrorModel

SPEC = ("bias_poly(2)+scale_poly(1)+scale_asym+scale_nonlin+misalignment+g_sens+gradient+"
        "temp_diff+hysteresis+thermal_lag(2)+warmup+aux(vdd,2)+term(temp*az*lag(vdd))")
THETA = {"thermal_lag": math.log(300.0), "warmup": math.log(600.0), "term": math.log(200.0)}


def _calibration(spec: str, devices: list[str]) -> C.Calibration:
    model = ErrorModel.from_spec(spec)
    rng = np.random.default_rng(5)
    theta = [THETA[t.name] for t in model.terms for _ in range(t.n_nonlinear)]
    devs = [{"device": d, "status": "ok", "beta": (rng.normal(size=(3, model.n_params)) * 0.02
                                                   ).tolist(), "theta": theta,
             "temp_centre": 28.0 + k, "temp_scale": 16.0, "temp_range": [14.0 + k, 45.0],
             "aux": {c: {"centre": 3.3, "scale": 0.15, "range": [3.15, 3.45]}
                     for c in ("vdd", "vbat") if f"aux:{c}" in model.requires()}}
            for k, d in enumerate(devices)]
    return C.from_json({"format": "diffgyro-calibration", "format_version": 1, "model": spec,
                        "dtemp_window": 60.0, "devices": devs})


@pytest.fixture(scope="module")
def batch() -> Batch:
    """Two devices, 3000 and 2400 s at 1 Hz (the second padded), turning in a chamber."""
    a = turning_chamber_run(3000, [0, 300, 1200, 1500, 2700, 3000], seed=3)
    b = turning_chamber_run(2400, [0, 200, 900, 1200, 2100, 2400], seed=4)
    return Batch.from_recordings([a, dataclasses.replace(b, device="imu1")])


def _run(cal, batch, engine):
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        out, clamped = C.compensate(cal, batch, engine=engine)
    return out, clamped, [str(w.message) for w in seen]


def test_numpy_engine_equals_the_model(batch):
    cal = _calibration(SPEC, list(batch.devices))
    ref, ref_clamped, ref_warned = _run(cal, batch, "jax")
    out, clamped, warned = _run(cal, batch, "numpy")
    assert clamped == ref_clamped and set(clamped) == {"imu0", "imu1"}
    assert warned == ref_warned and len(warned) == 1
    assert np.abs(np.asarray(ref.gyro) - batch.gyro).max() > 1e-3  # the terms act
    np.testing.assert_allclose(out.gyro, np.asarray(ref.gyro), rtol=0, atol=1e-10)
    assert not np.any(out.gyro[1, batch.n_valid[1]:])  # padding stays zero
    assert out.devices == ref.devices and sorted(out.aux) == sorted(ref.aux)
    for s in ("t", "temp", "temp_ext", "accel", "mask"):
        np.testing.assert_array_equal(getattr(out, s), np.asarray(getattr(ref, s)))


def test_numpy_engine_refuses_as_the_model_does(batch):
    cal = _calibration("bias_poly(1)+aux(vbat)", list(batch.devices))
    for engine in ("jax", "numpy"):
        with pytest.raises(DataError, match="needs extra column 'vbat'"):
            C.compensate(cal, batch, engine=engine)
    with pytest.raises(ValueError, match="engine"):
        C.compensate(cal, batch, engine="torch")


def test_a_signal_the_model_needs_is_named(batch):
    """Data without the temperature a thermal model reads: one DataError naming it, in
    either engine (the true rate a scale term reads is what compensation solves for)."""
    cal = _calibration("bias_poly(2)+gradient+scale_poly(0)", list(batch.devices))
    bare = dataclasses.replace(batch, temp=None, temp_ext=None)
    for engine in ("jax", "numpy"):
        with pytest.raises(DataError, match="needs temp, not in the data"):
            C.compensate(cal, bare, engine=engine)
