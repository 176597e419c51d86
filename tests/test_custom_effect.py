"""The custom-effect example of docs/effects.md: defined here, then fitted, diagnosed as a
candidate, written to a calibration file and applied, like any built-in term.

The page registers with ``@register`` at import; here registration happens in a
fixture and is undone afterwards, so other tests in the same process see the
built-in vocabulary only."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import registered

from diffgyro import ErrorModel, Params, calibration
from diffgyro.effects import AbstractEffect, registry
from diffgyro.fit import fit
from diffgyro.simulate import simulate


class TempRateProduct(AbstractEffect):
    """Bias ∝ T_s · dT/dt: a gradient sensitivity that changes with temperature."""

    name = "temp_rate_product"
    description = "bias proportional to temperature times dT/dt"
    needs = frozenset({"temp"})
    unit = "rad/s per °C/s"

    def param_names(self):
        return ("k",)

    def columns(self, sig, theta):
        col = sig.temp_s * sig.dtemp
        return jnp.broadcast_to(col[:, None, None], (col.shape[0], 3, 1))


SPEC = "bias_poly(2)+temp_rate_product"


@pytest.fixture(scope="module", autouse=True)
def user_term():
    with registered(TempRateProduct):
        yield


@pytest.fixture(scope="module")
def data():
    model = ErrorModel.from_spec(SPEC)
    rng = np.random.default_rng(3)
    beta = np.zeros((4, 3, model.n_params))
    beta[..., :3] = rng.normal(0.0, 2e-3, (4, 3, 3))
    beta[..., 3] = rng.choice([-1.0, 1.0], (4, 3)) * rng.uniform(0.4, 0.8, (4, 3))  # rad/s per °C/s
    params = Params(beta=beta, theta=np.zeros((4, 0)))
    noise = {"rrw": 0.0, "bias_instability": 0.0, "quantum": 0.0}
    return simulate("thermal", 4, effects=SPEC, params=params, seed=7, noise=noise)


def test_registered_and_parsed():
    assert registry()["temp_rate_product"] is TempRateProduct
    assert ErrorModel.from_spec(SPEC).spec == SPEC


def test_fitted_recovered_and_applied(data, tmp_path):
    batch, truth = data
    res = fit(SPEC, batch, norm=truth.norm)
    assert all(res.status_name(i) == "ok" for i in range(batch.n_devices))
    got = np.asarray(res.params.beta)[..., 3]
    want = np.asarray(truth.params.beta)[..., 3]
    assert np.max(np.abs(got - want) / np.abs(want)) < 0.1
    path = tmp_path / "cal.json"
    calibration.save(calibration.from_fit(res, batch), path)
    cal = calibration.load(path)
    assert cal.model == SPEC
    corrected, _ = calibration.compensate(cal, batch)
    n = int(batch.n_valid[0])
    resid = np.asarray(corrected.gyro[0, :n])
    assert np.all(resid.std(axis=0) < 1.1 * np.asarray(res.noise_axes[0]))


def test_diagnosed_as_candidate(data):
    from diffgyro.diagnose import diagnose

    batch, truth = data
    diag = diagnose("bias_poly(2)", batch)
    for dev in diag.records():
        names = [c["effect"] for c in dev["candidates"]]
        assert "temp_rate_product" in names
        assert dev["verdict"] == "missing_effect"
        assert dev["candidates"][0]["effect"] in ("temp_rate_product", "gradient", "thermal_lag")
