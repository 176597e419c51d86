"""Confidence intervals of an Allan curve: SP 1065's "simple" equivalent degrees of freedom
for the noise type the local slope shows, and chi-square quantiles (SP 1065 eq. 45)."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy.special import gammainc, gammaln

#: Two-sided probability mass of a one-sigma interval.
ONE_SIGMA = math.erf(1.0 / math.sqrt(2.0))


def edf_simple(n_phase, m, alpha):
    """SP 1065 Table 5 EDF of overlapping ADEV for noise exponent ``alpha``.

    ``alpha``: +2 white PM, 0 white FM, −1 flicker FM, −2 random-walk FM
    (flicker PM is read as white PM here). ``n_phase`` = samples + 1.

    **Arguments:**

    - ``n_phase``: the phase points (samples + 1).
    - ``m``: the cluster size.
    - ``alpha``: the noise exponent.
    """
    N = jnp.asarray(n_phase, jnp.result_type(float))
    m = jnp.asarray(m, N.dtype)
    wpm = (N + 1.0) * (N - 2.0 * m) / (2.0 * (N - m))
    wfm = (3.0 * (N - 1.0) / (2.0 * m) - 2.0 * (N - 2.0) / N) * (4.0 * m**2 / (4.0 * m**2 + 5.0))
    ffm = jnp.where(m == 1, 2.0 * (N - 2.0) / (2.3 * N - 4.9), 5.0 * N**2 / (4.0 * m * (N + 3.0 * m)))
    rfm = (N - 2.0) / (m * (N - 3.0) ** 2) * ((N - 1.0) ** 2 - 3.0 * m * (N - 1.0) + 4.0 * m**2)
    out = jnp.where(alpha == 2, wpm, jnp.where(alpha == 0, wfm, jnp.where(alpha == -1, ffm, rfm)))
    return jnp.maximum(out, 1e-3)


def alpha_from_slope(slope):
    """Noise exponent (FM convention) for the EDF from the ADEV log-log slope: −½ → 0 (white FM),
    0 → −1 (flicker FM), +½ → −2 (random-walk FM).

    Steeper slopes (quantisation, white PM) get the white-FM EDF, which is
    smaller, i.e. conservative: a chance −1 slope among the few long clusters
    must not be granted white PM's huge EDF.

    **Arguments:**

    - ``slope``: the ADEV log-log slope.
    """
    return jnp.clip(jnp.round(-2.0 * slope - 1.0), -2.0, 0.0)


def chi2_ppf(p, nu):
    """Chi-square quantile: Wilson–Hilferty start, then Newton steps on log x (traceable).

    **Arguments:**

    - ``p``: the probability.
    - ``nu``: the degrees of freedom.
    """
    p = jnp.asarray(p, jnp.result_type(float))
    nu = jnp.asarray(nu, p.dtype)
    z = jnp.sqrt(2.0) * jax.scipy.special.erfinv(2.0 * p - 1.0)
    h = 2.0 / (9.0 * nu)
    x = nu * jnp.maximum(1.0 - h + z * jnp.sqrt(h), 0.05) ** 3
    k = 0.5 * nu

    def step(lx, _):
        xx = jnp.exp(lx)
        cdf = gammainc(k, 0.5 * xx)
        logpdf = (k - 1.0) * jnp.log(0.5 * xx) - 0.5 * xx - gammaln(k) - jnp.log(2.0)
        # d cdf / d log x = x · pdf(x)
        g = xx * jnp.exp(logpdf)
        dl = (cdf - p) / jnp.maximum(g, 1e-300)
        return lx - jnp.clip(dl, -2.0, 2.0), None

    lx, _ = jax.lax.scan(step, jnp.log(x), None, length=30)
    return jnp.exp(lx)
