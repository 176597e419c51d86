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

Confidence intervals are chi-square intervals (SP 1065 eq. 45) with the
equivalent degrees of freedom of SP 1065 Table 5 ("simple" EDF) for the noise
type the curve shows at that τ: the local log-log slope picks white phase
(≤ −3/4), white FM / angle random walk (−1/2), flicker FM / bias instability
(0) or random-walk FM / rate random walk (+1/2).

Read-outs (IEEE Std 952 conventions), units stated:

* ``arw`` (rad/s/√Hz = rad/√s): the line of slope −1/2 fitted (in log-log,
  slope fixed, weighted by EDF) over the largest contiguous run of τ whose
  local slope lies within ``tol`` of −1/2, read at τ = 1 s.
* ``bias_instability`` (rad/s): the minimum of the curve divided by
  √(2 ln 2 / π) ≈ 0.664, reported only where the curve is flat there (local
  slope within ``tol_flat`` of 0 and the minimum not at either end).
* ``rrw`` (rad/s²/√Hz = rad/s/√s): the line of slope +1/2 fitted over the
  largest run whose local slope lies within ``tol_rrw`` of +1/2, read at
  τ = 3 s.

A read-out whose region does not exist is NaN (``None`` in JSON): no number is
invented for a term the data do not show.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import gammainc, gammaln
from jaxtyping import Array, Float, Int

#: Bias-instability factor: the flicker floor of ADEV is sqrt(2 ln 2 / π)·B.
FLICKER_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)
#: Two-sided probability mass of a one-sigma interval.
ONE_SIGMA = math.erf(1.0 / math.sqrt(2.0))
#: Stable32's stop ratio for overlapping ADEV: largest m is N / 4.
STOP_RATIO = 4


def default_m(n: int, per_decade: int = 10, stop_ratio: int = STOP_RATIO) -> np.ndarray:
    """Cluster sizes 1 .. n // stop_ratio, about ``per_decade`` per decade (integers, unique)."""
    top = max(1, int(n) // int(stop_ratio))
    k = int(math.floor(per_decade * math.log10(top))) + 1
    m = np.unique(np.round(np.logspace(0.0, math.log10(top), max(k, 1))).astype(np.int64))
    return m[m >= 1]


def _oadev_one(y, n_valid, dt, m, stop_ratio):
    """Overlapping ADEV of one padded series; returns (adev, count) per m (NaN if too few)."""
    n = y.shape[0]
    idx = jnp.arange(n)
    valid = idx < n_valid
    mean = jnp.sum(jnp.where(valid, y, 0.0)) / jnp.maximum(n_valid, 1)
    yc = jnp.where(valid, y - mean, 0.0)
    x = jnp.concatenate([jnp.zeros((1,), y.dtype), jnp.cumsum(yc)]) * dt  # phase, n+1
    j = jnp.arange(n + 1)

    def one(mi):
        count = n_valid + 1 - 2 * mi
        ok = j < count
        d = x[jnp.clip(j + 2 * mi, 0, n)] - 2.0 * x[jnp.clip(j + mi, 0, n)] + x
        s = jnp.sum(jnp.where(ok, d * d, 0.0))
        good = (count > 1) & (mi * stop_ratio <= n_valid) & (mi >= 1)
        adev = jnp.sqrt(s / (2.0 * jnp.maximum(count, 1))) / (mi * dt)
        return jnp.where(good, adev, jnp.nan), count

    return jax.lax.map(one, m)


@eqx.filter_jit
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
    """
    y = jnp.asarray(y)
    lead = y.shape[:-1]
    n = y.shape[-1]
    nv = jnp.broadcast_to(jnp.asarray(n if n_valid is None else n_valid), lead)
    dtb = jnp.broadcast_to(jnp.asarray(dt, y.dtype), lead)
    m = jnp.asarray(m)
    f = lambda yy, nn, dd: _oadev_one(yy, nn, dd, m, stop_ratio)  # noqa: E731
    flat = (y.reshape(-1, n), nv.reshape(-1), dtb.reshape(-1))
    adev, count = jax.vmap(f)(*flat)
    return adev.reshape(*lead, -1), count.reshape(*lead, -1)


# --- equivalent degrees of freedom and chi-square intervals -----------------------------


def edf_simple(n_phase, m, alpha):
    """SP 1065 Table 5 EDF of overlapping ADEV for noise exponent ``alpha``.

    ``alpha``: +2 white PM, 0 white FM, −1 flicker FM, −2 random-walk FM
    (flicker PM is read as white PM here). ``n_phase`` = samples + 1.
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
    """Noise exponent (FM convention) from the ADEV log-log slope: −1 → +2, −½ → 0, 0 → −1, ½ → −2."""
    a = jnp.clip(jnp.round(-2.0 * slope - 1.0), -2.0, 0.0)
    return jnp.where(slope <= -0.75, 2.0, a)


def chi2_ppf(p, nu):
    """Chi-square quantile: Wilson–Hilferty start, then Newton steps on log x (traceable)."""
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


# --- local slope, regions and read-outs ---------------------------------------------------


def local_slope(log_tau, log_adev, weight, half: int = 3):
    """Slope of log σ against log τ by weighted least squares over ±``half`` points."""
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
    """Noise terms read from one or many Allan curves (leading axes as the curves')."""

    arw: Float[Array, "..."]  # rad/s/√Hz  (σ at τ = 1 s on the −1/2 line)
    bias_instability: Float[Array, "..."]  # rad/s (flat minimum / 0.664)
    rrw: Float[Array, "..."]  # rad/s²/√Hz (σ at τ = 3 s on the +1/2 line)
    tau_min: Float[Array, "..."]  # s, where the flat minimum lies
    arw_region: Float[Array, "... k"]  # 1.0 on the τ used for the −1/2 line
    rrw_region: Float[Array, "... k"]  # 1.0 on the τ used for the +1/2 line


def _readouts_one(tau, adev, edf, slope, tol, tol_flat, tol_rrw):
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
    tau_min = jnp.where(flat, tau[imin], jnp.nan)
    return Readouts(arw=arw, bias_instability=bi, rrw=rrw, tau_min=tau_min,
                    arw_region=arw_reg.astype(tau.dtype), rrw_region=rrw_reg.astype(tau.dtype))


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
def _allan_core(y, n_valid, dt, m, ci, tol, tol_flat, tol_rrw, half, stop_ratio):
    adev, count = oadev(y, dt, m, n_valid, stop_ratio)
    lead = adev.shape[:-1]
    tau = jnp.broadcast_to(jnp.asarray(dt)[..., None], lead + (1,)) * m
    n_phase = jnp.broadcast_to(jnp.asarray(n_valid)[..., None], adev.shape) + 1
    ok = jnp.isfinite(adev) & (adev > 0)
    la = jnp.log(jnp.where(ok, adev, 1.0))
    lt = jnp.log(tau)
    # First pass: slope with white-FM weights, to choose each τ's noise type for the EDF.
    edf0 = jnp.where(ok, edf_simple(n_phase, m, 0.0), 0.0)
    slope0 = jax.vmap(lambda a, b, c: local_slope(a, b, c, half))(
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
    slope = jax.vmap(lambda a, b, c: local_slope(a, b, c, half))(flat(lt), flat(la), flat(weight))
    ro = jax.vmap(lambda t, a, e, s: _readouts_one(t, a, e, s, tol, tol_flat, tol_rrw))(
        flat(tau), flat(adev), flat(weight), slope)
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
    ``tol``, ``tol_flat``, ``tol_rrw`` are how close the local slope must be to
    −1/2, 0, +1/2 for a τ to count in that region; ``half`` is the half-width
    (in points) of the local-slope window.
    """
    y = jnp.asarray(y)
    lead = y.shape[:-1]
    n = y.shape[-1]
    nv = jnp.broadcast_to(jnp.asarray(n if n_valid is None else n_valid), lead)
    if m is None:
        m = default_m(int(np.max(np.asarray(nv))) if nv.size else n, per_decade, stop_ratio)
    m = jnp.asarray(np.asarray(m, dtype=np.int64) if not isinstance(m, jax.Array) else m)
    dtb = jnp.broadcast_to(jnp.asarray(dt, y.dtype), lead)
    return _allan_core(y, nv, dtb, m, jnp.asarray(ci, y.dtype), jnp.asarray(tol, y.dtype),
                       jnp.asarray(tol_flat, y.dtype), jnp.asarray(tol_rrw, y.dtype), half, stop_ratio)


def sample_interval(t: np.ndarray, n_valid: int | None = None) -> float:
    """Median spacing of the valid time stamps (seconds)."""
    t = np.asarray(t, dtype=np.float64)
    if n_valid is not None:
        t = t[: int(n_valid)]
    if t.shape[0] < 2:
        return 1.0
    return float(np.median(np.diff(t)))


def allan_batch(batch, m=None, **options) -> AllanResult:
    """Allan curves of every device and gyro axis of a :class:`~diffgyro.data.Batch`.

    Leading axes of the result: (devices, 3). Each device's sample interval is
    the median spacing of its time stamps; rates are taken as recorded (rad/s).
    """
    gyro = np.asarray(batch.gyro, dtype=np.float64)
    y = np.moveaxis(gyro, -1, 1)  # (d, 3, n)
    nv = np.asarray(batch.n_valid, dtype=np.int64)
    dt = np.array([sample_interval(batch.t[i], nv[i]) for i in range(batch.n_devices)])
    if m is None:
        m = default_m(int(nv.max()), options.pop("per_decade", 10),
                      options.get("stop_ratio", STOP_RATIO))
    return allan(y, dt[:, None], m, nv[:, None].repeat(3, axis=1), **options)


# --- output: JSON and figure ---------------------------------------------------------------


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def to_json(result: AllanResult, devices, axes=("gx", "gy", "gz")) -> dict:
    """The DESIGN.md §4 ``allan --json`` object (NaN becomes null; τ only where defined)."""
    tau = np.asarray(result.tau)
    adev = np.asarray(result.adev)
    ro = result.readouts
    out = []
    for d, dev in enumerate(devices):
        ax = {}
        for a, name in enumerate(axes):
            keep = np.isfinite(adev[d, a])
            ax[name] = {
                "tau": [float(v) for v in tau[d, a][keep]],
                "adev": [float(v) for v in adev[d, a][keep]],
                "arw": _num(ro.arw[d, a]),
                "bias_instability": _num(ro.bias_instability[d, a]),
                "rrw": _num(ro.rrw[d, a]),
            }
        out.append({"device": dev, "axes": ax})
    return {"devices": out}


def plot_allan(result: AllanResult, device: int = 0, axes=("gx", "gy", "gz"), ax=None, title=None):
    """Log-log Allan deviation of one device's axes with CIs, the −½, 0, +½ lines and read-outs."""
    import matplotlib

    if ax is None:
        matplotlib.use("Agg", force=False)
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
