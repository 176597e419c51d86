"""ErrorModel's parts: the deterministic effect terms and at most one noise component, from
the spec grammar; a user's noise process registered beside the built-in random walk."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import registered

from diffgyro import ErrorModel, kalman
from diffgyro.data import Recording
from diffgyro.diagnose import candidate_specs
from diffgyro.effects import (
    AbstractNoise,
    BiasPoly,
    Gradient,
    RandomWalk,
    noise_fit,
    register_noise_fit,
)
from diffgyro.errors import SpecError
from diffgyro.fit import fit


def test_the_random_walk_is_the_noise_component():
    model = ErrorModel.from_spec("bias_poly(2)+random_walk")
    assert model.terms == (BiasPoly(order=2),)
    assert isinstance(model.noise, RandomWalk)
    assert model.spec == "bias_poly(2)+random_walk"
    assert ErrorModel.from_spec(model.spec) == model
    assert model.n_params == 3
    assert model.param_labels()[0] == ["bias_poly(2).c0", "bias_poly(2).c1", "bias_poly(2).c2"]


def test_a_model_without_noise_and_adding_one():
    model = ErrorModel.from_spec("bias_poly(1)+gradient")
    assert model.noise is None and model.terms == (BiasPoly(order=1), Gradient())
    for extra in ("random_walk", RandomWalk(), ErrorModel.from_spec("random_walk")):
        walk = model + extra
        assert walk.terms == model.terms and walk.noise == RandomWalk()
        assert walk.spec == "bias_poly(1)+gradient+random_walk"
    # the noise is written after the terms, wherever the spec put it
    assert ErrorModel.from_spec("random_walk+bias_poly(1)").spec == "bias_poly(1)+random_walk"


def test_one_noise_component_per_model():
    with pytest.raises(SpecError, match="'random_walk' appears more than once"):
        ErrorModel.from_spec("random_walk+random_walk")
    model = ErrorModel.from_spec("bias_poly(0)+random_walk")
    for extra in ("random_walk", RandomWalk(), ErrorModel.from_spec("gradient+random_walk")):
        with pytest.raises(SpecError, match="more than once"):
            model + extra
    with pytest.raises(SpecError, match="not a deterministic effect"):
        ErrorModel((BiasPoly(order=0), RandomWalk()))
    with pytest.raises(SpecError, match="not a noise process"):
        ErrorModel((), BiasPoly(order=0))


class Flicker(AbstractNoise):
    """A user's noise process, with a fit of its own."""

    name = "flicker_walk"
    description = "bias flicker, fitted by the user's own smoother"
    unit = "(rad/s)²"


class SlowWalk(RandomWalk):
    """A user's variant of the random walk: the Kalman fit serves it too."""

    name = "slow_walk"


@pytest.fixture
def user_noise():
    from diffgyro.internal import NOISE_FITS

    with registered(Flicker, SlowWalk):
        yield
    NOISE_FITS.pop(Flicker, None)


def test_a_registered_user_noise_process(user_noise, monkeypatch):
    model = ErrorModel.from_spec("flicker_walk+bias_poly(1)")
    assert model.noise == Flicker() and model.terms == (BiasPoly(order=1),)
    assert model.spec == "bias_poly(1)+flicker_walk"
    with pytest.raises(SpecError, match="has 2 noise components .*; a model takes one"):
        ErrorModel.from_spec("flicker_walk+bias_poly(1)+random_walk")
    with pytest.raises(SpecError, match="2 noise components"):
        model + "random_walk"
    # diagnose offers each noise process to a model without one, none to a model with one
    offered = {c.effect: c.spec for c in candidate_specs(ErrorModel.from_spec("bias_poly(1)"),
                                                         frozenset({"temp"}))}
    assert offered["flicker_walk"] == "bias_poly(1)+flicker_walk"
    assert offered["random_walk"] == "bias_poly(1)+random_walk"
    assert not {"flicker_walk", "random_walk", "slow_walk"} & {
        c.effect for c in candidate_specs(model, frozenset({"temp"}))}

    # fit() finds the noise component's fit by its class (or the nearest registered base);
    # the front door registers the random walk's, which runs the state-space path
    assert noise_fit(SlowWalk()) is noise_fit(RandomWalk())
    monkeypatch.setattr(kalman, "fit_random_walk", lambda m, batch, **kw: ("kalman", m.spec))
    walk = ErrorModel.from_spec("bias_poly(1)+slow_walk")
    assert noise_fit(walk.noise)(walk, None) == ("kalman", "bias_poly(1)+slow_walk")
    rec = Recording(t=np.arange(200.0), gyro=np.zeros((200, 3)), temp=np.linspace(20, 30, 200))
    with pytest.raises(SpecError, match="no fit is registered for the noise component"):
        fit(model, rec)
    register_noise_fit(Flicker)(lambda m, batch, **kw: (m, batch.n_devices))
    assert fit(model, rec) == (model, 1)


def test_diagnose_lists_a_noise_process_it_does_not_score(user_noise):
    """diagnose's smoother is the random walk's: another noise process offered is listed
    under ``skipped`` with the reason, not dropped without a word."""
    from diffgyro.diagnose import diagnose

    rng = np.random.default_rng(1)
    t = np.arange(2000.0)
    rec = Recording(t=t, gyro=1e-3 * rng.normal(size=(2000, 3)), temp=20 + 10 * np.sin(t / 300))
    d = diagnose("bias_poly(1)", rec, candidates=["flicker_walk", "random_walk"]).devices[0]
    assert "diagnose scores one noise process" in d.skipped["flicker_walk"]
    assert d.random_walk is not None and "random_walk" not in d.skipped
