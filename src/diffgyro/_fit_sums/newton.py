"""Newton on the projected cost: the time constants of the full fit and of every
held-out fold's refit, problems of one batched loop solved in turn."""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float, Int, PyTree

#: ``evaluate(j, θ)``: problem j's value, gradient, Hessian and aux pytree at θ.
Evaluate = Callable[[Int[Array, ""], Float[Array, " q"]],
                    tuple[Float[Array, ""], Float[Array, " q"], Float[Array, "q q"], PyTree]]


def _proposal(th: Float[Array, " q"], g: Float[Array, " q"], h: Float[Array, "q q"],
              lam: Float[Array, ""], rtol: float,
              ) -> tuple[Float[Array, " q"], Bool[Array, ""], Bool[Array, ""]]:
    """The damped Newton step at θ, whether the point is near a minimum (take the plain
    step untested), and whether the plain step is below ``rtol·(1 + |θ|)`` (converged)."""
    if th.shape[0] == 1:  # one time constant: the eigen-decomposition is the number
        e, vec = h[0], jnp.ones((1, 1), h.dtype)
    else:
        e, vec = jnp.linalg.eigh(0.5 * (h + h.T))
    convex = jnp.all(e > 0)
    e = jnp.abs(e)
    big = jnp.max(e) + 1e-300
    gv = vec.T @ g
    plain = -(vec @ (gv / jnp.maximum(e, 1e-300 * big)))
    scale_th = 1.0 + jnp.linalg.norm(th)
    size_n = jnp.linalg.norm(plain)
    # close to a minimum Newton converges quadratically and f's rounding noise (a
    # difference of sums) would veto its last steps: take them without the f test
    near = convex & (size_n <= 1e-3 * scale_th)
    step = -(vec @ (gv / (e + lam * big)))
    step = jnp.where(near, plain, step)
    size = jnp.linalg.norm(step)
    step = step * jnp.minimum(1.0, 1.0 / jnp.maximum(size, 1e-300))
    return step, near, size_n <= rtol * scale_th


def _split_point(x: Float[Array, " point"], q: int) -> tuple[
        Float[Array, ""], Float[Array, " q"], Float[Array, " q"], Float[Array, "q q"],
        Float[Array, " aux"]]:
    """f, θ, g, H, aux of a point vector."""
    cuts = np.cumsum([1, q, q, q * q])
    f, th, g, h, aux = jnp.split(x, cuts)
    return f[0], th, g, h.reshape(q, q), aux


def _join_point(f: Float[Array, ""], th: Float[Array, " q"], g: Float[Array, " q"],
                h: Float[Array, "q q"], aux: Float[Array, " aux"]) -> Float[Array, " point"]:
    return jnp.concatenate([f[None], th, g, h.reshape(-1), aux])


def _loop_body(evaluate: Evaluate, rtol: float, q: int, head: int, row: int,
               problems: Int[Array, " problems"], caps_: Float[Array, " problems"], dtype,
               ) -> Callable[[Float[Array, " state"]], Float[Array, " state"]]:
    """One pass of the loop: a trial step of the current problem evaluated, accepted or
    not, and the problem's row written when it ends (the next starts from problem 0's
    optimum)."""
    n_problems = problems.shape[0]

    def flat_aux(aux: PyTree) -> Float[Array, " aux"]:
        return jnp.concatenate([a.reshape(-1).astype(dtype) for a in jax.tree.leaves(aux)])

    def body(state: Float[Array, " state"]) -> Float[Array, " state"]:
        j, k, lam = state[0], state[1], state[2]
        cur = state[3:head]
        out = state[head:].reshape(n_problems, row)
        v, th, g, h, aux = _split_point(cur, q)
        first = k == 0
        step, near, _ = _proposal(th, g, h, lam, rtol)
        step = jnp.where(first, 0.0, step)
        v_new, g_new, h_new, aux_new = evaluate(j.astype(jnp.int32), th + step)
        ok = jnp.isfinite(v_new) & ((v_new <= v) | near | first)
        cur = jnp.where(ok, _join_point(v_new, th + step, g_new, h_new, flat_aux(aux_new)), cur)
        v, th, g, h, aux = _split_point(cur, q)
        lam = jnp.where(first, lam, jnp.where(ok, lam * 0.3, lam * 10.0))
        # a start where the function is not finite ends the problem there
        done = (jnp.isfinite(v) & _proposal(th, g, h, lam, rtol)[2]) | ~jnp.isfinite(v)
        k = k + 1
        end = done | (k > jnp.sum(jnp.where(problems == j, caps_, 0.0)))
        here = end & (problems == j)
        result = jnp.concatenate([th, v[None], aux, (k - 1)[None], done.astype(dtype)[None]])
        out = jnp.where(here[:, None], result[None], out)
        # the next problem starts afresh from problem 0's optimum
        restart = _join_point(jnp.asarray(jnp.inf, dtype), out[0, :q], jnp.zeros_like(g),
                              jnp.eye(q, dtype=dtype), aux)
        cur = jnp.where(end, restart, cur)
        lam = jnp.where(end, 1e-3, lam)
        k = jnp.where(end, 0.0, k)
        return jnp.concatenate([jnp.stack([j + end, k, lam]), cur, out.reshape(-1)])

    return body


def newton(evaluate: Evaluate, theta0: Float[Array, " q"], caps: tuple[int, ...], rtol: float,
           aux_shapes: PyTree[jax.ShapeDtypeStruct],
           ) -> tuple[Float[Array, "problems q"], Float[Array, " problems"], PyTree,
                      Int[Array, " problems"], Bool[Array, " problems"]]:
    """Minimise smooth functions of a few parameters (log time constants), one after another.

    ``evaluate(j, θ)`` gives problem j's value, gradient, Hessian and an aux pytree
    (of ``aux_shapes``: given, so that ``evaluate`` is traced once) in one pass over
    the samples. Problem 0 starts at ``theta0``, every later one at
    problem 0's optimum (the folds' refits start from the full fit's); problem j takes
    at most ``caps[j]`` steps. The problems share one loop, so ``evaluate`` is traced
    and compiled once, and each pass evaluates one problem, as many passes as steps.

    Newton steps: negative curvature is flipped and a Levenberg term damps the step,
    which is accepted only if the value does not grow (and is at most 1 in log τ);
    near a minimum (convex, Newton step below 1e-3) the plain Newton step is taken. A
    trial is evaluated once — its gradient and Hessian come with its value, so an
    accepted step needs no second pass. Converged when the Newton step at the current
    point is below ``rtol·(1 + |θ|)``. A problem's first pass evaluates its start.
    Returns per problem (theta, value, aux, steps, converged), stacked.
    """
    n_problems = len(caps)
    q, dtype = theta0.shape[0], theta0.dtype
    aux_leaves, aux_tree = jax.tree.flatten(aux_shapes)
    aux_sizes = [int(np.prod(a.shape, dtype=np.int64)) for a in aux_leaves]
    n_aux = sum(aux_sizes)
    # the whole state is one vector (counters as exact floats): under vmap the loop
    # keeps each device's state by one select, and XLA emits one kernel for it, not
    # one per carry. It holds j (problem), k (pass) and λ; f, θ, g, H and aux at the
    # current point; then per problem a row of θ, f, aux, steps and converged.
    point = 1 + q + q + q * q + n_aux  # f, θ, g, H, aux
    head = 3 + point
    row = q + 1 + n_aux + 2
    problems = jnp.arange(n_problems)
    caps_ = jnp.asarray(caps, dtype)
    body = _loop_body(evaluate, rtol, q, head, row, problems, caps_, dtype)

    def cond(state: Float[Array, " state"]) -> Bool[Array, ""]:
        return state[0] < n_problems

    # θ0 makes the state batched from the start under vmap: the loop's batching rule
    # then traces the body once, not twice
    init = jnp.concatenate([jnp.asarray([0.0, 0.0, 1e-3], dtype),
                            _join_point(jnp.asarray(jnp.inf, dtype), theta0,
                                        jnp.zeros((q,), dtype), jnp.eye(q, dtype=dtype),
                                        jnp.zeros((n_aux,), dtype)),
                            jnp.zeros((n_problems * row,), dtype)])
    out = lax.while_loop(cond, body, init)[head:].reshape(n_problems, row)
    cuts = np.cumsum([0] + aux_sizes)
    aux = jax.tree.unflatten(aux_tree, [
        out[:, q + 1 + a:q + 1 + b].reshape((n_problems,) + leaf.shape).astype(leaf.dtype)
        for a, b, leaf in zip(cuts[:-1], cuts[1:], aux_leaves)])
    return (out[:, :q], out[:, q], aux, out[:, -2].astype(jnp.int32), out[:, -1] > 0.5)
