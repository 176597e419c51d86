"""diagnose prepares its scoring before the base fit, and the scores do not depend on it.

The candidates' ranges and the scoring program read the base fit's temperature norm, its
extra columns' norms and three options; ``diffgyro.diagnose._ahead`` forms them from the
batch before the fit, so the scoring program compiles on a thread while the fit runs.
Checked here: the prediction is the fit's setting bit for bit (a temperature model and a
model reading an extra column), the program prepared ahead is the one the scoring calls,
a diagnosis so prepared equals one given the base fit (which prepares nothing ahead),
and a prediction the fit contradicts is replaced by the fit's, with the same scores.

Data: two thermal runs made apart from the project's simulator (``hidden_effects.py``),
the hidden bias following dT/dt, one with an extra logged column ``vdd`` (the supply).
"""

from __future__ import annotations

import hidden_effects as H
import numpy as np
import pytest

from diffgyro.data import Batch, Recording
from diffgyro.diagnose import _ahead as ahead
from diffgyro.diagnose import _plan as plan
from diffgyro.diagnose import diagnose
from diffgyro.fit import fit
from diffgyro.signals import TempNorm

BASE = "bias_poly(2)"
#: Few candidates, no pair, synthesis or noise: the test is about the plumbing.
KW = dict(candidates=["gradient", "hysteresis"], greedy=False, synthesis=False, noise=False)


@pytest.fixture(scope="module")
def batch() -> Batch:
    recs = []
    for k in range(2):
        h = H.make_recording("thermal", "gradient", BASE, 70 + k, size=1.5,
                             noise=H.Noise(white=2e-4, flicker=0.1, drift=0.1), hours=2.0,
                             device=f"d{k}")
        r = h.recording
        vdd = 3.3 + 0.01 * np.sin(np.linspace(0.0, 7.0, r.n)) + 0.002 * k
        recs.append(Recording(t=r.t, gyro=r.gyro, temp=r.temp, temp_ext=r.temp_ext,
                              accel=r.accel, rate=r.rate, device=r.device, aux={"vdd": vdd}))
    return Batch.from_recordings(recs)


@pytest.mark.parametrize("spec", [BASE, "bias_poly(1)+aux(vdd)"])
def test_the_prediction_is_the_fits_setting_bit_for_bit(batch, spec):
    from diffgyro.model import ErrorModel

    model = ErrorModel.from_spec(spec)
    options = {"dtemp_window": 45.0, "n_folds": 4}
    st = ahead.predicted(model, batch, options)
    res = fit(model, batch, **options)
    assert ahead.same(st, ahead.of_fit(res))
    assert (st.n_folds, st.dtemp_window) == (4, 45.0)
    assert st.norm is not None and set(st.aux_norm) == ({"vdd"} if "aux" in spec else set())
    # options it does not follow: no prediction; a different norm is told apart
    assert ahead.predicted(model, batch, {"static_only": True}) is None
    # (the motion check sets the status, not the setting)
    assert ahead.same(ahead.predicted(model, batch, {**options, "check_motion": False}), st)
    off = st._replace(norm=TempNorm(centre=st.norm.centre, scale=np.nextafter(st.norm.scale, 99)))
    assert not ahead.same(off, ahead.of_fit(res))


def _same_diagnosis(a, b) -> None:
    assert a.to_json() == b.to_json()
    for k, v in a.raw.items():
        if isinstance(v, np.ndarray):
            assert v.tobytes() == b.raw[k].tobytes(), k
    assert np.asarray(a.residuals).tobytes() == np.asarray(b.residuals).tobytes()
    assert np.asarray(a.allan.adev).tobytes() == np.asarray(b.allan.adev).tobytes()


def test_prepared_ahead_equals_given_the_fit_and_a_missed_prediction_is_replaced(batch,
                                                                                  monkeypatch):
    before = dict(ahead.AHEAD)
    prepared = diagnose(BASE, batch, dtemp_window=60.0, **KW)
    assert ahead.AHEAD["hit"] == before.get("hit", 0) + 1  # the scoring ran what was compiled
    assert ahead.AHEAD["miss"] == before.get("miss", 0)
    assert ahead.AHEAD["refit"] == before.get("refit", 0)
    given = diagnose(BASE, batch, base_fit=fit(BASE, batch, dtemp_window=60.0), **KW)
    assert ahead.AHEAD["hit"] == before.get("hit", 0) + 1  # nothing prepared: the fit was given
    _same_diagnosis(prepared, given)

    def wrong(model, b, options):  # a norm the fit will not hold
        st = ahead.predicted(model, b, options)
        return st._replace(norm=TempNorm(centre=st.norm.centre + 1.0, scale=st.norm.scale))

    monkeypatch.setattr(plan, "predicted", wrong)
    replaced = diagnose(BASE, batch, dtemp_window=60.0, **KW)
    assert ahead.AHEAD["refit"] == before.get("refit", 0) + 1
    assert ahead.AHEAD["hit"] == before.get("hit", 0) + 2  # the same shapes: the program serves
    _same_diagnosis(replaced, given)
