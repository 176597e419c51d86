"""Behaviour keyed on effect metadata, not on effect names: a user's ``@register``ed term
that declares ``constant_bias`` is treated exactly like ``bias_poly(0)`` by the
random-walk fit (the walk starts at zero beside it); without the declaration it is not."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro.effects import AbstractEffect, register
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
    from diffgyro.effects import base

    register(Offset)
    register(PlainOffset)
    yield simulate("thermal", 2, effects="bias_poly(0)+gradient", seed=4, duration=1800.0)[0]
    for c in (Offset, PlainOffset):
        base._REGISTRY.pop(c.name, None)


def test_the_random_walk_starts_at_zero_beside_a_declared_constant(batch):
    want = fit_random_walk("bias_poly(0)+random_walk", batch, max_steps=20)
    got = fit_random_walk("offset+random_walk", batch, max_steps=20)
    plain = fit_random_walk("plain_offset+random_walk", batch, max_steps=20)
    np.testing.assert_allclose(got.loglik, want.loglik, rtol=1e-9)
    assert not np.allclose(plain.loglik, want.loglik, rtol=1e-6)
