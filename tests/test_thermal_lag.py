"""The first-order lag's two forms (a sequential loop on a CPU, a parallel prefix on an
accelerator) agree, and the CPU runs the loop bit for bit."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro.effects import first_order_lag
from diffgyro.internal import (
    LOG_TAU_RANGE,
    jet_parallel,
    jet_sequential,
    lag_parallel,
    lag_sequential,
    time_constant,
)
from diffgyro.internal import fit_groups as groups


def _record(n=3000, seed=0):
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 1.5, n))  # irregular sampling
    x = 20.0 + np.cumsum(rng.normal(size=n)) * 0.1
    return t, x


def _jet_inputs(t, log_tau):
    lo, hi = LOG_TAU_RANGE
    inside = float(lo <= log_tau <= hi)
    u = jnp.diff(t) / time_constant(log_tau)
    e = jnp.exp(-u)
    a1 = -u * e * inside
    return -jnp.expm1(-u), a1, -a1 * (1.0 - u), e


@pytest.mark.parametrize("tau", [0.3, 5.0, 300.0, 1e5])
def test_parallel_prefix_equals_the_loop(tau):
    t, x = _record()
    u = jnp.diff(t) / tau
    seq, par = lag_sequential(u, x), lag_parallel(u, x)
    np.testing.assert_allclose(par, seq, rtol=1e-13, atol=0)
    a, a1, a2, e = _jet_inputs(t, np.log(tau))
    js, jp = jet_sequential(a, a1, a2, e, x), jet_parallel(a, a1, a2, e, x)
    for k in range(3):  # the lag and its two derivatives in log τ
        scale = float(jnp.max(jnp.abs(js[:, k]))) or 1.0
        np.testing.assert_allclose(jp[:, k], js[:, k], rtol=0, atol=1e-12 * scale)


def test_jet_derivatives_match_finite_differences():
    t, x = _record(800, seed=1)
    lt, h = np.log(40.0), 1e-4
    a, a1, a2, e = _jet_inputs(t, lt)
    jet = jet_parallel(a, a1, a2, e, x)

    def lag_at(v):
        return first_order_lag(t, x, time_constant(v))

    d1 = (lag_at(lt + h) - lag_at(lt - h)) / (2 * h)
    d2 = (lag_at(lt + h) - 2 * lag_at(lt) + lag_at(lt - h)) / h**2
    np.testing.assert_allclose(jet[:, 1], d1, atol=1e-6 * float(jnp.max(jnp.abs(d1))))
    np.testing.assert_allclose(jet[:, 2], d2, atol=1e-3 * float(jnp.max(jnp.abs(d2))))


def test_cpu_runs_the_loop_bit_for_bit():
    t, x = _record()
    got = jax.jit(first_order_lag)(t, x, 50.0)
    want = jax.jit(lambda t, x: lag_sequential(jnp.diff(t) / 50.0, x))(t, x)
    assert jax.default_backend() == "cpu"
    assert bool(jnp.all(got == want))


def test_accelerator_groups_are_large():
    """An accelerator takes a fleet in few large calls; a CPU in cache-sized groups."""
    cpu = groups.devices_per_call(10_000, 10_000, nonlinear=True, fused=False)
    gpu = groups.devices_per_call(10_000, 10_000, nonlinear=True, fused=False, platform="gpu")
    assert cpu == 2
    assert gpu == groups.pow2_floor(groups.ACCELERATOR_GROUP_SAMPLES // 10_000) > 1000
    assert groups.devices_per_call(5, 10_000, True, False, "gpu") == 8  # the batch's own size
    # a linear model's transfers spread over the sending threads, two groups each
    assert groups.devices_per_call(1000, 10_000, False, True, "gpu", senders=4) == 128
    assert groups.devices_per_call(10_000, 10_000, False, True, "gpu", senders=4) == 1024
