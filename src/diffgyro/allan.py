"""Overlapping Allan deviation of gyro rates and the read-outs of its noise terms.

For a rate series ``y`` sampled every ``dt`` seconds, the overlapping Allan
deviation at ``τ = m·dt`` is (NIST SP 1065 eq. 11)::

    σ²(τ) = 1 / (2 τ² (N+1-2m)) · Σ_i (x[i+2m] - 2 x[i+m] + x[i])²

with the phase (angle) ``x = dt·[0, cumsum(y - mean y)]``: one pass of
cumulative sums, then O(N) per τ. The definition, the mean removal and the
counting are those of ``allantools.oadev(y, rate=1/dt, data_type="freq")``
(its ``taus`` are ``m·dt``), which the tests reproduce to 1e-10.

Everything is vmapped: a Batch's gyro (devices, samples, 3) gives one curve
per device and axis, padded samples excluded through ``n_valid``.

Its companions, for comparison with published tables and other tools, work
on the same phase in numpy, one vectorised pass per τ: the non-overlapping
deviation (:func:`adev_nonoverlapping`, SP 1065 eq. 7) and the modified one
(:func:`mdev`, SP 1065 eq. 14). A τ with fewer than one term is NaN.

Confidence intervals are chi-square intervals (SP 1065 eq. 45) with the
equivalent degrees of freedom of SP 1065 Table 5 ("simple" EDF) for the noise
type the curve shows at that τ: the local log-log slope picks white FM /
angle random walk (≤ −1/4; also used, conservatively, for quantisation),
flicker FM / bias instability (0) or random-walk FM / rate random walk (+1/2).

Read-outs (IEEE Std 952 conventions), units stated:

* ``arw`` N (rad/s/√Hz = rad/√s): σ at τ = 1 s on the −1/2 line ``N/√τ``;
* ``bias_instability`` B (rad/s): the flat floor ``0.664·B`` divided by
  √(2 ln 2 / π) ≈ 0.664;
* ``rrw`` K (rad/s²/√Hz = rad/s/√s): σ at τ = 3 s on the +1/2 line ``K·√(τ/3)``;
* ``quantization`` Q (rad): the −1 line ``√3·Q/τ``.

How the lines are placed (``method``):

* ``"fit"`` (default): the Allan *variance* is fitted with all four terms at
  once, ``σ² = 3Q²/τ² + N²/τ + 0.664²B² + K²τ/3``, by non-negative weighted
  least squares (weights EDF/σ⁴, the inverse variance of σ̂²). Each line is
  then free of the others' contamination: on simulated white + flicker
  noise the −1/2 line alone read ARW 6 % high, the fit reads it within 1 %.
  A term is reported only if it carries at least half the variance at some
  measured τ (it shows a region of its own slope) *and* dropping it worsens
  the weighted misfit by more than ``evidence`` (χ², default 25, chosen
  because neighbouring τ are strongly correlated); otherwise NaN.
* ``"lines"``: the graphical reading automated: each fixed-slope line is
  fitted alone (log-log, EDF-weighted) over the largest run of τ whose local
  slope is within ``tol`` of −1/2 or ``tol_rrw`` of +1/2, and the bias
  instability is the curve's minimum / 0.664 where the slope there is within
  ``tol_flat`` of 0.

A read-out the data do not support is NaN (``None`` in JSON): no number is
invented for a term the curve does not show. White noise plus a bias random
walk has a minimum where the two lines cross, but no flat floor: "fit"
reports no bias instability there ("lines" reports the crossing, as a
reading by eye would).
"""

from __future__ import annotations

import math
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammainc, gammaln
from jaxtyping import Array, Float, Int

from ._jit import filter_jit, release_compiled_if_crowded
from ._jsonio import number
from ._xla_options import FAST_COMPILE
from .errors import DataError
from .signals import prefix_sums

__all__ = ["allan", "allan_batch", "AllanResult", "Readouts", "noise_terms", "plot_allan",
           "to_json", "allan_at_taus", "oadev", "adev_nonoverlapping", "mdev", "log_slope",
           "default_m", "cluster_sizes", "sample_interval", "sample_intervals", "edf_simple",
           "chi2_ppf", "alpha_from_slope", "FLICKER_FACTOR"]

#: Bias-instability factor: the flicker floor of ADEV is sqrt(2 ln 2 / π)·B.
FLICKER_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)
#: Two-sided probability mass of a one-sigma interval.
ONE_SIGMA = math.erf(1.0 / math.sqrt(2.0))
#: Stable32's stop ratio for overlapping ADEV: largest m is N / 4.
STOP_RATIO = 4


def default_m(n: int, per_decade: int = 10, stop_ratio: int = STOP_RATIO) -> np.ndarray:
    """Cluster sizes 1 .. n // stop_ratio, about ``per_decade`` per decade (integers, unique).

    **Arguments:**

    - ``n``: the series' samples.
    - ``per_decade``: cluster sizes per decade.
    - ``stop_ratio``: the longest cluster is ``n / stop_ratio`` samples.
    """
    top = max(1, int(n) // int(stop_ratio))
    k = int(math.floor(per_decade * math.log10(top))) + 1
    m = np.unique(np.round(np.logspace(0.0, math.log10(top), max(k, 1))).astype(np.int64))
    return m[m >= 1]


#: Samples per step of the loop over series: one 1M-sample series at a time keeps its padded
#: phase (12 MB) in cache while all τ are summed (with one whole-series pass per τ, two
#: series at a time were ~1.6× slower per series and all at once, the former vmap, slower
#: still; measured).
_CHUNK_SAMPLES = 1 << 20
#: Terms (τ × samples) summed per step of the loop over blocks: all τ of one block of
#: samples at once, so the three windows of a small-m τ are read from a block already in
#: cache and the (τ, block) temporary stays a few MB. Blocks of 16 384 samples for 51 τ
#: were ~1.2-1.7× faster than one whole-series pass per τ (measured; 65 536 was slower).
_BLOCK_TERMS = 1 << 20
#: The same two budgets on a GPU or TPU, where each loop step must carry far more work (one
#: step per series and block would leave the device mostly idle): up to 128 series of 1M
#: samples per step, a (τ, series, block) temporary of at most 512 MB. Not measured (no
#: accelerator was available when they were set); the code path is the CPU one.
_ACCEL_CHUNK_SAMPLES = 1 << 27
_ACCEL_BLOCK_TERMS = 1 << 26


def _block_length(n: int, k: int, terms: int) -> int:
    """Samples per block: a power of two with k · block ≈ ``terms`` (k: τ × series summed
    together), at least 256, at most n."""
    target = max(terms // max(k, 1), 256)
    return max(1, min(n, 1 << (target.bit_length() - 1)))


def _oadev_one(y, n_valid, dt, m, stop_ratio, batch, block_terms, padded=True):
    """Overlapping ADEV of one padded series; returns (adev, count) per m (NaN if too few).

    One prefix sum gives the phase x (mean removed first, as allantools does, so
    that x stays small and its second differences do not cancel). The sums of
    squared second differences are then accumulated block by block of samples,
    all τ of a block at once: for τ = m the block's terms read three contiguous
    windows of x at offsets 0, m, 2m (a fused gather; no (τ, n) temporary).
    Only m ≤ n / stop_ratio can be defined, so x is zero-padded by 2·that.
    ``batch`` series run together (vmapped), so their blocks share ``block_terms``;
    ``padded=False`` (static) says that all n samples are real.
    """
    n = y.shape[0]
    k = m.shape[0]
    mmax = max(n // stop_ratio, 1) if stop_ratio > 0 else n
    blk = _block_length(n, k * batch, block_terms)
    nblocks = -(-n // blk)  # terms i < n suffice: count ≤ n − 1 for m ≥ 1
    if padded:
        valid = jax.lax.iota(jnp.int32, n) < n_valid
        mean = jnp.sum(jnp.where(valid, y, 0.0)) / jnp.maximum(n_valid, 1)
        yc = jnp.where(valid, y - mean, 0.0)
    else:  # every sample real (n_valid not given): no masked copy of y for the mean
        mean = jnp.sum(y) / n
        yc = y - mean
    # phase x[0..n] (x[0] = 0), then zeros so that every window below stays in bounds
    x = jnp.concatenate([prefix_sums(yc[:, None])[:, 0] * dt,
                         jnp.zeros((nblocks * blk - n - 1 + 2 * mmax,), y.dtype)])
    mc = jnp.clip(m, 1, mmax)  # larger m are NaN below; clipped only to stay in bounds
    count = n_valid + 1 - 2 * m

    def block(acc, start):
        window = lambda off: jax.lax.dynamic_slice(x, (start + off,), (blk,))  # noqa: E731
        d = jax.vmap(window)(2 * mc) - 2.0 * jax.vmap(window)(mc) + window(0)[None, :]
        i = start + jax.lax.broadcasted_iota(count.dtype, (k, blk), 1)
        return acc + jnp.sum(jnp.where(i < count[:, None], d * d, 0.0), axis=1), None

    s, _ = jax.lax.scan(block, jnp.zeros((k,), y.dtype), jnp.arange(nblocks) * blk)
    good = (count > 1) & (m * stop_ratio <= n_valid) & (m >= 1)
    adev = jnp.sqrt(s / (2.0 * jnp.maximum(count, 1))) / (m * dt)
    return jnp.where(good, adev, jnp.nan), count


#: :func:`oadev`'s XLA options, here and where its body is compiled for a batch's size
#: (``diagnose``): XLA's loop emitters (:data:`~diffgyro._xla_options.FAST_COMPILE`): the
#: same sums bit for bit, run as fast, and compiled in about two thirds of the fusion
#: emitters' time (benchmarks/README.md, noise identification).
OADEV_OPTIONS = FAST_COMPILE


@filter_jit(compiler_options=OADEV_OPTIONS)  # (kept traced on disk under the command line)
def oadev(
    y: Float[Array, "... n"],
    dt: Float[Array, "..."] | float,
    m: Int[Array, " k"],
    n_valid: Int[Array, "..."] | None = None,
    stop_ratio: int = STOP_RATIO,
) -> tuple[Float[Array, "... k"], Int[Array, "... k"]]:
    """Overlapping Allan deviation at ``τ = m·dt`` for every leading index of ``y``.

    ``n_valid`` (default: all) counts the real samples of each padded series;
    ``dt`` broadcasts against the leading axes. Returns (adev, count): count is
    the number of overlapping second differences, N + 1 − 2m. Entries with
    fewer than 2 terms or ``m > n_valid / stop_ratio`` are NaN.

    **Arguments:**

    - ``y``: the rates (..., n).
    - ``dt``: the sample interval, s.
    - ``m``: the cluster sizes (k,).
    - ``n_valid``: the real samples of each padded series (default: all).
    - ``stop_ratio``: the longest cluster is ``n_valid / stop_ratio`` samples.
    """
    y = jnp.asarray(y)
    lead = y.shape[:-1]
    n = y.shape[-1]
    nv = jnp.broadcast_to(jnp.asarray(n if n_valid is None else n_valid), lead)
    dtb = jnp.broadcast_to(jnp.asarray(dt, y.dtype), lead)
    m = jnp.asarray(m)
    flat = (y.reshape(-1, n), nv.reshape(-1), dtb.reshape(-1))
    cpu = jax.default_backend() == "cpu"
    chunk, terms = ((_CHUNK_SAMPLES, _BLOCK_TERMS) if cpu
                    else (_ACCEL_CHUNK_SAMPLES, _ACCEL_BLOCK_TERMS))
    series = flat[0].shape[0]
    batch = max(1, min(series, chunk // max(n, 1)))
    f = lambda yy, nn, dd: _oadev_one(yy, nn, dd, m, stop_ratio, batch, terms,  # noqa: E731
                                      n_valid is not None)
    # the same steps in batches of one size: a remainder would be a second copy of the loop
    # in the program, compiled again. The blocks stay those of ``batch``, so every series'
    # sums are the same bit for bit; the last batch is filled with copies of the first
    # series, dropped
    steps = -(-series // batch)
    even = -(-series // steps)
    fill = steps * even - series
    if fill:
        flat = tuple(jnp.concatenate([a, jnp.repeat(a[:1], fill, axis=0)]) for a in flat)
    # batch_size=1 would copy the whole input into the loop state; a plain map does not
    adev, count = jax.lax.map(lambda a: f(*a), flat, batch_size=even if even > 1 else None)
    return adev[:series].reshape(*lead, -1), count[:series].reshape(*lead, -1)


# --- non-overlapping and modified deviations (NIST SP 1065 §5.2.2, §5.2.5) ------------


def _phase(y: np.ndarray, dt: float) -> np.ndarray:
    """The phase (angle) ``x = dt·[0, cumsum(y − mean y)]`` of a rate series (n + 1 points)."""
    y = np.asarray(y, dtype=np.float64)
    yc = y - y.mean(axis=-1, keepdims=True)  # the deviations ignore the mean; x stays small
    zero = np.zeros(y.shape[:-1] + (1,))
    return np.concatenate([zero, np.cumsum(yc, axis=-1) * dt], axis=-1)


def adev_nonoverlapping(y: Float[np.ndarray, "... n"], dt: float,
                        m: Int[np.ndarray, " k"]) -> Float[np.ndarray, "... k"]:
    """Non-overlapping Allan deviation of ``y`` (..., n) at τ = m·dt; NaN where K < 1::

        σ²(τ) = 1 / (2 τ² K) · Σ_j (x[(j+2)m] − 2 x[(j+1)m] + x[jm])²,  K = ⌊n/m⌋ − 1

    **Arguments:**

    - ``y``: the rates (..., n).
    - ``dt``: the sample interval, s.
    - ``m``: the cluster sizes (k,).
    """
    x = _phase(y, dt)
    n = x.shape[-1] - 1
    out = np.full(x.shape[:-1] + (len(m),), np.nan)
    for j, mj in enumerate(np.asarray(m, dtype=np.int64)):
        k = n // mj - 1
        if mj < 1 or k < 1:
            continue
        xd = x[..., : (k + 2) * mj : mj]  # x[0], x[m], ..., x[(K+1)m]
        d = xd[..., 2:] - 2.0 * xd[..., 1:-1] + xd[..., :-2]
        out[..., j] = np.sqrt(np.sum(d * d, axis=-1) / (2.0 * k)) / (mj * dt)
    return out


def mdev(y: Float[np.ndarray, "... n"], dt: float,
         m: Int[np.ndarray, " k"]) -> Float[np.ndarray, "... k"]:
    """Modified Allan deviation of ``y`` (..., n) at τ = m·dt; NaN where N − 3m + 1 < 1::

        Mod σ²(τ) = 1 / (2 m² τ² (N − 3m + 1)) · Σ_j (Σ_{i=j}^{j+m−1} x[i+2m] − 2 x[i+m] + x[i])²

    with N = n + 1 phase points.

    **Arguments:**

    - ``y``: the rates (..., n).
    - ``dt``: the sample interval, s.
    - ``m``: the cluster sizes (k,).
    """
    x = _phase(y, dt)
    big_n = x.shape[-1]
    out = np.full(x.shape[:-1] + (len(m),), np.nan)
    for j, mj in enumerate(np.asarray(m, dtype=np.int64)):
        count = big_n - 3 * mj + 1
        if mj < 1 or count < 1:
            continue
        d = x[..., 2 * mj:] - 2.0 * x[..., mj:-mj] + x[..., : big_n - 2 * mj]
        c = np.concatenate([np.zeros(d.shape[:-1] + (1,)), np.cumsum(d, axis=-1)], axis=-1)
        s = c[..., mj:] - c[..., :-mj]  # the m-term window sums, N − 3m + 1 of them
        out[..., j] = np.sqrt(np.sum(s * s, axis=-1) / (2.0 * count)) / (mj * mj * dt)
    return out


# --- equivalent degrees of freedom and chi-square intervals -----------------------------


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


# --- log-log slope, regions and read-outs ------------------------------------------------


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


def _readouts_lines(tau, adev, edf, slope, tol, tol_flat, tol_rrw):
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


def _readouts_fit(tau, adev, edf, dominance, evidence):
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


class AllanResult(eqx.Module):
    """Allan curves of many series, with intervals and read-outs.

    Shapes: ``tau`` (..., k) in seconds; ``adev``, ``lo``, ``hi``, ``edf``,
    ``slope`` (..., k) in rad/s (slope dimensionless); read-outs (...,).
    For a Batch the leading axes are (devices, 3 axes).
    """

    m: Int[Array, " k"]
    tau: Float[Array, "... k"]
    adev: Float[Array, "... k"]
    lo: Float[Array, "... k"]
    hi: Float[Array, "... k"]
    edf: Float[Array, "... k"]
    slope: Float[Array, "... k"]
    readouts: Readouts


@eqx.filter_jit
def _allan_core(y, n_valid, dt, m, ci, tol, tol_flat, tol_rrw, dominance, evidence, half, stop_ratio,
                method):
    adev, count = oadev(y, dt, m, n_valid, stop_ratio)
    lead = adev.shape[:-1]
    tau = jnp.broadcast_to(jnp.asarray(dt)[..., None], lead + (1,)) * m
    n_phase = jnp.broadcast_to(jnp.asarray(n_valid)[..., None], adev.shape) + 1
    ok = jnp.isfinite(adev) & (adev > 0)
    la = jnp.log(jnp.where(ok, adev, 1.0))
    lt = jnp.log(tau)
    # First pass: slope with white-FM weights, to choose each τ's noise type for the EDF.
    edf0 = jnp.where(ok, edf_simple(n_phase, m, 0.0), 0.0)
    slope0 = jax.vmap(lambda a, b, c: log_slope(a, b, c, half))(
        lt.reshape(-1, lt.shape[-1]), la.reshape(-1, la.shape[-1]), edf0.reshape(-1, edf0.shape[-1])
    ).reshape(adev.shape)
    alpha = alpha_from_slope(jnp.where(jnp.isfinite(slope0), slope0, -0.5))
    edf = jnp.where(ok, edf_simple(n_phase, m, alpha), jnp.nan)
    p_lo = 0.5 * (1.0 - ci)
    nu = jnp.where(ok, edf, 1.0)
    lo = adev * jnp.sqrt(nu / chi2_ppf(1.0 - p_lo, nu))
    hi = adev * jnp.sqrt(nu / chi2_ppf(p_lo, nu))
    lo = jnp.where(ok, lo, jnp.nan)
    hi = jnp.where(ok, hi, jnp.nan)
    k = adev.shape[-1]
    flat = lambda a: a.reshape(-1, k)  # noqa: E731
    weight = jnp.where(ok, edf, 0.0)
    slope = jax.vmap(lambda a, b, c: log_slope(a, b, c, half))(flat(lt), flat(la), flat(weight))
    if method == "lines":
        ro = jax.vmap(lambda t, a, e, s: _readouts_lines(t, a, e, s, tol, tol_flat, tol_rrw))(
            flat(tau), flat(adev), flat(weight), slope)
    else:
        ro = jax.vmap(lambda t, a, e: _readouts_fit(t, a, e, dominance, evidence))(
            flat(tau), flat(adev), flat(weight))
    ro = jax.tree_util.tree_map(lambda a: a.reshape(*lead, *a.shape[1:]), ro)
    slope = jnp.where(ok, slope.reshape(adev.shape), jnp.nan)
    return AllanResult(m=m, tau=tau, adev=adev, lo=lo, hi=hi, edf=edf, slope=slope, readouts=ro)


def allan(
    y: Float[Array, "... n"],
    dt: Float[Array, "..."] | float,
    m: Int[Array, " k"] | None = None,
    n_valid: Int[Array, "..."] | None = None,
    *,
    ci: float = ONE_SIGMA,
    method: str = "fit",
    dominance: float = 0.5,
    evidence: float = 25.0,
    tol: float = 0.1,
    tol_flat: float = 0.15,
    tol_rrw: float = 0.15,
    half: int = 3,
    stop_ratio: int = STOP_RATIO,
    per_decade: int = 10,
) -> AllanResult:
    """Allan curves, confidence intervals (probability ``ci``) and read-outs of ``y`` (..., n).

    ``dt`` is the sample interval in seconds (broadcast over the leading axes);
    ``m`` the cluster sizes (default :func:`default_m` of the longest series).
    ``method="fit"`` reads the lines from a non-negative fit of the four
    noise terms to the whole curve (a term is reported where it carries at
    least ``dominance`` of the variance at some τ); ``method="lines"`` fits
    each fixed-slope line alone where the local slope (window ±``half``
    points) is within ``tol`` (−½), ``tol_flat`` (0) or ``tol_rrw`` (+½).

    **Arguments:**

    - ``y``: the rates (..., n), rad/s.
    - ``dt``: the sample interval, s (broadcast over the leading axes).
    - ``m``: the cluster sizes (default: :func:`default_m` of the longest series).
    - ``n_valid``: the real samples of each padded series (default: all n).
    - ``ci``: the confidence intervals' probability.
    - ``method``: ``"fit"`` or ``"lines"``, as above.
    - ``dominance``: the share of the variance at some τ a term must carry to be read out
      (``fit``).
    - ``evidence``: how much worse (χ²) the fit without a term must be for the term to be
      read out (``fit``).
    - ``tol``: the local slope's tolerance around −½ (``lines``).
    - ``tol_flat``: its tolerance around 0 (``lines``).
    - ``tol_rrw``: its tolerance around +½ (``lines``).
    - ``half``: the local slope's window, ± points.
    - ``stop_ratio``: the longest cluster is ``n / stop_ratio`` samples.
    - ``per_decade``: cluster sizes per decade of the default ``m``.
    """
    if method not in ("fit", "lines"):
        raise ValueError(f"unknown read-out method {method!r} (use 'fit' or 'lines')")
    y = jnp.asarray(y) if isinstance(y, jax.Array) else jax.device_put(np.asarray(y))
    lead = y.shape[:-1]
    n = y.shape[-1]
    nv = _on_device(np.int64(n) if n_valid is None else n_valid, None, lead)
    if m is None:
        m = default_m(int(np.max(np.asarray(nv))) if nv.size else n, per_decade, stop_ratio)
    m = m if isinstance(m, jax.Array) else jax.device_put(np.asarray(m, dtype=np.int64))
    dtb = _on_device(dt, y.dtype, lead)
    f = lambda v: _on_device(v, y.dtype)  # noqa: E731  (arrays: changing them does not recompile)
    return _allan_core(y, nv, dtb, m, f(ci), f(tol), f(tol_flat), f(tol_rrw), f(dominance),
                       f(evidence), half, stop_ratio, method)


def _on_device(x, dtype, shape=None) -> jax.Array:
    """``x`` as a JAX array of ``dtype`` (None: its own), broadcast to ``shape``.

    Host values are cast and broadcast by numpy and sent as they are: the same operations
    on a JAX array outside a compiled program would each compile a small program of
    their own (a cold command pays its trace, compilation and cache write). JAX arrays
    and tracers go through ``jax.numpy``."""
    if isinstance(x, jax.Array):
        x = jnp.asarray(x, dtype)
        return x if shape is None else jnp.broadcast_to(x, shape)
    x = np.asarray(x, dtype)
    return jax.device_put(x if shape is None else np.broadcast_to(x, shape))


def sample_interval(t: np.ndarray, n_valid: int | None = None) -> float:
    """Median spacing of the valid time stamps (seconds).

    **Arguments:**

    - ``t``: time stamps (n,), s.
    - ``n_valid``: the valid samples (default: all).
    """
    t = np.asarray(t, dtype=np.float64)
    if n_valid is not None:
        t = t[: int(n_valid)]
    if t.shape[0] < 2:
        return 1.0
    return float(np.median(np.diff(t)))


def sample_intervals(batch) -> np.ndarray:
    """Each device's sample interval (s): the median spacing of its valid time stamps.

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch`.
    """
    nv = np.asarray(batch.n_valid, dtype=np.int64)
    return np.array([sample_interval(batch.t[i], nv[i]) for i in range(batch.n_devices)])


def cluster_sizes(taus, dt: float, rtol: float = 1e-6) -> np.ndarray:
    """Cluster sizes ``m = τ / dt`` of the requested τ (s), as integers.

    Raises ValueError naming the first τ that is not a whole number (≥ 1) of
    sample intervals within ``rtol``: the deviation is only defined there.

    **Arguments:**

    - ``taus``: the requested τ, s.
    - ``dt``: the sample interval, s.
    - ``rtol``: how close to a whole number of intervals each τ must be.
    """
    taus = np.asarray(taus, dtype=np.float64)
    m = np.round(taus / dt)
    for tau, mi in zip(taus, m):
        if not (mi >= 1 and abs(tau - mi * dt) <= rtol * max(tau, dt)):
            raise ValueError(f"τ = {tau:g} s is not a whole number of sample intervals "
                             f"(dt = {dt:g} s)")
    return m.astype(np.int64)


def allan_batch(batch, m=None, **options) -> AllanResult:
    """Allan curves of every device and gyro axis of a :class:`~diffgyro.data.Batch`.

    Leading axes of the result: (devices, 3). Each device's sample interval is
    the median spacing of its time stamps; rates are taken as recorded (rad/s).

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch`.
    - ``m``: the cluster sizes (default: from the longest device).
    - ``**options``: options of :func:`allan`.
    """
    release_compiled_if_crowded(interval=1.0)  # before this call compiles its programs
    gyro = np.asarray(batch.gyro, dtype=np.float64)
    y = np.moveaxis(gyro, -1, 1)  # (d, 3, n)
    nv = np.asarray(batch.n_valid, dtype=np.int64)
    dt = sample_intervals(batch)
    if m is None:
        m = default_m(int(nv.max()), options.pop("per_decade", 10),
                      options.get("stop_ratio", STOP_RATIO))
    return allan(y, dt[:, None], m, nv[:, None].repeat(3, axis=1), **options)


def allan_at_taus(batch, taus, **options) -> list[tuple[np.ndarray, AllanResult]]:
    """Allan curves at exactly the requested τ (s) for every device of ``batch``.

    Devices sampled at different rates need different cluster sizes for the
    same τ, so they are computed in groups of equal ``m``: returns
    ``[(device indices, AllanResult of those devices), ...]``. Raises
    :class:`~diffgyro.errors.DataError` (naming file and device) where a τ is
    not a whole number of its sample intervals; a τ longer than
    ``n / stop_ratio`` is NaN as usual.

    **Arguments:**

    - ``batch``: the :class:`~diffgyro.data.Batch`.
    - ``taus``: the cluster times, s.
    - ``**options``: options of :func:`allan`.
    """

    dt = sample_intervals(batch)
    ms = []
    for i, dev in enumerate(batch.devices):
        try:
            ms.append(tuple(cluster_sizes(taus, dt[i])))
        except ValueError as err:
            raise DataError(f"requested {err}", device=str(dev),
                            file=batch.sources[i] if batch.sources else None) from None
    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(ms):
        groups.setdefault(m, []).append(i)
    return [(np.array(idx), allan_batch(batch.select(idx), np.array(m, dtype=np.int64), **options))
            for m, idx in groups.items()]


# --- output: JSON and figure ---------------------------------------------------------------


def to_json(result: AllanResult, devices, axes=("gx", "gy", "gz")) -> dict:
    """The ``allan --json`` object (NaN becomes null, and the axis' ``missing``
    says why; τ only where defined).

    **Arguments:**

    - ``result``: the :class:`AllanResult` (leading axes: devices, axes).
    - ``devices``: the devices' names.
    - ``axes``: the axes' labels.
    """
    tau = np.asarray(result.tau)
    adev = np.asarray(result.adev)
    ro = result.readouts
    arw, bi, rrw = (np.asarray(v) for v in (ro.arw, ro.bias_instability, ro.rrw))
    out = []
    for d, dev in enumerate(devices):
        ax = {}
        for a, name in enumerate(axes):
            keep = np.isfinite(adev[d, a])
            ax[name] = {
                "tau": [float(v) for v in tau[d, a][keep]],
                "adev": [float(v) for v in adev[d, a][keep]],
                "arw": number(arw[d, a]),
                "bias_instability": number(bi[d, a]),
                "rrw": number(rrw[d, a]),
            }
            missing = {k: _MISSING[k] if keep.any() else "no τ with a defined Allan deviation "
                       "(too few valid samples)" for k in _MISSING if ax[name][k] is None}
            if missing:  # why a read-out is null, in plain words
                ax[name]["missing"] = missing
        out.append({"device": dev, "axes": ax})
    return {"devices": out}


#: Why a read-out is null (the curve does not show its term; see the module notes).
_MISSING = {
    "arw": "the curve shows no white-noise (-1/2 slope) region at the measured τ",
    "bias_instability": "the curve shows no flat (slope 0) floor at the measured τ",
    "rrw": "the curve shows no rate-random-walk (+1/2 slope) region at the measured τ "
           "(a longer static recording may)",
}


def plot_allan(result: AllanResult, device: int = 0, axes=("gx", "gy", "gz"), ax=None, title=None):
    """Log-log Allan deviation of one device's axes with CIs, the −½, 0, +½ lines and read-outs.

    **Arguments:**

    - ``result``: the :class:`AllanResult`.
    - ``device``: the device's index.
    - ``axes``: the axes' labels.
    - ``ax``: a matplotlib axes to draw on (default: a new figure).
    - ``title``: the figure's title.
    """
    import matplotlib

    if ax is None:

        if "matplotlib.pyplot" not in sys.modules:  # a notebook keeps its own backend
            matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(7.5, 5.0))
    else:
        fig = ax.figure
    tau = np.asarray(result.tau)[device]
    adev = np.asarray(result.adev)[device]
    lo = np.asarray(result.lo)[device]
    hi = np.asarray(result.hi)[device]
    ro = result.readouts
    colors = ("tab:blue", "tab:orange", "tab:green")
    for a, name in enumerate(axes):
        keep = np.isfinite(adev[a])
        if not keep.any():
            continue
        t, s = tau[a][keep], adev[a][keep]
        c = colors[a % 3]
        ax.fill_between(t, lo[a][keep], hi[a][keep], color=c, alpha=0.15, lw=0)
        arw = float(ro.arw[device, a])
        bi = float(ro.bias_instability[device, a])
        rrw = float(ro.rrw[device, a])
        label = (f"{name}: ARW {_fmt(arw)} rad/s/√Hz, BI {_fmt(bi)} rad/s, "
                 f"RRW {_fmt(rrw)} rad/s²/√Hz")
        ax.loglog(t, s, "o-", ms=2.5, lw=1.0, color=c, label=label)
        tt = np.array([t[0], t[-1]])
        if math.isfinite(arw):
            ax.loglog(tt, arw / np.sqrt(tt), "--", color=c, lw=0.8)
            ax.plot([1.0], [arw], "s", color=c, mfc="none")
        if math.isfinite(bi):
            ax.loglog(tt, np.full(2, bi * FLICKER_FACTOR), ":", color=c, lw=0.8)
        if math.isfinite(rrw):
            ax.loglog(tt, rrw * np.sqrt(tt / 3.0), "-.", color=c, lw=0.8)
            ax.plot([3.0], [rrw], "^", color=c, mfc="none")
    ax.set_xlabel("τ (s)")
    ax.set_ylabel("Allan deviation (rad/s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    ax.set_title(title or "Overlapping Allan deviation (−½: ARW at 1 s, 0: bias instability, +½: RRW at 3 s)",
                 fontsize=8)
    return fig


def _fmt(x: float) -> str:
    return "n/a" if not math.isfinite(x) else f"{x:.3g}"
