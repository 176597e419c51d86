"""Covariance of the empirical Haar wavelet variances under a Gaussian model (the GMWM weights).

For a Gaussian series whose Haar coefficients at scales i, j have the filters
``H_i``, ``H_j`` (``|H_m(f)|² = sin⁴(πfm)/(m² sin²(πf))``, f in cycles per
sample), the overlapping means of the squared coefficients have, to first
order in 1/M (M terms averaged; Percival & Walden ch. 8)::

    Cov(ν̂²_i, ν̂²_j) ≈ 2/M · ∫_{−½}^{½} |H_i(f)|² |H_j(f)|² S(f)² df

with S the two-sided spectral density of the rate per sample (white: N²/dt;
quantization: 4Q² sin²(πf)/dt²; Gauss–Markov: σ²(1−φ²)/((1−φ)² + 4φ sin²(πf));
random walk: K²dt/(4 sin²(πf)); the Haar filters cancel its pole). A rate ramp
is deterministic; it adds ``4 d_i d_j S_ij(0)/M`` (``d = R·m·dt/2`` its Haar
coefficient, ``S_ij(0) = m_i m_j K²dt/4`` the random walk's cross-spectrum of
coefficients at zero frequency).

The integral runs on a logarithmic frequency grid. Where ``πfm`` exceeds a few
periods the factor ``sin⁴(πfm)`` oscillates faster than the grid resolves; it is
replaced there by its average (3/8; for a product of two, 35/128 at the same
scale, 7/64 an octave apart, 9/64 further), which leaves the integral within a
few per cent while the grid stays a thousand points for any record length.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

#: Frequency points of the quadrature, from 0.02/n to 1/2 cycles per sample.
GRID = 1200
#: Above this many radians of πfm a sin⁴ factor is replaced by its average.
_U = 6.0 * jnp.pi


def psd(theta: Float[Array, " 8"], mask: Bool[Array, " 8"], f: Float[Array, " G"],
        dt) -> Float[Array, " G"]:
    """Two-sided spectral density of the composite rate per sample, (rad/s)² per cycle/sample."""
    p = jnp.exp(theta)
    s2 = jnp.sin(jnp.pi * f) ** 2
    out = jnp.where(mask[0], p[0] / dt, 0.0)
    out = out + jnp.where(mask[1], 4.0 * p[1] * s2 / dt**2, 0.0)
    for iv, it in ((2, 3), (4, 5)):
        a = dt / p[it]
        one_phi = -jnp.expm1(-a)
        phi = 1.0 - one_phi
        gm = p[iv] * (-jnp.expm1(-2.0 * a)) / (one_phi**2 + 4.0 * phi * s2)
        out = out + jnp.where(mask[iv], gm, 0.0)
    out = out + jnp.where(mask[6], p[6] * dt / (4.0 * s2), 0.0)
    return out


@jax.jit
def wv_covariance(theta: Float[Array, " 8"], mask: Bool[Array, " 8"], m: Float[Array, " J"],
                  count: Float[Array, " J"], n, dt) -> Float[Array, "J J"]:
    """Covariance of the empirical Haar wavelet variances at cluster sizes ``m`` (each averaged
    over ``count`` terms) of an n-sample series of the model (module docstring). Traced once
    per shape (:mod:`.identify`'s note)."""
    m = jnp.asarray(m, jnp.float64)
    lf = jnp.linspace(jnp.log(0.02 / n), jnp.log(0.5), GRID)
    f = jnp.exp(lf)
    s = psd(theta, mask, f, dt)
    sin2 = jnp.sin(jnp.pi * f) ** 2
    arg = jnp.pi * f[None, :] * m[:, None]  # (J, G)
    fast = arg >= _U
    env = 1.0 / (m[:, None] ** 2 * sin2[None, :])  # |H|² with sin⁴ at its bound, 1
    gain = jnp.where(fast, 0.375, jnp.sin(arg) ** 4) * env  # |H|² with the fast factor averaged
    # the trapezoid rule's weights times S² f (the integral runs over log f)
    h = lf[1] - lf[0]
    ends = jnp.ones_like(f).at[0].set(0.5).at[-1].set(0.5)
    w = h * ends * s**2 * f
    # Σ_g gain_i gain_j w: both factors averaged where both are fast (3/8 · 3/8 = 9/64);
    # there the average of the product is 35/128 at one scale, 7/64 an octave apart and
    # 9/64 further, so the difference is added where both are fast: two products of
    # (J, G) matrices instead of a (J, J, G) array
    octaves = jnp.abs(jnp.round(jnp.log2(m[:, None] / m[None, :])))
    both = jnp.where(octaves == 0, 35.0 / 128.0, jnp.where(octaves == 1, 7.0 / 64.0, 9.0 / 64.0))
    fe = jnp.where(fast, env, 0.0)
    integral = (gain * w) @ gain.T + (both - 9.0 / 64.0) * ((fe * w) @ fe.T)
    big_m = jnp.maximum(count[:, None], count[None, :])
    cov = 4.0 * integral / big_m  # 2/M ∫_{−½}^{½} = 4/M ∫_0^{½}
    # the ramp's deterministic coefficients times the mean of the noise's: the random walk's
    # zero-frequency coefficients (order 1/M), and the record's ends for the rest (order 1/M²)
    p = jnp.exp(theta)
    d = jnp.where(mask[7], jnp.sqrt(p[7]) * m * dt / 2.0, 0.0)
    s0 = jnp.where(mask[6], m[:, None] * m[None, :] * p[6] * dt / 4.0, 0.0)
    ends = _ends(p, mask, m, count, dt)
    return cov + 4.0 * d[:, None] * d[None, :] * (s0 / big_m + ends)


def _ends(p, mask, m, count, dt):
    """Covariance of the means of the Haar coefficients at scales i, j of the noise but the
    random walk: the filter sums to zero, so the mean over M positions keeps only the
    record's two ends, triangles of 2m samples with weights up to 1/(2M): Σ c_i c_j =
    2·T_ij/(4 m_i m_j M_i M_j) per unit of white variance, T_ii = 2m³/3, T_ij = min(m)³
    (scales an octave or more apart). White noise and each Gauss–Markov process count with
    their long-scale white variance per sample (σ²(1+φ)/(1−φ)); quantization, a difference
    itself, cancels further. Small beside the noise's own variance, it is the whole spread
    of a ramp's wavelet variance where the ramp dominates (its intervals were too narrow
    without it: none of 12 covered a white + ramp truth)."""
    var = jnp.where(mask[0], p[0] / dt, 0.0)
    for iv, it in ((2, 3), (4, 5)):
        one_phi = -jnp.expm1(-dt / p[it])
        var = var + jnp.where(mask[iv], p[iv] * (2.0 - one_phi) / one_phi, 0.0)
    lo = jnp.minimum(m[:, None], m[None, :])
    t = jnp.where(m[:, None] == m[None, :], 2.0 * lo**3 / 3.0, lo**3)
    cnt = jnp.maximum(count, 1.0)
    return var * 2.0 * t / (4.0 * m[:, None] * m[None, :] * cnt[:, None] * cnt[None, :])
