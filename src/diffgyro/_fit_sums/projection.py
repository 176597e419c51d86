"""Variable projection: the projected cost's value, gradient and Hessian in the time
constants from the sums and their derivatives."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .normal_equations import cho_solve, cholesky, residual_ss


def product_jet(u: Float[Array, "..."], du: Float[Array, "q ..."] | None,
                ddu: Float[Array, "q q ..."] | None, v: Float[Array, "..."],
                dv: Float[Array, "q ..."] | None, ddv: Float[Array, "q q ..."] | None, q: int,
                ) -> list[Float[Array, "..."]]:
    """``u·v``, its first derivatives (q) and second derivatives (q·q, row-major) by the
    product rule; a derivative given as None is zero (a factor that does not move)."""
    def total(parts):
        parts = [t for t in parts if t is not None]
        return functools.reduce(lambda x, y: x + y, parts) if parts else jnp.zeros_like(u)

    def d1(k):
        return total([None if du is None else du[k] * v, None if dv is None else u * dv[k]])

    def d2(k, r):
        both = du is not None and dv is not None
        return total([None if ddu is None else ddu[k, r] * v,
                      None if ddv is None else u * ddv[k, r],
                      du[k] * dv[r] if both else None, du[r] * dv[k] if both else None])

    return [u * v] + [d1(k) for k in range(q)] + [d2(k, r) for k in range(q) for r in range(q)]


def projected_cost(sums: tuple[Float[Array, "3 p p"], Float[Array, "3 p"], Float[Array, " 3"],
                                 Float[Array, ""]],
                   dsums: tuple[Float[Array, "q 3 p p"], Float[Array, "q 3 p"],
                                Float[Array, "q 3"], Float[Array, " q"]],
                   ddsums: tuple[Float[Array, "q q 3 p p"], Float[Array, "q q 3 p"],
                                 Float[Array, "q q 3"], Float[Array, "q q"]],
                   ) -> tuple[Float[Array, ""], Float[Array, " q"], Float[Array, "q q"]]:
    """Value, gradient and Hessian of the projected cost ``Σ_i min_β Σ(y_i − x_iβ)²``
    from the sums (A, c, Q, count) of :func:`.normal_equations.unpack` and their derivatives (leading
    axes (q,) and (q, q)).

    With ``β = A⁻¹c`` stationary, ``f = Q − 2βᵀc + βᵀAβ`` has ``∂f = ∂Q − 2βᵀ∂c + βᵀ∂Aβ``
    and ``∂²f = ∂²Q − 2βᵀ∂²c + βᵀ∂²Aβ − 2 r_kᵀA⁻¹r_l`` with ``r = ∂c − ∂Aβ``: one
    factorisation of each A, no derivative of the factorisation itself.
    """
    a, c, q, _ = sums
    da, dc, dq, _ = dsums
    dda, ddc, ddq, _ = ddsums
    chol, d = cholesky(a)
    beta = cho_solve(chol, d, c)

    def first(a_, c_, q_):  # Σ_i ∂Q − 2βᵀ∂c + βᵀ∂Aβ over the leading axes
        return jnp.sum(q_ - 2.0 * jnp.einsum("ip,...ip->...i", beta, c_)
                       + jnp.einsum("ip,...ipr,ir->...i", beta, a_, beta), axis=-1)

    r = dc - jnp.einsum("kipr,ir->kip", da, beta)  # (q, 3, p)
    rhs = jnp.moveaxis(r, 0, -1) / d[..., None]  # (3, p, q)
    ar = jax.scipy.linalg.cho_solve((chol, True), rhs) / d[..., None]
    hess = first(dda, ddc, ddq) - 2.0 * jnp.einsum("ipk,ipl->kl", jnp.moveaxis(r, 0, -1), ar)
    value = jnp.sum(residual_ss(a, c, q, beta))
    return value, first(da, dc, dq), hess
