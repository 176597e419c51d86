"""Allan curves with intervals and read-outs: :func:`allan` on arrays, :func:`allan_batch`
and :func:`allan_at_taus` on a :class:`~diffgyro.data.Batch`."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._jit import release_compiled_if_crowded
from ..errors import DataError
from ._intervals import ONE_SIGMA, alpha_from_slope, chi2_ppf, edf_simple
from ._oadev import STOP_RATIO, default_m, oadev
from ._readouts import Readouts, log_slope, readouts_fit, readouts_lines


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
        ro = jax.vmap(lambda t, a, e, s: readouts_lines(t, a, e, s, tol, tol_flat, tol_rrw))(
            flat(tau), flat(adev), flat(weight), slope)
    else:
        ro = jax.vmap(lambda t, a, e: readouts_fit(t, a, e, dominance, evidence))(
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
