"""The sums path's Newton solver (``fit_sums.newton``): problems solved in turn to
their known minima, step caps, a non-finite start, results equal under vmap."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from diffgyro._fit_sums import newton as newton_loop

CENTRES = np.array([[0.3, -1.2], [2.0, 0.5], [-0.7, 0.1]])  # problem j's minimum


def quartic(centres):
    """Problem j: f = Σ (θ − c_j)² + (θ − c_j)⁴ (+ a cross term), minimum 1 at c_j,
    with its exact gradient and Hessian and an aux pytree (θ, and j as a float)."""
    def evaluate(j, th):
        c = jnp.asarray(centres)[j]
        d = th - c
        f = 1.0 + jnp.sum(d**2 + d**4) + 0.3 * d[0] * d[1]
        g = 2 * d + 4 * d**3 + 0.3 * d[::-1]
        h = jnp.diag(2 + 12 * d**2) + 0.3 * (1 - jnp.eye(2))
        return f, g, h, {"at": th, "problem": jnp.asarray(j, th.dtype)[None]}
    return evaluate


def newton(evaluate, theta0, caps):
    """``fit_sums.newton`` told the aux pytree of :func:`quartic`."""
    aux = {"at": jax.ShapeDtypeStruct((2,), theta0.dtype),
           "problem": jax.ShapeDtypeStruct((1,), theta0.dtype)}
    return newton_loop(evaluate, theta0, caps, 1e-10, aux)


def test_every_problem_reaches_its_minimum_in_turn():
    th, f, aux, steps, done = jax.jit(
        lambda t0: newton(quartic(CENTRES), t0, (40, 20, 20)))(jnp.array([5.0, 5.0]))
    np.testing.assert_allclose(th, CENTRES, atol=1e-8)
    np.testing.assert_allclose(f, 1.0, atol=1e-14)
    assert np.all(done) and np.all(steps >= 1) and np.all(steps <= np.array([40, 20, 20]))
    # aux is the one evaluated at each problem's optimum, of its own shape and dtype
    np.testing.assert_array_equal(aux["at"], th)
    np.testing.assert_array_equal(aux["problem"][:, 0], [0.0, 1.0, 2.0])


def test_a_cap_ends_a_problem_unconverged():
    # problem 1 may take one step from problem 0's optimum: not enough to get there
    th, _, _, steps, done = newton(quartic(CENTRES), jnp.array([5.0, 5.0]), (40, 1, 20))
    assert done[0] and not done[1] and done[2]
    assert steps[1] == 1
    assert np.linalg.norm(np.asarray(th[1]) - CENTRES[1]) > 1e-3


def test_a_start_that_is_not_finite_ends_that_problem_only():
    def evaluate(j, th):
        f, g, h, aux = quartic(CENTRES)(j, th)
        # problem 1 starts from problem 0's optimum, where it is not finite
        bad = (j == 1) & (jnp.max(jnp.abs(th - jnp.asarray(CENTRES[0]))) < 1e-6)
        return jnp.where(bad, jnp.nan, f), g, h, aux

    th, f, _, steps, done = newton(evaluate, jnp.array([5.0, 5.0]), (40, 20, 20))
    assert not np.isfinite(f[1]) and steps[1] == 0 and done[1]
    np.testing.assert_allclose(np.asarray(th)[[0, 2]], CENTRES[[0, 2]], atol=1e-8)


@pytest.mark.parametrize("starts", [[[5.0, 5.0], [-3.0, 1.0], [0.3, -1.2]]])
def test_batched_devices_equal_one_at_a_time(starts):
    """Under vmap every device runs the loop until its own last problem ends (the
    others' states held by a select): each equals its own unbatched solve."""
    solve = jax.jit(lambda t0: newton(quartic(CENTRES), t0, (40, 20, 20)))
    batched = jax.jit(jax.vmap(lambda t0: newton(quartic(CENTRES), t0, (40, 20, 20))))(
        jnp.asarray(starts))
    for i, s in enumerate(starts):
        one = solve(jnp.asarray(s))
        for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(batched)):
            np.testing.assert_array_equal(a, b[i])


def test_groups_sent_ahead_from_threads_give_the_same_fit(monkeypatch):
    """An accelerator's groups are sent from host threads (``transfer.in_order``); forced
    here on the CPU, with groups of 8 devices, the fit is the same to the bit."""
    from diffgyro._fit_sums import groups, transfer
    from diffgyro.fit import fit
    from diffgyro.simulate import simulate

    batch, _ = simulate("thermal", 20, effects="bias_poly(2)+gradient", seed=3,
                        sample_rate=1.0, duration=2000.0)
    monkeypatch.setattr(groups, "MAX_GROUP_DEVICES", 8)
    plain = fit("bias_poly(2)+gradient", batch, check_motion=False, noise_floor=False)
    order = transfer.in_order
    seen = []

    def ahead(send, count, platform, threads=None):
        seen.append(count)
        return order(send, count, "accelerator", 3)

    monkeypatch.setattr(transfer, "in_order", ahead)
    sent = fit("bias_poly(2)+gradient", batch, check_motion=False, noise_floor=False)
    assert seen == [3]  # 20 devices in groups of 8
    for a, b in zip(jax.tree.leaves(plain.params), jax.tree.leaves(sent.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(plain.status), np.asarray(sent.status))
