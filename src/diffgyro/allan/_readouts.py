"""Read-outs of the noise terms from an Allan curve (IEEE Std 952): the four terms fitted at
once by non-negative least squares (``method="fit"``) or each fixed-slope line alone where
the local slope shows it (``method="lines"``); the package's notes say how and why."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

#: Bias-instability factor: the flicker floor of ADEV is sqrt(2 ln 2 / π)·B.
FLICKER_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)


def log_slope(log_tau, log_adev, weight, half: int = 3):
    """Slope of log σ against log τ by weighted least squares over ±``half`` points.

    **Arguments:**

    - ``log_tau``: log τ of the points.
    - ``log_adev``: log σ of the points.
    - ``weight``: each point's weight.
    - ``half``: the window, ± points.
    """
    k = log_tau.shape[-1]
    i = jnp.arange(k)
    win = (jnp.abs(i[:, None] - i[None, :]) <= half).astype(log_tau.dtype)
    w = win * weight[None, :]
    sw = jnp.sum(w, -1)
    mx = jnp.sum(w * log_tau[None, :], -1) / jnp.maximum(sw, 1e-300)
    my = jnp.sum(w * log_adev[None, :], -1) / jnp.maximum(sw, 1e-300)
    dx = log_tau[None, :] - mx[:, None]
    dy = log_adev[None, :] - my[:, None]
    sxx = jnp.sum(w * dx * dx, -1)
    sxy = jnp.sum(w * dx * dy, -1)
    npts = jnp.sum(win * (weight[None, :] > 0), -1)
    ok = (sxx > 0) & (npts >= 3)
    return jnp.where(ok, sxy / jnp.where(ok, sxx, 1.0), jnp.nan)


def _largest_run(flag, weight):
    """Mask of the contiguous run of True in ``flag`` with the largest total weight."""
    k = flag.shape[0]
    start = flag & ~jnp.concatenate([jnp.zeros((1,), bool), flag[:-1]])
    run_id = jnp.cumsum(start) - 1
    run_id = jnp.where(flag, run_id, k)
    tot = jax.ops.segment_sum(jnp.where(flag, weight, 0.0), run_id, num_segments=k + 1)[:k]
    best = jnp.argmax(tot)
    return flag & (run_id == best) & (tot[best] > 0)


def _line_readout(log_tau, log_adev, weight, region, slope, tau_read):
    """σ at ``tau_read`` on the line of fixed ``slope`` fitted (EDF-weighted) over ``region``."""
    w = jnp.where(region, weight, 0.0)
    c = jnp.sum(w * (log_adev - slope * log_tau)) / jnp.maximum(jnp.sum(w), 1e-300)
    return jnp.where(jnp.any(region), jnp.exp(c + slope * jnp.log(tau_read)), jnp.nan)


class Readouts(eqx.Module):
    """Noise terms read from one or many Allan curves (leading axes as the curves').

    ``*_region`` mark (1.0) the τ where that term dominates (``method="fit"``)
    or where the line was fitted (``method="lines"``).
    """

    arw: Float[Array, "..."]  # rad/s/√Hz  (σ at τ = 1 s on the −1/2 line)
    bias_instability: Float[Array, "..."]  # rad/s (flat floor / 0.664)
    rrw: Float[Array, "..."]  # rad/s²/√Hz (σ at τ = 3 s on the +1/2 line)
    quantization: Float[Array, "..."]  # rad (σ = √3·Q/τ on the −1 line; "fit" only)
    tau_min: Float[Array, "..."]  # s, where the curve is lowest
    arw_region: Float[Array, "... k"]
    flat_region: Float[Array, "... k"]
    rrw_region: Float[Array, "... k"]


def readouts_lines(tau, adev, edf, slope, tol, tol_flat, tol_rrw):
    """Graphical reading: fixed-slope lines fitted where the local slope is near −½ / +½,
    and the flat minimum where the local slope is near 0 (IEEE 952's figure, automated)."""
    ok = jnp.isfinite(adev) & (adev > 0) & jnp.isfinite(tau)
    weight = jnp.where(ok, edf, 0.0)
    lt = jnp.log(jnp.where(ok, tau, 1.0))
    la = jnp.log(jnp.where(ok, adev, 1.0))
    sl_ok = ok & jnp.isfinite(slope)
    arw_reg = _largest_run(sl_ok & (jnp.abs(slope + 0.5) <= tol), weight)
    rrw_reg = _largest_run(sl_ok & (jnp.abs(slope - 0.5) <= tol_rrw), weight)
    arw = _line_readout(lt, la, weight, arw_reg, -0.5, 1.0)
    rrw = _line_readout(lt, la, weight, rrw_reg, 0.5, 3.0)
    k = tau.shape[0]
    imin = jnp.argmin(jnp.where(ok, adev, jnp.inf))
    first = jnp.argmax(ok)
    last = k - 1 - jnp.argmax(ok[::-1])
    flat = (imin > first) & (imin < last) & (jnp.abs(slope[imin]) <= tol_flat) & jnp.any(ok)
    bi = jnp.where(flat, adev[imin] / FLICKER_FACTOR, jnp.nan)
    flat_reg = (jnp.arange(k) == imin) & flat
    f = tau.dtype
    return Readouts(arw=arw, bias_instability=bi, rrw=rrw, quantization=jnp.nan * arw,
                    tau_min=jnp.where(jnp.any(ok), tau[imin], jnp.nan),
                    arw_region=arw_reg.astype(f), flat_region=flat_reg.astype(f),
                    rrw_region=rrw_reg.astype(f))


#: Every non-empty subset of the four Allan-variance terms (quantisation, ARW, BI, RRW).
_SUBSETS = np.array([[(i >> j) & 1 for j in range(4)] for i in range(1, 16)], dtype=bool)


def noise_terms(tau, adev, edf, ok, iterations: int = 4):
    """Non-negative weighted least squares of the Allan variance on its four terms.

    ``σ²(τ) = 3Q²/τ² + N²/τ + (0.664·B)² + K²τ/3`` (quantisation Q, ARW N,
    bias instability B, RRW K). Every subset of terms is solved in closed
    form and the best one with all coefficients ≥ 0 is kept (exact NNLS for
    four terms); weights are the EDF over the squared modelled variance
    (var σ̂² ≈ 2σ⁴/EDF), refined a few times. Returns the coefficients
    ``(3Q², N², 0.664²B², K²/3)``, the design columns, and each term's
    evidence: the rise of the weighted squared misfit (a χ²) when the best
    fit must do without it.

    **Arguments:**

    - ``tau``: the cluster times τ (k,), s.
    - ``adev``: the Allan deviation at each (k,).
    - ``edf``: its equivalent degrees of freedom (k,).
    - ``ok``: which points are defined (k,).
    - ``iterations``: refinements of the weights.
    """
    x = jnp.stack([1.0 / tau**2, 1.0 / tau, jnp.ones_like(tau), tau], axis=-1)
    x = jnp.where(ok[:, None], x, 0.0)
    y = jnp.where(ok, adev**2, 0.0)
    subsets = jnp.asarray(_SUBSETS)

    def solve(w, mask):
        xm = x * mask
        sc = jnp.sqrt(jnp.sum(w[:, None] * xm**2, axis=0))
        sc = jnp.where(mask & (sc > 0), sc, 1.0)
        xs = xm / sc
        a = (xs * w[:, None]).T @ xs + jnp.diag(jnp.where(mask, 0.0, 1.0))
        c = jnp.linalg.solve(a + 1e-12 * jnp.eye(4), (xs * w[:, None]).T @ y) / sc
        c = jnp.where(mask, c, 0.0)
        cost = jnp.sum(w * (y - x @ c) ** 2)
        return c, jnp.where(jnp.all(c >= 0), cost, jnp.inf)

    def iterate(w, _):
        cs, costs = jax.vmap(lambda m: solve(w, m))(subsets)
        best = jnp.argmin(costs)
        c = cs[best]
        model = jnp.maximum(x @ c, 1e-3 * y)
        # evidence for each term: how much worse the best fit without it is
        without = jnp.min(jnp.where(subsets, jnp.inf, costs[:, None]), axis=0)
        gain = jnp.where(subsets[best], without - costs[best], 0.0)
        return jnp.where(ok, edf / jnp.where(ok, model, 1.0) ** 2, 0.0), (c, gain)

    w0 = jnp.where(ok, edf / jnp.where(ok, y, 1.0) ** 2, 0.0)
    _, (cs, gains) = jax.lax.scan(iterate, w0, None, length=iterations)
    return cs[-1], x, gains[-1]


def readouts_fit(tau, adev, edf, dominance, evidence):
    """Read-outs from the fitted terms; a term is reported only where it dominates some τ
    and the fit without it is worse by more than ``evidence`` (χ²)."""
    ok = jnp.isfinite(adev) & (adev > 0) & jnp.isfinite(tau) & jnp.isfinite(edf) & (edf > 0)
    c, x, gain = noise_terms(jnp.where(ok, tau, 1.0), jnp.where(ok, adev, 1.0),
                             jnp.where(ok, edf, 0.0), ok)
    contrib = x * c
    frac = contrib / jnp.maximum(jnp.sum(contrib, axis=-1, keepdims=True), 1e-300)
    region = ok[:, None] & (frac >= dominance)
    seen = jnp.any(region, axis=0) & jnp.any(ok) & (gain > evidence)
    q = jnp.where(seen[0], jnp.sqrt(c[0] / 3.0), jnp.nan)
    arw = jnp.where(seen[1], jnp.sqrt(c[1]), jnp.nan)
    bi = jnp.where(seen[2], jnp.sqrt(c[2]) / FLICKER_FACTOR, jnp.nan)
    rrw = jnp.where(seen[3], jnp.sqrt(3.0 * c[3]), jnp.nan)
    imin = jnp.argmin(jnp.where(ok, adev, jnp.inf))
    f = tau.dtype
    return Readouts(arw=arw, bias_instability=bi, rrw=rrw, quantization=q,
                    tau_min=jnp.where(jnp.any(ok), tau[imin], jnp.nan),
                    arw_region=region[:, 1].astype(f), flat_region=region[:, 2].astype(f),
                    rrw_region=region[:, 3].astype(f))
