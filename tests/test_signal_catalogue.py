"""The signal catalogue and the one builder from a batch to signals: every signal described,
the effects that follow it named, apply.py's numpy derivations equal to the builder's, and
a derived signal added in the catalogue alone usable in ``term(...)`` and fitted."""

from __future__ import annotations

from pathlib import Path

import jax
import numpy as np
import pytest
from recordings import turning_chamber_run

import diffgyro
from diffgyro import apply as A
from diffgyro.data import Batch, Recording
from diffgyro.effects import STANDARD as CATALOGUE
from diffgyro.effects import SignalInfo, register_signal, registry
from diffgyro.fit import fit
from diffgyro.internal import batch_signals
from diffgyro.signals import TempNorm


@pytest.fixture(scope="module", autouse=True)
def _x64():
    diffgyro.enable_x64()


@pytest.fixture(scope="module")
def recording() -> Recording:
    """30 min at 1 Hz: temperature up, soak, down; turning on all axes with a reference
    rate; tilting (:func:`recordings.turning_chamber_run`)."""
    return turning_chamber_run(1800, [0, 200, 800, 1000, 1600, 1800], seed=5,
                               temps=(20, 20, 45, 45, 15, 15), gain=1.0, noise=1e-3,
                               ext_offset=3.0, reference=True)


def test_every_signal_is_described_and_names_the_effects_that_follow_it():
    for name, s in CATALOGUE.items():
        assert s.name == name and s.unit and s.derivation and s.words and s.reads
        assert set(s.effects) <= set(registry()), (name, s.effects)
    for name, cls in registry().items():
        if cls.follows in CATALOGUE:
            assert name in CATALOGUE[cls.follows].effects, (name, cls.follows)


def test_the_docs_list_every_catalogue_signal():
    text = (Path(__file__).parents[1] / "docs" / "effects.md").read_text()
    for name in CATALOGUE:
        assert f"`{name}`" in text, name


def test_apply_derives_every_catalogue_signal_as_the_builder(recording):
    """apply.py (numpy only) keeps its own derivations: each catalogue signal equals the
    builder's to 1e-12 relative; dT/dt to 1e-11 (JAX's blocked prefix sums and numpy's
    cumsum round the window sums differently)."""
    centre, scale = 30.0, 15.0
    sig = batch_signals(Batch.from_recordings([recording]),
                        norm=TempNorm(centre=np.float64(centre), scale=np.float64(scale)))
    one = jax.tree.map(lambda a: a[0], sig)
    dev = {"temp_centre": centre, "temp_scale": scale}
    env = A.environment(dev, recording.t, temp=recording.temp, temp_ext=recording.temp_ext,
                        accel=recording.accel)
    for name in CATALOGUE:
        ours = np.asarray(CATALOGUE[name].value(one))[: recording.n]
        ref = A._signal(name, dev, recording.rate, env)
        assert ours.shape == ref.shape, name
        tol = (1e-11 if name == "dtemp" else 1e-12) * max(1.0, float(np.max(np.abs(ref))))
        np.testing.assert_allclose(ours, ref, rtol=0, atol=tol, err_msg=name)


def test_a_derived_signal_in_the_catalogue_alone_fits(recording):
    """|dT/dt| (°C/min), added as one catalogue entry, is a signal ``term(...)`` reads: a bias
    that follows it is fitted back to its coefficients."""
    info = register_signal(SignalInfo(
        "dtemp_abs", "°C/min", "|dT/dt|", "the temperature rate's size", frozenset({"temp"}),
        ("dtemp",), lambda sig: 60.0 * abs(sig.dtemp), derived=True))
    try:
        sig = batch_signals(Batch.from_recordings([recording]))
        x = np.asarray(info.value(sig))[0, : recording.n]
        true = np.array([2e-2, -1e-2, 5e-3])
        rec = Recording(t=recording.t, gyro=recording.gyro + x[:, None] * true,
                        rate=recording.rate, temp=recording.temp, device="imu0")
        res = fit("bias_poly(1)+term(dtemp_abs)", Batch.from_recordings([rec]))
        beta = np.asarray(res.params.beta)[0, :, -1]
        np.testing.assert_allclose(beta, true, atol=1e-4)
    finally:
        CATALOGUE.pop("dtemp_abs")
