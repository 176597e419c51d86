"""Behaviour keyed on effect metadata, not on effect names: a user's ``@register``ed term
that declares ``constant_bias`` is treated exactly like ``bias_poly(0)`` by the
random-walk fit (the walk starts at zero beside it); without the declaration it is not."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from conftest import registered

from diffgyro.effects import AbstractEffect
from diffgyro.kalman import fit_random_walk
from diffgyro.simulate import simulate


class Offset(AbstractEffect):
    """A constant bias per axis, written as a user would."""

    name = "offset"
    description = "constant bias"
    constant_bias = True

    def param_names(self):
        return ("c",)

    def columns(self, sig, theta):
        return jnp.ones((sig.t.shape[0], 3, 1), sig.t.dtype)


class PlainOffset(Offset):
    """The same column without the declaration."""

    name = "plain_offset"
    constant_bias = False


@pytest.fixture(scope="module")
def batch():
    with registered(Offset, PlainOffset):
        yield simulate("thermal", 2, effects="bias_poly(0)+gradient", seed=4, duration=1800.0)[0]


def test_the_random_walk_starts_at_zero_beside_a_declared_constant(batch):
    want = fit_random_walk("bias_poly(0)+random_walk", batch, max_steps=20)
    got = fit_random_walk("offset+random_walk", batch, max_steps=20)
    plain = fit_random_walk("plain_offset+random_walk", batch, max_steps=20)
    np.testing.assert_allclose(got.loglik, want.loglik, rtol=1e-9)
    assert not np.allclose(plain.loglik, want.loglik, rtol=1e-6)


class SlowBias(AbstractEffect):
    """A user's transient term declaring the diagnose metadata a built-in carries."""

    name = "slow_bias"
    description = "bias following dT/dt through a fitted lag"
    follows = "dtemp"
    evidence_phrase = "creeps after every temperature change"
    family = "thermal transient"
    tau_from_dtemp_window = True

    def param_names(self):
        return ("c",)

    def nonlinear_names(self):
        return ("tau",)

    def nonlinear_grid(self, sig):
        return jnp.log(jnp.array([[1.0], [10.0], [1000.0]]))

    def columns(self, sig, theta):
        return jnp.zeros((sig.t.shape[0], 3, 1), sig.t.dtype) + theta[0]


class SlowBiasUndeclared(SlowBias):
    name = "slow_bias_plain"
    evidence_phrase = None
    family = None
    tau_from_dtemp_window = False


@pytest.fixture()
def user_terms():
    with registered(SlowBias, SlowBiasUndeclared):
        yield


def test_diagnose_reads_family_phrase_and_lag_floor_from_the_class(user_terms):
    from diffgyro.diagnose import (
        Candidate,
        CandidateSpec,
        DeviceDiagnosis,
        explain,
        families,
        family_of,
    )
    from diffgyro.internal import candidate_grid
    from diffgyro.model import ErrorModel
    from diffgyro.signals import make_signals

    assert family_of("slow_bias") == family_of("thermal_lag") == "thermal transient"
    assert "slow_bias" in families()["thermal transient"]
    assert family_of("slow_bias_plain") is None

    def said(effect):
        best = Candidate(effect=effect, spec=f"bias_poly(1)+{effect}", heldout_rms=1e-4,
                         significant=True, gain=5.0, closure=0.95, t=9.0, folds_improved=5,
                         rms=1e-4, term=effect)
        d = DeviceDiagnosis(device="d0", status="ok", rms=2e-4, heldout_rms=2e-4,
                            white_noise_rms=1e-4, white_noise_axes=[1e-4] * 3, floor_allan=1e-4,
                            verdict="missing_effect", candidates=[best], best=best,
                            alternatives=[], random_walk=None, allan_slope=0.0,
                            evidence={"dtemp": {"r": 0.93, "axis": "x", "label": "dT/dt"}})
        return explain(d)

    assert "creeps after every temperature change (r = +0.93 on axis x" in said("slow_bias")
    assert "follows the `slow_bias_plain` term" in said("slow_bias_plain")

    n = 8
    sig = make_signals(jnp.arange(n, dtype=float), jnp.zeros((n, 3)), jnp.ones(n, bool),
                       temp=jnp.linspace(20.0, 30.0, n))
    base = ErrorModel.from_spec("bias_poly(1)")
    lows = {}
    for name in ("slow_bias", "slow_bias_plain", "thermal_lag"):
        spec = CandidateSpec(effect=name, term=ErrorModel.from_spec(name).terms[0],
                             model=base + name)
        grid, _ = candidate_grid(spec, base, sig, jnp.zeros((0,)), np.log(60.0))
        lows[name] = float(np.exp(grid[0, 0]))
    assert lows["slow_bias"] == pytest.approx(60.0) == lows["thermal_lag"]
    assert lows["slow_bias_plain"] == pytest.approx(1.0)
