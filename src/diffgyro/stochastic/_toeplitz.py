"""The Gaussian deviance of a series under a symmetric Toeplitz covariance, and its
gradient with respect to the autocovariance, in O(M²) (numba).

For Σ with entries c(|i − j|) the Durbin–Levinson recursion gives, order by order, the
coefficients φ_(k,1…k) of the best linear prediction of x_k from x_(k−1) … x_0 and its
error variance v_k; Σ is positive definite exactly when every v_k is. Then

* ``log det Σ = Σ_k log v_k`` (Σ = A⁻¹DA⁻ᵀ, A unit lower triangular with row k the
  prediction error's coefficients, D = diag v_k);
* ``rᵀΣ⁻¹s = Σ_k e_k(r) e_k(s) / v_k`` with ``e_k(r) = r_k − Σ_j φ_(k,j) r_(k−j)`` the
  prediction errors, and ``Σ⁻¹r = AᵀD⁻¹e(r)``, accumulated row by row;
* the sums of Σ⁻¹ along its diagonals from the Gohberg–Semencul form of the inverse:
  with a = (1, −φ_(M−1,1), …, −φ_(M−1,M−1)), b = (0, −φ_(M−1,M−1), …, −φ_(M−1,1)) and
  L(x) the lower triangular Toeplitz matrix of first column x,
  ``Σ⁻¹ = (L(a)L(a)ᵀ − L(b)L(b)ᵀ) / v_(M−1)``; the sum of L(x)L(x)ᵀ along diagonal h
  is ``Σ_s (M − h − s) x_s x_(s+h)``.

The gradient of ``log det Σ + rᵀΣ⁻¹r`` along the Toeplitz indicator T_h (ones where
|i − j| = h) is ``tr(Σ⁻¹T_h) − αᵀT_hα`` with α = Σ⁻¹r: twice the diagonal sum and twice
α's lag-h product for h ≥ 1, once each at h = 0. The dense Cholesky factor gives the same
numbers at O(M³) (tests/test_block_likelihood.py compares them).

Compiled on first use and cached on disk (``cache=True``); imported when a block
likelihood is formed (numba's import takes about half a second).
"""

from __future__ import annotations

import math

import numpy as np
from jaxtyping import Bool, Float
from numba import njit


@njit(cache=True, nogil=True, fastmath={'reassoc', 'contract'})
def _deviance(c, d, ramp, grad):  # pragma: no cover - compiled
    m = c.shape[0]
    want = grad.shape[0] == m
    phi = np.zeros(m)
    tmp = np.zeros(m)
    alpha_d = np.zeros(m)  # AᵀD⁻¹e(d) and AᵀD⁻¹e(1): Σ⁻¹d and Σ⁻¹1
    alpha_1 = np.zeros(m)
    v = c[0]
    if not v > 0.0:
        return math.inf
    logdet = math.log(v)
    qdd, q1d, q11 = d[0] * d[0] / v, d[0] / v, 1.0 / v
    alpha_d[0] = d[0] / v
    alpha_1[0] = 1.0 / v
    for k in range(1, m):
        acc = c[k]
        for j in range(1, k):
            acc -= phi[j] * c[k - j]
        kappa = acc / v
        ed, e1 = d[k] - kappa * d[0], 1.0 - kappa
        for j in range(1, k):  # φ_(k,j) into tmp, and the prediction errors with them
            t = phi[j] - kappa * phi[k - j]
            tmp[j] = t
            ed -= t * d[k - j]
            e1 -= t
        for j in range(1, k):
            phi[j] = tmp[j]
        phi[k] = kappa
        v *= (1.0 - kappa) * (1.0 + kappa)
        if not v > 0.0:
            return math.inf
        logdet += math.log(v)
        qdd += ed * ed / v
        q1d += e1 * ed / v
        q11 += e1 * e1 / v
        if want:  # row k of A: −φ_(k,k) … −φ_(k,1), 1
            wd, w1 = ed / v, e1 / v
            alpha_d[k] += wd
            alpha_1[k] += w1
            for j in range(1, k + 1):
                alpha_d[k - j] -= phi[j] * wd
                alpha_1[k - j] -= phi[j] * w1
    mean = q1d / q11 if ramp else 0.0
    dev = logdet + qdd - (q1d * q1d / q11 if ramp else 0.0)
    if not want:
        return dev
    for i in range(m):
        tmp[i] = alpha_d[i] - mean * alpha_1[i]  # α = Σ⁻¹(d − mean)
    # a = (1, −φ_1 … −φ_(M−1)) in phi's place, b = (0, −φ_(M−1) … −φ_1) in alpha_d's
    phi[0] = -1.0
    for j in range(1, m):
        alpha_d[j] = phi[m - j]
    alpha_d[0] = 0.0
    for h in range(m):
        s_ab, s_tt = 0.0, 0.0
        for s in range(m - h):
            s_ab += (m - h - s) * (phi[s] * phi[s + h] - alpha_d[s] * alpha_d[s + h])
            s_tt += tmp[s] * tmp[s + h]
        grad[h] = (s_ab / v - s_tt) * (1.0 if h == 0 else 2.0)
    return dev


def toeplitz_deviance(c: Float[np.ndarray, " m"], d: Float[np.ndarray, " m"], ramp: bool,
                      grad: Float[np.ndarray, " m"] | None = None) -> float:
    """``log det Σ + rᵀΣ⁻¹r`` for Σ the symmetric Toeplitz matrix of first row ``c`` and
    r = d less its generalised least-squares mean where ``ramp`` (else r = d); inf where Σ is
    not positive definite. ``grad`` (M,), where given, receives the gradient with respect to
    c(0 … M−1)."""
    out = np.empty(0) if grad is None else grad
    return float(_deviance(np.ascontiguousarray(c, np.float64), np.ascontiguousarray(d, np.float64),
                           bool(ramp), out))


def toeplitz_deviances(c: Float[np.ndarray, "k m"], d: Float[np.ndarray, " m"],
                       ramp: Bool[np.ndarray, " k"], grad: bool = False):
    """:func:`toeplitz_deviance` of several candidates: −2 log L (K,) and, with ``grad``,
    the gradients (K, M)."""
    c = np.ascontiguousarray(c, np.float64)
    d = np.ascontiguousarray(d, np.float64)
    dev = np.empty(c.shape[0])
    g = np.zeros(c.shape) if grad else None
    for k in range(c.shape[0]):
        dev[k] = _deviance(c[k], d, bool(ramp[k]), g[k] if grad else np.empty(0))
    return (dev, g) if grad else dev
