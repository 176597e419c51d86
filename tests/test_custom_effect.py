"""The custom-effect example of docs/effects.md: defined here and diagnosed as a candidate;
added as the docs show (tests/readme_effect.py), it is fitted, written to a calibration
file and applied by the registry-driven tests, like any built-in term.

The page registers with ``@register`` at import; here registration happens in a
fixture and is undone afterwards, so other tests in the same process see the
built-in vocabulary only."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import ROOT, TESTS, registered

from diffgyro import ErrorModel, Params
from diffgyro.effects import AbstractEffect, registry
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


def test_registered_effect_is_covered_by_the_registry_driven_tests():
    """A new effect registered as docs/effects.md shows (tests/readme_effect.py, loaded as a
    plugin in a fresh pytest) gets the fit, calibration-file and apply-parity tests without
    their files being edited: collected under its name, and passing. The docs' term has
    no numpy form, so apply-parity checks that apply.py refuses it by name; the second term
    declares one (``numpy_columns``) and is compared with the fit's compensation (its fit,
    the same as the first's, is left out here for time)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(ROOT / "src"), str(TESTS)] + [p for p in os.environ.get("PYTHONPATH", "").split(
            os.pathsep) if p])}
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-v", "-p", "no:cacheprovider", "-p", "readme_effect",
         "tests/test_fit.py", "tests/test_apply_parity.py",
         "-k", "temp_rate_product or (apply and temp_rate_firmware)"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    passed = set(re.findall(r"(tests/\S+::\S+) PASSED", proc.stdout))
    assert passed == {
        "tests/test_fit.py::test_recovers_truth[temp_rate_product]",
        "tests/test_fit.py::test_calibration_file_compensates[temp_rate_product]",
        "tests/test_apply_parity.py::test_apply_equals_compensate_for_each_effect"
        "[temp_rate_product-no-numpy-form]",
        "tests/test_apply_parity.py::test_apply_equals_compensate_for_each_effect"
        "[temp_rate_firmware]",
    }, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert proc.returncode == 0, proc.stdout[-3000:]


def test_diagnosed_as_candidate(data):
    from diffgyro.diagnose import diagnose

    batch, truth = data
    diag = diagnose("bias_poly(2)", batch)
    for dev in diag.records():
        names = [c["effect"] for c in dev["candidates"]]
        assert "temp_rate_product" in names
        assert dev["verdict"] == "missing_effect"
        assert dev["candidates"][0]["effect"] in ("temp_rate_product", "gradient", "thermal_lag")
